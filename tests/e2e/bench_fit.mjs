// Browser benchmark of the photo → body fit (issue #20): the same photo and schedule fitted on
// the CPU (burn NdArray in wasm, the app's default) and on the page's WebGPU device (burn
// wgpu), in one run; prints ms per Adam step of each and their ratio.
//
//   cargo xtask serve            # another shell; or any server of dist/
//   cd tests/e2e && node bench_fit.mjs [iterations, default 5,5,3]
//
// GETAVATAR_URL (default http://127.0.0.1:8080/) and GETAVATAR_CHROMIUM as for app.e2e.mjs.
// Headless Chromium runs WebGPU on SwiftShader (a CPU); on a real GPU the WebGPU figure is
// the one to re-measure.

import { chromium } from 'playwright-core';
import { PNG } from 'pngjs';
import fs from 'node:fs';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const iterations = (process.argv[2] ?? '5,5,3').split(',').map(Number);
const browser = await chromium.launch({
  executablePath: process.env.GETAVATAR_CHROMIUM ?? '/usr/bin/chromium',
  headless: true,
  args: ['--no-sandbox', '--enable-unsafe-webgpu', '--use-angle=swiftshader', '--enable-features=Vulkan',
    '--use-vulkan=swiftshader', '--disable-quic'],
});
const page = await (await browser.newContext({ viewport: { width: 1280, height: 800 } })).newPage();
const status = () => page.evaluate(() => (window.getavatar ? window.getavatar.status() : null)).catch(() => null);
async function waitFor(pred, what, timeout = 900000) {
  const t0 = Date.now();
  for (;;) {
    const s = await status();
    if (s && pred(s)) return s;
    if (Date.now() - t0 > timeout) throw new Error(`timed out waiting for ${what}`);
    await page.waitForTimeout(250);
  }
}
await page.goto(url);
const st = await waitFor((s) => s.ready, 'the app');
// The e2e photo over grey, as a blob URL the app fetches.
const render = PNG.sync.read(fs.readFileSync(new URL('./fixtures/kick_clothed.png', import.meta.url)));
for (let k = 0; k < render.data.length; k += 4) {
  const a = render.data[k + 3] / 255;
  for (let c = 0; c < 3; c++) render.data[k + c] = Math.round(render.data[k + c] * a + 120 * (1 - a));
  render.data[k + 3] = 255;
}
const bytes = [...PNG.sync.write(render)];
async function fit(device, its) {
  const before = (await status()).photo.fits;
  const err = await page.evaluate(([b, device, its]) => window.getavatar.command({
    photo: { url: URL.createObjectURL(new Blob([new Uint8Array(b)], { type: 'image/png' })), device, iterations: its },
  }), [bytes, device, its]);
  if (err) throw new Error(err);
  const p = (await waitFor((s) => s.photo.fits > before || s.photo.state === 'failed', `the ${device} fit`)).photo;
  if (p.state !== 'fitted') throw new Error(`${device}: ${p.message}`);
  return p;
}
const rows = [];
for (const device of ['cpu', 'webgpu']) {
  await fit(device, [1, 1, 1]); // warm-up: shaders, first allocations
  const p = await fit(device, iterations);
  rows.push({ device, steps: p.steps_total, ms: p.fit_ms, perStep: p.fit_ms / p.steps_total, residual: p.relative_to_height });
}
console.log(`photo → body fit in the browser (${st.adapter}, ${st.backend}), iterations ${iterations.join('+')}, 512² photo:`);
console.log('| device | steps | total ms | ms/step | keypoint residual |');
console.log('|---|---|---|---|---|');
for (const r of rows) console.log(`| ${r.device} | ${r.steps} | ${r.ms.toFixed(0)} | ${r.perStep.toFixed(1)} | ${(100 * r.residual).toFixed(2)} % |`);
console.log(`ratio webgpu/cpu ms per step: ${(rows[1].perStep / rows[0].perStep).toFixed(1)}`);
await browser.close();
