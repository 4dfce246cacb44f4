// Browser benchmark of Generate (a new identity: mapping, synthesis, the posed grid, DMTet,
// normals and colours, rigging) on each device: `cpu` in the reconstruction worker on burn's
// NdArray, `webgpu` on the page's WebGPU device (`auto`, the app's default, takes the first on
// a software adapter). Per device: the first generation (a fresh worker builds its body
// context and posed grid then) and the mean of the rest, milliseconds by stage, and the
// devices' ratio, all in one run.
//
//   cargo xtask serve            # another shell; or any server of dist/
//   cd tests/e2e && node bench_generate.mjs [generations per device, default 4] [devices, default cpu,webgpu]
//
// GETAVATAR_URL (default http://127.0.0.1:8080/) and GETAVATAR_CHROMIUM as for app.e2e.mjs.
// Headless Chromium runs WebGPU on SwiftShader (a CPU); on a real GPU the figures are the
// ones to re-measure.

import { appStatus, launchChromium } from './browser.mjs';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const n = Number(process.argv[2] ?? 4);
const devices = (process.argv[3] ?? 'cpu,webgpu').split(',');
const browser = await launchChromium();
const page = await (await browser.newContext({ viewport: { width: 1280, height: 800 } })).newPage();
page.on('console', (m) => {
  if (m.type() === 'error') console.log(`console error: ${m.text()}`);
  if (/^the model: /.test(m.text())) console.log(m.text());
});
const { status, waitFor } = appStatus(page);
await page.goto(url);
const t0 = Date.now();
const st = await waitFor((s) => s.ready && !/loading/.test(s.model), 'the app and its model', 300000);
console.log(`model ready ${((Date.now() - t0) / 1000).toFixed(1)} s after the page loaded: ${st.model}`);

const rows = [];
let seed = 100;
for (const device of devices) {
  for (let i = 0; i < n; i++) {
    const before = (await status()).generations;
    const t = Date.now();
    seed += 1;
    const e = await page.evaluate(([g, device]) => window.getavatar.command({
      generate: { seed_geo: g, seed_tex: g + 1, device },
    }), [seed, device]);
    if (e) throw new Error(e);
    const s = await waitFor((s) => s.generations > before && !s.generating, `generation ${i + 1} on ${device}`, 600000);
    rows.push({ device, i, ms: s.last_generation_ms, wallS: (Date.now() - t) / 1000, on: s.last_generation_on, stages: s.last_generation_stages?.stages ?? [], vertices: s.avatar_vertices });
  }
}
const mean = (xs) => xs.reduce((a, x) => a + x, 0) / Math.max(xs.length, 1);
console.log(`Generate in the browser (page adapter ${st.adapter}, ${st.backend}), ${n} per device:`);
console.log('| device | ran on | first ms | mean of the rest ms | wall s (mean) | vertices |');
console.log('|---|---|---|---|---|---|');
const summary = {};
for (const device of devices) {
  const r = rows.filter((x) => x.device === device);
  const rest = r.slice(1);
  summary[device] = { first: r[0].ms, rest: rest.length ? mean(rest.map((x) => x.ms)) : r[0].ms };
  console.log(`| ${device} | ${r[0].on} | ${r[0].ms.toFixed(0)} | ${summary[device].rest.toFixed(0)} | ${mean(r.map((x) => x.wallS)).toFixed(1)} | ${r.map((x) => x.vertices).join(', ')} |`);
  const last = r[r.length - 1];
  console.log(`  last by stage (ms, host + GPU wait): ${last.stages.map((x) => `${x.stage} ${(x.host_ms + x.gpu_wait_ms).toFixed(0)}`).join(', ')}`);
}
if (summary.cpu && summary.webgpu) {
  console.log(`WebGPU / CPU: first ${(summary.webgpu.first / summary.cpu.first).toFixed(1)}×, the rest ${(summary.webgpu.rest / summary.cpu.rest).toFixed(1)}×`);
}
await browser.close();
