// Browser benchmark of the downloads' texture bake (atlas, texel points, the texture field at
// every covered texel, the image) with its texture-field queries on each device: `cpu` in the
// reconstruction worker on burn's NdArray, `webgpu` on the page's WebGPU device (`auto`, the
// app's default, takes the first on a software adapter). Per avatar both devices bake the same
// generated identity (generated again in between, so nothing is reused) and the two textures
// are compared texel by texel; one unmeasured round first (the worker starts, the page
// compiles its kernels). Prints per device the milliseconds of each bake, the medians and
// their ratio, all in one run.
//
//   cargo xtask serve            # another shell; or any server of dist/
//   cd tests/e2e && node bench_bake.mjs [avatars, default 3] [texture side, default 256] [devices, default webgpu,cpu]
//
// GETAVATAR_URL (default http://127.0.0.1:8080/) and GETAVATAR_CHROMIUM as for app.e2e.mjs.
// Headless Chromium runs WebGPU on SwiftShader (a CPU); on a real GPU re-measure.

import { PNG } from 'pngjs';
import { appStatus, launchChromium } from './browser.mjs';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const count = Number(process.argv[2] ?? 3);
const res = Number(process.argv[3] ?? 256);
const devices = (process.argv[4] ?? 'webgpu,cpu').split(',');
if (!(count >= 1) || ![256, 512, 1024, 2048].includes(res) || devices.some((d) => !['auto', 'cpu', 'webgpu'].includes(d))) {
  console.error('usage: node bench_bake.mjs [avatars ≥ 1] [texture side: 256|512|1024|2048] [devices: auto,cpu,webgpu]');
  process.exit(2);
}
const browser = await launchChromium();
const context = await browser.newContext({ viewport: { width: 1280, height: 800 }, acceptDownloads: true });
const page = await context.newPage();
const warnings = [];
page.on('console', (m) => {
  if (m.type() === 'error') console.log(`console error: ${m.text()}`);
  if (m.type() === 'warning' && /in the worker failed/.test(m.text())) warnings.push(m.text());
});
const { status, waitFor } = appStatus(page, { timeoutMs: 900000 });
const command = async (c) => {
  const err = await page.evaluate((c) => window.getavatar.command(c), c);
  if (err) throw new Error(`${JSON.stringify(c)}: ${err}`);
};
await page.goto(url);
await waitFor((s) => s.ready && s.model && !s.model.startsWith('loading'), 'the app and its model');
await command({ texture_res: res });

async function generate(seedGeo, seedTex) {
  const before = (await status()).generations;
  await command({ generate: { seed_geo: seedGeo, seed_tex: seedTex, device: 'cpu' } });
  await waitFor((s) => s.generations > before && !s.generating, `generation ${seedGeo}/${seedTex}`);
}

/** The baked texture of the avatar shown, with texture-field queries on `device`. */
async function bake(device) {
  await command({ texture_device: device });
  const before = (await status()).motion.bakes;
  const [dl] = await Promise.all([page.waitForEvent('download', { timeout: 900000 }), command({ download: true })]);
  const bytes = new Uint8Array(await (await dl.createReadStream()).toArray().then((c) => Buffer.concat(c)));
  const s = await status();
  if (s.motion.bakes !== before + 1) throw new Error(`no new bake on ${device}`);
  const jsonLen = new DataView(bytes.buffer, bytes.byteOffset).getUint32(12, true);
  const json = JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + jsonLen)));
  const view = json.bufferViews[json.images[0].bufferView];
  const start = 20 + jsonLen + 8 + (view.byteOffset ?? 0);
  const png = PNG.sync.read(Buffer.from(bytes.subarray(start, start + view.byteLength)));
  return { ms: s.motion.last_bake_ms, on: s.motion.last_bake_on, detail: s.motion.last_bake_detail, png };
}

/** Mean and largest difference of two RGBA images' colours, in 8-bit levels. */
function difference(a, b) {
  let sum = 0, max = 0, n = 0;
  for (let i = 0; i < a.data.length; i += 4) {
    for (let c = 0; c < 3; c++) {
      const d = Math.abs(a.data[i + c] - b.data[i + c]);
      sum += d; max = Math.max(max, d); n++;
    }
  }
  return { mean: sum / n, max };
}

const median = (xs) => [...xs].sort((a, b) => a - b)[Math.floor(xs.length / 2)];
const times = Object.fromEntries(devices.map((d) => [d, []]));
for (let k = -1; k < count; k++) {
  const seeds = [31 + 2 * k, 32 + 2 * k];
  const baked = {};
  for (const device of devices) {
    await generate(...seeds);
    baked[device] = await bake(device);
    if (k >= 0) times[device].push(baked[device].ms);
  }
  const line = devices.map((d) => `${d} ${baked[d].ms.toFixed(0)} ms (${baked[d].on}: ${baked[d].detail})`).join(', ');
  let diff = '';
  if (devices.length > 1) {
    const d = difference(baked[devices[0]].png, baked[devices[1]].png);
    diff = `; the textures differ by ${d.mean.toFixed(3)} levels on average, ${d.max} at most`;
  }
  console.log(`${k < 0 ? 'warm-up' : `avatar ${k + 1}`} (seeds ${seeds.join('/')}), ${res}²: ${line}${diff}`);
}
console.log(`\nmedian ${res}² bake: ${devices.map((d) => `${d} ${median(times[d]).toFixed(0)} ms`).join(', ')}`);
if (devices.length > 1) console.log(`${devices[0]}/${devices[1]}: ${(median(times[devices[0]]) / median(times[devices[1]])).toFixed(1)}×`);
if (warnings.length) console.log(`the worker fell back: ${warnings.join('; ')}`);
await browser.close();
