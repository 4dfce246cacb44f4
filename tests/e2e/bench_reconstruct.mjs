// Browser benchmark of the single-image reconstruction: the e2e photo is fitted,
// then reconstructed in the reconstruction worker's own WebGPU device (burn wgpu + autodiff) at each render size;
// prints milliseconds per W+ step and per PTI step, the start (model loading, start choice)
// and the finish (extraction, rigging, projection), and the result's mask IoU / masked PSNR.
//
//   cargo xtask serve            # another shell; or any server of dist/
//   cd tests/e2e && node bench_reconstruct.mjs [sizes, default 64,128] [W+ steps, default 4] [PTI steps, default 3]
//
// GETAVATAR_URL (default http://127.0.0.1:8080/) and GETAVATAR_CHROMIUM as for app.e2e.mjs.
// Headless Chromium runs WebGPU on SwiftShader (a CPU); on a real GPU the figures are the
// ones to re-measure. GETAVATAR_OUT (default out/) receives a screenshot per size.

import { appStatus, greyPhoto, launchChromium } from './browser.mjs';
import fs from 'node:fs';
import path from 'node:path';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const out = process.env.GETAVATAR_OUT ?? 'out';
fs.mkdirSync(out, { recursive: true });
const sizes = (process.argv[2] ?? '64,128').split(',').map(Number);
const steps = Number(process.argv[3] ?? 4);
const ptiSteps = Number(process.argv[4] ?? 3);
const browser = await launchChromium();
const page = await (await browser.newContext({ viewport: { width: 1280, height: 800 } })).newPage();
page.on('console', (m) => { if (m.type() === 'error') console.log(`console error: ${m.text()}`); });
const { status, waitFor } = appStatus(page);
await page.goto(url);
const st = await waitFor((s) => s.ready && !/loading/.test(s.model), 'the app and its model');
// The e2e photo over grey, as a blob URL the app fetches.
const bytes = [...greyPhoto()];
const err = await page.evaluate((b) => window.getavatar.command({
  photo: { url: URL.createObjectURL(new Blob([new Uint8Array(b)], { type: 'image/png' })) },
}), bytes);
if (err) throw new Error(err);
const p = (await waitFor((s) => s.photo.fits > 0 || s.photo.state === 'failed', 'the fit')).photo;
if (p.state !== 'fitted') throw new Error(p.message);

const rows = [];
for (const res of sizes) {
  const before = (await status()).reconstruct.done;
  const t0 = Date.now();
  const e = await page.evaluate(([res, steps, pti]) => window.getavatar.command({
    reconstruct: { res, steps, pti_steps: pti, preview_every: 0 },
  }), [res, steps, ptiSteps]);
  if (e) throw new Error(e);
  const r = (await waitFor((s) => s.reconstruct.done > before || s.reconstruct.state === 'failed', `the ${res}² reconstruction`)).reconstruct;
  if (r.state !== 'done') throw new Error(`${res}²: ${r.message}`);
  rows.push({ res, r, wallS: (Date.now() - t0) / 1000 });
  await page.screenshot({ path: path.join(out, `bench_reconstruct_${res}.png`) });
}
console.log(`reconstruction in the browser (${st.adapter}, ${st.backend}), ${steps} W+ + ${ptiSteps} PTI steps, perceptual term ${rows[0]?.r.perceptual ? 'on' : 'off'}:`);
console.log('| render size | ms per W+ step | ms per PTI step | start (load, choice) s | finish s | total s | mask IoU | masked PSNR |');
console.log('|---|---|---|---|---|---|---|---|');
for (const { res, r, wallS } of rows) {
  console.log(`| ${res}² | ${r.ms_per_latent_step.toFixed(0)} | ${r.ms_per_pivotal_step.toFixed(0)} | ${(r.start_ms / 1000).toFixed(1)} | ${(r.finish_ms / 1000).toFixed(1)} | ${wallS.toFixed(1)} | ${r.mask_iou.toFixed(3)} | ${r.psnr_db.toFixed(2)} dB |`);
}
if (rows.length > 1) {
  const [a, b] = [rows[0], rows[rows.length - 1]];
  console.log(`ratio ${b.res}²/${a.res}² ms per W+ step: ${(b.r.ms_per_latent_step / a.r.ms_per_latent_step).toFixed(2)}`);
}
await browser.close();
