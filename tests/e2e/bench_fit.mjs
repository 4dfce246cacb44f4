// Browser benchmark of the photo → body fit: the same photo and schedule fitted on
// the CPU (burn NdArray in wasm, the app's default) and on the page's WebGPU device (burn
// wgpu), in one run; prints ms per Adam step of each and their ratio.
//
//   cargo xtask serve            # another shell; or any server of dist/
//   cd tests/e2e && node bench_fit.mjs [iterations, default 5,5,3]
//
// GETAVATAR_URL (default http://127.0.0.1:8080/) and GETAVATAR_CHROMIUM as for app.e2e.mjs.
// Headless Chromium runs WebGPU on SwiftShader (a CPU); on a real GPU the WebGPU figure is
// the one to re-measure.

import { appStatus, greyPhoto, launchChromium } from './browser.mjs';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const iterations = (process.argv[2] ?? '5,5,3').split(',').map(Number);
const browser = await launchChromium();
const page = await (await browser.newContext({ viewport: { width: 1280, height: 800 } })).newPage();
const { status, waitFor } = appStatus(page, { timeoutMs: 900000 });
await page.goto(url);
const st = await waitFor((s) => s.ready, 'the app');
// The e2e photo over grey, as a blob URL the app fetches.
const bytes = [...greyPhoto()];
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
