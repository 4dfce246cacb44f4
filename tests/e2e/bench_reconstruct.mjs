// Browser benchmark of the single-image reconstruction: the e2e photo is fitted, then
// reconstructed in the reconstruction worker, from the photo encoder's guess, on each device
// (`cpu`: burn NdArray in the worker's wasm; `webgpu`: the worker's WebGPU device) at each
// render size; prints the time to the first avatar (the encoder's guess on screen),
// milliseconds per W+ step and per PTI step, the start (model loading, the encoder) and the
// finish (extraction, rigging, projection), the result's mask IoU / masked PSNR, and the
// devices' ratio per step.
//
//   cargo xtask serve            # another shell; or any server of dist/
//   cd tests/e2e && node bench_reconstruct.mjs [sizes, default 64,128] [W+ steps, default 4] [PTI steps, default 3] [devices, default cpu,webgpu]
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
const devices = (process.argv[5] ?? 'cpu,webgpu').split(',');
// A figure, or "–" where there is none (the encoder's guess is shown unmeasured before the refit).
const fixed = (x, digits) => (x == null ? '–' : x.toFixed(digits));
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
console.log(`photo fitted: ${p.message}`);

const rows = [];
for (const device of devices) {
  for (const res of sizes) {
    const before = (await status()).reconstruct.done;
    const t0 = Date.now();
    const e = await page.evaluate(([res, steps, pti, device]) => window.getavatar.command({
      reconstruct: { res, steps, pti_steps: pti, preview_every: 0, device },
    }), [res, steps, ptiSteps, device]);
    if (e) throw new Error(e);
    let said = 0;
    const r = (await waitFor((s) => {
      if (Date.now() - said > 30000) {
        said = Date.now();
        console.log(`  ${device} ${res}²: ${s.reconstruct.state} ${s.reconstruct.steps_done}/${s.reconstruct.steps_total} after ${((Date.now() - t0) / 1000).toFixed(0)} s: ${s.reconstruct.message}`);
      }
      return s.reconstruct.done > before || s.reconstruct.state === 'failed';
    }, `the ${res}² reconstruction on ${device}`, 3600000)).reconstruct;
    if (r.state !== 'done') throw new Error(`${device} ${res}²: ${r.message}`);
    rows.push({ device, res, r, wallS: (Date.now() - t0) / 1000 });
    await page.screenshot({ path: path.join(out, `bench_reconstruct_${device}_${res}.png`) });
  }
}
console.log(`reconstruction in the browser (page adapter ${st.adapter}, ${st.backend}), ${steps} W+ + ${ptiSteps} PTI steps from the encoder's guess, perceptual term ${rows[0]?.r.perceptual ? 'on' : 'off'}:`);
console.log('| device | render size | first avatar s | ms per W+ step | ms per PTI step | start (load, encoder) s | finish s | total s | mask IoU first → last | masked PSNR first → last |');
console.log('|---|---|---|---|---|---|---|---|---|---|');
for (const { device, res, r, wallS } of rows) {
  console.log(`| ${device} (${r.device}) | ${res}² | ${(r.first_avatar_ms / 1000).toFixed(1)} | ${r.ms_per_latent_step.toFixed(0)} | ${r.ms_per_pivotal_step.toFixed(0)} | ${(r.start_ms / 1000).toFixed(1)} | ${(r.finish_ms / 1000).toFixed(1)} | ${wallS.toFixed(1)} | ${fixed(r.first_mask_iou, 3)} → ${r.mask_iou.toFixed(3)} | ${fixed(r.first_psnr_db, 2)} → ${r.psnr_db.toFixed(2)} dB |`);
}
for (const res of sizes) {
  const [c, w] = ['cpu', 'webgpu'].map((d) => rows.find((x) => x.device === d && x.res === res));
  if (c && w) {
    console.log(`${res}²: WebGPU / CPU ms per W+ step ${(w.r.ms_per_latent_step / c.r.ms_per_latent_step).toFixed(1)}×, per PTI step ${(w.r.ms_per_pivotal_step / c.r.ms_per_pivotal_step).toFixed(1)}×, first avatar ${(w.r.first_avatar_ms / c.r.first_avatar_ms).toFixed(1)}×`);
  }
}
await browser.close();
