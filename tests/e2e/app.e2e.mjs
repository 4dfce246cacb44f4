// Browser end-to-end test of the GETAvatar web app in headless Chromium (WebGPU on
// SwiftShader). Run by `cargo xtask test`, which builds and serves the app and sets
// GETAVATAR_URL. Screenshots go to GETAVATAR_OUT for a person to look at.
//
// What it checks (each assertion can fail):
//  - the page loads with zero console errors and the app reports a WebGPU adapter;
//  - a frame shows the body: the mask view's foreground bounding box equals the projection
//    of the exported mesh's vertices through the reference camera (fov 49.13°, r = 2.3 m);
//  - the normal view encodes world normals as (n+1)/2 (background = zero vector);
//  - changing the pose changes the silhouette;
//  - the downloaded .glb passes the Khronos glTF-Validator with 0 errors;
//  - Generate runs the generator on WebGPU and shows an avatar at the model's default ψ; a new
//    texture seed changes RGB pixels but not the mask.
//  - Reconstruct from photo: bad files (empty, random bytes, a 1×1 PNG, a 40 MP PNG) each give
//    one message and change nothing; a clothed synthetic subject in an unseen pose
//    (fixtures/kick_clothed.png, `trainer synth-scans --pose kick` + `trainer prepare` at 512²,
//    over grey), opened by clicking "Open photo…" and answering the file chooser: MediaPipe
//    finds the person, the body is fitted in the browser, the person mask's IoU with the
//    photo's alpha ≥ 0.8, the keypoint residual ≤ 3 % of the person's height; Download fit
//    gives fit.json + kp.json; beside a smaller copy of itself at 4.7 MP, two people are
//    counted, the larger is fitted and detection ran at ≤ 4 MP; a re-fit can be cancelled.
//  - Reconstruct: `instant` (the shipped photo encoder's guess, no step) runs in the
//    reconstruction worker (on NdArray there on a software adapter, on its WebGPU device on a
//    hardware one) and gives an avatar whose mask overlaps the photo's person (IoU ≥ 0.75 at
//    the photo's camera); a short reconstruction on the same device lowers the loss (IoU ≥
//    0.6); neither makes a network request or a console error; Cancel after a step (on the
//    worker's WebGPU device) keeps the last preview's state as the avatar; "Save reconstruction" downloads one .safetensors
//    (generator, codes, photo) that "Open reconstruction…" turns back into the same avatar;
//    a broken file is refused.
//  - Motion: the built-in walk scrubbed to two times changes the mask; playing re-poses every
//    frame; the AMASS fixture loads as a clip (resampled), a broken .npz gets one message; the
//    animated .glb (walk + wave) passes the validator with 2 animations and a skin; with the
//    texture at 256² the avatar is baked once and both downloads carry the image;
//    re-posing with the walk playing uploads no mesh and the same bytes per frame for avatar and
//    bare body; their median frame times at 1024² are printed.

import { chromium } from 'playwright-core';
import { PNG } from 'pngjs';
import validator from 'gltf-validator';
import fs from 'node:fs';
import path from 'node:path';
import { maskIou, pixelAt } from './browser.mjs';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const out = process.env.GETAVATAR_OUT ?? 'out';
const executablePath = process.env.GETAVATAR_CHROMIUM ?? '/usr/bin/chromium';
fs.mkdirSync(out, { recursive: true });

let failures = 0;
function check(cond, msg) {
  console.log(`${cond ? 'ok  ' : 'FAIL'} ${msg}`);
  if (!cond) failures++;
}

const browser = await chromium.launch({
  executablePath,
  headless: true,
  args: [
    '--no-sandbox', '--enable-unsafe-webgpu', '--use-angle=swiftshader',
    '--enable-features=Vulkan', '--use-vulkan=swiftshader',
    '--disable-background-networking', '--disable-component-update', '--disable-sync',
    '--no-first-run', '--disable-quic',
  ],
});
const context = await browser.newContext({ viewport: { width: 1280, height: 800 }, deviceScaleFactor: 1, acceptDownloads: true });
const page = await context.newPage();
// The page's clock (performance.now), and the windows of the jobs the e2e bounds:
// [name, from, to, why it is only measured (absent: checked)].
const pageNow = () => page.evaluate(() => performance.now());
const jobs = [];
// Every GPU device the page creates, so the device-loss check can destroy it.
await page.addInitScript(() => {
  // The UI thread's long tasks (> 50 ms), for "no job blocks the UI over 100 ms".
  window.__longTasks = [];
  new PerformanceObserver((list) => {
    for (const e of list.getEntries()) window.__longTasks.push([e.startTime, e.duration]);
  }).observe({ type: 'longtask', buffered: true });
  window.__gpuDevices = [];
  if (navigator.gpu) {
    const requestDevice = GPUAdapter.prototype.requestDevice;
    GPUAdapter.prototype.requestDevice = async function (...args) {
      const d = await requestDevice.apply(this, args);
      window.__gpuDevices.push(d);
      return d;
    };
  }
});
const consoleErrors = [];
page.on('console', (m) => { if (m.type() === 'error') consoleErrors.push(m.text()); });
page.on('pageerror', (e) => consoleErrors.push(`pageerror: ${e.message}`));

const status = () => page.evaluate(() => window.getavatar.status());
async function waitFor(pred, what, timeout = 120000) {
  const t0 = Date.now();
  for (;;) {
    const s = await page.evaluate(() => (window.getavatar ? window.getavatar.status() : { ready: false })).catch(() => ({ ready: false }));
    if (pred(s)) return s;
    if (Date.now() - t0 > timeout) throw new Error(`timed out waiting for ${what}; last status ${JSON.stringify(s)}; console errors ${JSON.stringify(consoleErrors)}`);
    await page.waitForTimeout(250);
  }
}
/** Apply a command and wait until the app has rendered it (two renders later: settled). */
async function command(cmd, pred = () => true) {
  const before = (await status()).renders;
  const err = await page.evaluate((c) => window.getavatar.command(c), cmd);
  if (err) throw new Error(`command ${JSON.stringify(cmd)} rejected: ${err}`);
  const s = await waitFor((s) => s.renders > before && pred(s), `render after ${JSON.stringify(cmd)}`);
  await page.waitForTimeout(300);
  return s;
}

/** Screenshot of the viewport image as {w, h, data} (RGBA). */
async function grab(name) {
  const s = await status();
  const [x, y, w, h] = s.viewport.map(Math.round);
  // A 1024² frame on SwiftShader can keep the page busy for a while: wait for it.
  const buf = await page.screenshot({ clip: { x, y, width: w, height: h }, timeout: 120000 });
  fs.writeFileSync(path.join(out, `${name}.png`), buf);
  const png = PNG.sync.read(buf);
  return { w: png.width, h: png.height, data: png.data };
}
const px = (img, x, y) => { const i = (y * img.w + x) * 4; return [img.data[i], img.data[i + 1], img.data[i + 2]]; };
function maskOf(img, fg) {
  const m = new Uint8Array(img.w * img.h);
  for (let y = 0; y < img.h; y++) for (let x = 0; x < img.w; x++) m[y * img.w + x] = fg(px(img, x, y)) ? 1 : 0;
  return m;
}
function bbox(m, w, h) {
  let [x0, y0, x1, y1] = [w, h, -1, -1];
  for (let y = 0; y < h; y++) for (let x = 0; x < w; x++) if (m[y * w + x]) { x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x); y1 = Math.max(y1, y); }
  return [x0, y0, x1, y1];
}
const coverage = (m) => m.reduce((a, b) => a + b, 0) / m.length;
function iou(a, b) { let i = 0, u = 0; for (let k = 0; k < a.length; k++) { i += a[k] & b[k]; u += a[k] | b[k]; } return i / u; }

/** Positions of the first mesh primitive of a .glb (float32 VEC3 accessor). */
function glbJson(bytes) {
  const jsonLen = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength).getUint32(12, true);
  return { json: JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + jsonLen))), jsonLen };
}

function glbPositions(bytes) {
  const { json, jsonLen } = glbJson(bytes);
  const binStart = 20 + jsonLen + 8;
  const acc = json.accessors[json.meshes[0].primitives[0].attributes.POSITION];
  const view = json.bufferViews[acc.bufferView];
  const off = binStart + (view.byteOffset ?? 0) + (acc.byteOffset ?? 0);
  const f = new Float32Array(bytes.buffer.slice(bytes.byteOffset + off, bytes.byteOffset + off + acc.count * 12));
  return { f, count: acc.count, json };
}

async function download(name) {
  const [dl] = await Promise.all([page.waitForEvent('download'), page.evaluate(() => window.getavatar.command({ download: true }))]);
  const file = path.join(out, name);
  await dl.saveAs(file);
  return { file, suggested: dl.suggestedFilename(), bytes: new Uint8Array(fs.readFileSync(file)) };
}

try {
  const t0 = Date.now();
  await page.goto(`${url}?view=mask&pose=T`);
  let s = await waitFor((s) => s.ready, 'first frame');
  await page.waitForTimeout(500);
  console.log(`first frame after ${((Date.now() - t0) / 1000).toFixed(1)} s; adapter "${s.adapter}" backend ${s.backend}`);
  check(/webgpu/i.test(s.backend), `app reports a WebGPU adapter (backend ${s.backend}, adapter "${s.adapter}")`);
  check(s.pose === 'T' && s.view === 'mask', `URL parameters applied (pose ${s.pose}, view ${s.view})`);
  check(s.vertices > 10000 && s.triangles > 20000, `body mesh uploaded (${s.vertices} vertices, ${s.triangles} triangles)`);

  // --- a frame shows the body where the camera model says it must be ---------------
  const tMask = await grab('mask_T');
  const mT = maskOf(tMask, (c) => c[0] > 127);
  const covT = coverage(mT);
  check(covT > 0.08 && covT < 0.45, `T-pose mask covers ${(100 * covT).toFixed(1)} % of the viewport`);
  const dlT = await download('body_T.glb');
  const { f, count } = glbPositions(dlT.bytes);
  check(count === s.vertices, `.glb has the app's ${s.vertices} vertices (${count})`);
  const tanHalf = Math.tan(Math.atan(16 / 35));
  const eye = [0, -0.185, 2.3];
  let [u0, v0, u1, v1] = [Infinity, Infinity, -Infinity, -Infinity];
  for (let i = 0; i < count; i++) {
    const [x, y, z] = [f[3 * i] - eye[0], f[3 * i + 1] - eye[1], f[3 * i + 2] - eye[2]];
    const u = (x / (-z * tanHalf) + 1) / 2 * tMask.w;
    const v = (1 - y / (-z * tanHalf)) / 2 * tMask.h;
    u0 = Math.min(u0, u); u1 = Math.max(u1, u); v0 = Math.min(v0, v); v1 = Math.max(v1, v);
  }
  const got = bbox(mT, tMask.w, tMask.h);
  const want = [u0, v0, u1, v1];
  const tol = 0.012 * tMask.w + 1.5;
  const worst = Math.max(...got.map((g, k) => Math.abs(g + (k >= 2 ? 1 : 0) - want[k])));
  check(worst <= tol, `mask bbox ${JSON.stringify(got)} matches projected mesh bbox ${JSON.stringify(want.map((x) => +x.toFixed(1)))} (worst ${worst.toFixed(2)} px, tol ${tol.toFixed(1)})`);

  // --- normal map: (n+1)/2 in world space, background = zero vector ----------------
  s = await command({ view: 'normal' }, (s) => s.view === 'normal');
  const nImg = await grab('normal_T');
  const bg = px(nImg, 3, 3);
  check(bg.every((c) => Math.abs(c - 128) <= 1), `normal-map background encodes the zero vector (${bg})`);
  // Chest: centre column, 40 % down the mask bbox; faces the camera (+z) → blue ≈ 255.
  const cx = Math.round((got[0] + got[2]) / 2);
  const cy = Math.round(got[1] + 0.3 * (got[3] - got[1]));
  const chest = px(nImg, cx, cy);
  const n = chest.map((c) => c / 127.5 - 1);
  const len = Math.hypot(...n);
  check(n[2] > 0.8 && Math.abs(len - 1) < 0.08, `chest normal ${n.map((x) => x.toFixed(2))} faces +z with unit length (${len.toFixed(3)})`);
  // Left arm (image right, +x side) top surface: normal points up (+y) → green high.
  const armY = Math.round(want[1] + (want[3] - want[1]) * 0.0);
  let armPix = null;
  for (let y = got[1]; y < got[3]; y++) { if (mT[y * tMask.w + Math.round(got[2] - 0.12 * (got[2] - got[0]))]) { armPix = px(nImg, Math.round(got[2] - 0.12 * (got[2] - got[0])), y + 1); break; } }
  check(armPix && armPix[1] > 200, `top of the left arm faces up (+y): ${armPix} (y ${armY})`);

  // --- RGB view differs from the background where the body is ----------------------
  s = await command({ view: 'rgb' }, (s) => s.view === 'rgb');
  const rgb = await grab('rgb_T');
  const body = px(rgb, cx, cy), back = px(rgb, 3, 3);
  check(Math.abs(body[0] - back[0]) + Math.abs(body[1] - back[1]) + Math.abs(body[2] - back[2]) > 60, `shaded body ${body} stands out from the background ${back}`);

  // --- changing the pose changes the silhouette -------------------------------------
  s = await command({ view: 'mask' }, (s) => s.view === 'mask');
  s = await command({ pose: 'arms_up' }, (s) => s.pose === 'arms_up');
  const upImg = await grab('mask_arms_up');
  const mUp = maskOf(upImg, (c) => c[0] > 127);
  const bUp = bbox(mUp, upImg.w, upImg.h);
  const j = iou(mT, mUp);
  check(j < 0.85, `arms_up silhouette differs from T (IoU ${j.toFixed(3)})`);
  check(bUp[1] < got[1] - 10 && bUp[2] - bUp[0] < 0.7 * (got[2] - got[0]), `arms_up is taller and narrower: bbox ${JSON.stringify(bUp)} vs T ${JSON.stringify(got)}`);
  s = await command({ joint: 'right_knee', value: [1.5, 0, 0] }, (s) => s.pose === 'custom');
  const knee = maskOf(await grab('mask_knee'), (c) => c[0] > 127);
  check(iou(knee, mUp) < 0.98 && iou(knee, mUp) > 0.6, `bending one knee changes part of the silhouette (IoU ${iou(knee, mUp).toFixed(3)})`);

  // --- camera: orbiting 90° shows the side view (narrower silhouette) ----------------
  s = await command({ pose: 'T' }, (s) => s.pose === 'T');
  s = await command({ yaw: 90 }, (s) => Math.abs(s.yaw_deg - 90) < 0.01);
  const side = maskOf(await grab('mask_T_side'), (c) => c[0] > 127);
  const bSide = bbox(side, tMask.w, tMask.h);
  check(bSide[2] - bSide[0] < 0.4 * (got[2] - got[0]), `side view is narrow (${bSide[2] - bSide[0]} px vs ${got[2] - got[0]} px front)`);
  s = await command({ reset_camera: true }, (s) => Math.abs(s.yaw_deg) < 0.01);

  // --- 1024² resolution ---------------------------------------------------------------
  s = await command({ res: 1024 }, (s) => s.res === 1024);
  check(s.res === 1024, 'render resolution switches to 1024²');

  // --- .glb download passes the Khronos validator ------------------------------------
  s = await command({ pose: 'walking' }, (s) => s.pose === 'walking');
  s = await command({ view: 'rgb' }, (s) => s.view === 'rgb');
  await grab('rgb_walking');
  const dl = await download('body_walking.glb');
  check(dl.suggested === 'getavatar_body_posed_walking.glb', `download is named after what it holds: ${dl.suggested}`);
  const report = await validator.validateBytes(dl.bytes);
  const iss = report.issues;
  check(iss.numErrors === 0, `glTF-Validator: ${iss.numErrors} errors, ${iss.numWarnings} warnings, ${iss.numInfos} infos`);
  if (iss.numErrors) console.log(JSON.stringify(iss.messages.slice(0, 5), null, 1));
  const st = await status();
  check(st.downloads === 2, `app counted ${st.downloads} downloads`);

  // --- the generator on WebGPU (burn's wgpu backend on egui's device) --------------
  s = await command({ view: 'mask' }, (s) => s.view === 'mask');
  s = await command({ pose: 'standing' }, (s) => s.pose === 'standing');
  const bodyStanding = maskOf(await grab('mask_body_standing'), (c) => c[0] > 127);
  s = await command({ pose: 'arms_up' }, (s) => s.pose === 'arms_up');
  const bodyUp = maskOf(await grab('mask_body_arms_up'), (c) => c[0] > 127);
  s = await command({ pose: 'standing' }, (s) => s.pose === 'standing');
  // The shipped demo model (listed in models/manifest.json by the build) is fetched at start-up.
  const manifest = await (await fetch(`${url}models/manifest.json`)).json();
  s = await waitFor((s) => s.model && !s.model.startsWith('loading'), 'generator weights', 120000);
  check(manifest.demo ? s.model.startsWith('trained demo model') : s.model.startsWith('untrained'),
    `generator weights: ${s.model} (manifest ${JSON.stringify(manifest)})`);
  const g0 = (await status()).generations;
  const tGen = Date.now();
  const jGen = await pageNow();
  await page.evaluate(() => window.getavatar.command({ generate: { seed_geo: 1, seed_tex: 2 } }));
  s = await waitFor((s) => s.generations > g0 && !s.generating, 'generation', 300000);
  jobs.push(['generate', jGen, await pageNow()]);
  await page.waitForTimeout(800);
  console.log(`generation took ${s.last_generation_ms.toFixed(0)} ms in the app on ${s.last_generation_on} (${((Date.now() - tGen) / 1000).toFixed(1)} s wall)`);
  // A new identity on a software adapter (SwiftShader here) is generated in the worker on
  // NdArray, on a hardware one on the page's WebGPU device.
  const softwareGen = /Cpu/.test(s.adapter);
  check(softwareGen ? /^the worker's CPU/.test(s.last_generation_on) : /^the page's WebGPU/.test(s.last_generation_on),
    `a new identity is generated on ${softwareGen ? "the worker's CPU, the adapter being a software one" : "the page's WebGPU device"} (${s.last_generation_on})`);
  // On a software adapter the worker warms up when the model is ready; in this fresh profile
  // it builds the body's context and keeps it in the browser's Cache API (read back after the
  // reload at the end).
  let builtContext = '';
  if (softwareGen) {
    s = await waitFor((s) => typeof s.worker_body_context === 'string' && s.worker_body_context !== '', "the worker's warm-up", 120000);
    builtContext = s.worker_body_context;
    const entries = await page.evaluate(async () => (await (await caches.open('getavatar-body-context')).keys()).map((r) => r.url));
    check(/^built in \d+ ms, kept in the browser's cache \(\d+\.\d MB in \d+ ms\)$/.test(builtContext) && entries.length === 1 && /\/body_context\/body-[0-9a-f]{16}-\d+-\d+\.bin$/.test(entries[0]),
      `a fresh profile's worker builds the body's context and keeps it in the Cache API ("${builtContext}"; ${JSON.stringify(entries)})`);
  }
  // The stage breakdown: host ms, waits on GPU read-backs, read-backs, per stage.
  const stageRows = s.last_generation_stages?.stages ?? [];
  console.log('generation by stage (ms):\n' + stageRows.map((x) => `  ${x.stage.padEnd(12)} host ${x.host_ms.toFixed(1).padStart(7)}  GPU wait ${x.gpu_wait_ms.toFixed(1).padStart(7)}  yields ${x.yield_ms.toFixed(1).padStart(7)}  read-backs ${x.readbacks}  dispatches ${x.dispatches}`).join('\n'));
  const names = stageRows.map((x) => x.stage).join(',');
  const sum = stageRows.reduce((a, x) => a + x.host_ms + x.gpu_wait_ms + x.yield_ms, 0);
  check(names === 'mapping,synthesis,posed grid,grid decode,DMTet,normals & colours,rigging,upload'
    && sum <= s.last_generation_ms + 100,
    `the generation's stage breakdown covers its stages (${names}; ${sum.toFixed(0)} ms of ${s.last_generation_ms.toFixed(0)})`);
  // The target: at most 2 GPU→CPU read-backs per new identity (the grid's geometry
  // fields, then the mesh vertices' normals and colours together).
  const readbacks = stageRows.reduce((a, x) => a + x.readbacks, 0);
  check(readbacks === 2, `a new identity takes 2 read-backs (${readbacks})`);
  check(s.showing === 'avatar' && s.avatar_vertices > 500, `Generate shows an avatar (${s.avatar_vertices} vertices)`);
  // ψ was not set, so the model's default applies: 0 (its training subjects) for a checkpoint
  // with latent modes, 0.7 otherwise; the slider shows it.
  const wantPsi = s.model.includes('latent modes') ? 0 : 0.7;
  check(Math.abs(s.psi - wantPsi) < 1e-6, `default ψ follows the model: ${s.psi} (${s.model})`);
  const avMask = maskOf(await grab('mask_avatar'), (c) => c[0] > 127);
  const jb = iou(avMask, bodyStanding);
  check(jb > 0.6, `the avatar follows the posed body (mask IoU ${jb.toFixed(3)})`);
  // The paper's per-pixel RGB: canonical coordinates rasterised on the GPU, the texture
  // field queried at every covered pixel. It covers exactly the mask, and is not flat.
  const t0Tex = (await status()).texture_images;
  s = await command({ view: 'texture' }, (s) => s.view === 'texture');
  s = await waitFor((s) => s.texture_images > t0Tex, 'per-pixel texture image', 180000);
  await page.waitForTimeout(500);
  const texImg = await grab('texture_avatar');
  const texCover = maskOf(texImg, (c) => Math.abs(c[0] - 38) + Math.abs(c[1] - 40) + Math.abs(c[2] - 46) > 6);
  const jt = iou(texCover, avMask);
  let mean = [0, 0, 0], nTex = 0;
  for (let k = 0; k < avMask.length; k++) if (avMask[k]) { for (let c = 0; c < 3; c++) mean[c] += texImg.data[4 * k + c]; nTex++; }
  mean = mean.map((v) => v / Math.max(1, nTex));
  let spread = 0;
  for (let k = 0; k < avMask.length; k++) if (avMask[k]) for (let c = 0; c < 3; c++) spread += Math.abs(texImg.data[4 * k + c] - mean[c]);
  spread /= Math.max(1, 3 * nTex);
  check(jt > 0.95 && s.texture_pixels > 1000 && spread > 2,
    `per-pixel texture view covers the mask (IoU ${jt.toFixed(3)}, ${s.texture_pixels} queried pixels, colour spread ${spread.toFixed(1)}, ${s.last_texture_ms.toFixed(0)} ms)`);
  s = await command({ view: 'rgb' }, (s) => s.view === 'rgb');
  const rgb1 = await grab('rgb_avatar_tex2');
  const g1 = (await status()).generations;
  await page.evaluate(() => window.getavatar.command({ retexture: { seed_tex: 3 } }));
  s = await waitFor((s) => s.generations > g1 && !s.generating, 're-texturing', 300000);
  await page.waitForTimeout(800);
  const rgb2 = await grab('rgb_avatar_tex3');
  let diff = 0, nBody = 0;
  for (let k = 0; k < avMask.length; k++) if (avMask[k]) { for (let c = 0; c < 3; c++) diff += Math.abs(rgb1.data[4 * k + c] - rgb2.data[4 * k + c]); nBody++; }
  diff /= Math.max(1, 3 * nBody);
  check(diff > 3, `a new texture seed changes RGB pixels (mean |Δ| ${diff.toFixed(1)} on the body)`);
  check(softwareGen ? /^the worker's CPU/.test(s.last_generation_on) : /^the page's WebGPU/.test(s.last_generation_on),
    `a new texture is computed on ${softwareGen ? "the worker's CPU" : "the page's WebGPU device"} (${s.last_generation_on}, ${s.last_generation_ms.toFixed(0)} ms)`);
  s = await command({ view: 'mask' }, (s) => s.view === 'mask');
  const avMask2 = maskOf(await grab('mask_avatar_tex3'), (c) => c[0] > 127);
  check(iou(avMask, avMask2) > 0.999, `…but not the mask (IoU ${iou(avMask, avMask2).toFixed(4)})`);
  s = await command({ view: 'rgb' }, (s) => s.view === 'rgb');
  // Vertex colours here (texture_res 0): the file has the app's vertices one to one.
  await page.evaluate(() => window.getavatar.command({ texture_res: 0 }));
  const dlA = await download('avatar.glb');
  const repA = await validator.validateBytes(dlA.bytes);
  check(repA.issues.numErrors === 0 && glbPositions(dlA.bytes).count === s.vertices, `avatar .glb: ${repA.issues.numErrors} validator errors, ${glbPositions(dlA.bytes).count} vertices`);

  // --- re-posing the avatar runs on the GPU (bone transforms only, no new generation) --
  s = await command({ view: 'mask' }, (s) => s.view === 'mask');
  const gPose = (await status()).generations;
  s = await command({ pose: 'arms_up' }, (s) => s.pose === 'arms_up');
  const avUp = maskOf(await grab('mask_avatar_arms_up'), (c) => c[0] > 127);
  const jUp = iou(avUp, bodyUp), jStill = iou(avMask, bodyUp);
  check(s.generations === gPose && s.showing === 'avatar' && jUp > 0.6 && jUp > jStill + 0.1,
    `the avatar re-posed to arms_up on the GPU follows the body (IoU ${jUp.toFixed(3)}; unposed ${jStill.toFixed(3)}; frame ${s.last_render_ms.toFixed(1)} ms)`);

  // --- reconstruct from photo ---------------------------------------------------------
  const photoStatus = async () => (await status()).photo;
  async function badPhoto(bytes, name, expect) {
    const before = await photoStatus();
    const ready = (await status()).renders;
    await page.evaluate(([b, n]) => window.getavatar.photo(new Uint8Array(b), n), [[...bytes], name]);
    const p = (await waitFor((s) => s.photo.failures > before.failures, `the message about ${name}`, 120000)).photo;
    const st = await status();
    check(p.state === 'failed' && expect.test(p.message) && st.pose === 'arms_up' && st.renders >= ready && st.photo_view[2] === 0,
      `${name}: one message ("${p.message}"), the app as it was`);
  }
  await badPhoto(new Uint8Array(0), 'empty.png', /empty/);
  const junk = new Uint8Array(4096);
  for (let k = 0; k < junk.length; k++) junk[k] = (k * 2654435761) >>> 24;
  await badPhoto(junk, 'junk.jpg', /not an image/);
  const tiny = new PNG({ width: 1, height: 1 });
  tiny.data.set([200, 100, 50, 255]);
  await badPhoto(PNG.sync.write(tiny), 'tiny.png', /too small/);
  // Over 40 MP (8000 × 5001, one colour: a small file that decodes to 160 MB) is refused.
  const huge = new PNG({ width: 8000, height: 5001 });
  huge.data.fill(180);
  await badPhoto(PNG.sync.write(huge), 'huge.png', /40 MP/);

  // The photo: the render over grey (a photo has no alpha), its alpha kept as the truth.
  const render = PNG.sync.read(fs.readFileSync(new URL('./fixtures/kick_clothed.png', import.meta.url)));
  const photo = new PNG({ width: render.width, height: render.height });
  for (let k = 0; k < render.data.length; k += 4) {
    const a = render.data[k + 3] / 255;
    for (let c = 0; c < 3; c++) photo.data[k + c] = Math.round(render.data[k + c] * a + 120 * (1 - a));
    photo.data[k + 3] = 255;
  }
  const fitsBefore = (await photoStatus()).fits;
  const tPhoto = Date.now();
  const jPhoto = await pageNow();
  // Through the UI: click "Open photo…" in the side panel, answer the browser's file chooser.
  const [bx, by, bw, bh] = (await status()).open_photo_button;
  check(bw > 0 && bh > 0 && bx + bw <= 1280 && by + bh <= 800, `the "Open photo…" button is on screen (${[bx, by, bw, bh].map(Math.round)})`);
  // egui hit-tests a press where the pointer hovered in the previous frame: hover first, then
  // press and release like a person; a second try if the app was busy with a frame.
  let chooser = null;
  for (let attempt = 1; attempt <= 3 && !chooser; attempt++) {
    const waiting = page.waitForEvent('filechooser', { timeout: 10000 }).catch(() => null);
    await page.mouse.move(bx + bw / 2, by + bh / 2, { steps: 4 });
    await page.waitForTimeout(300);
    await page.mouse.down();
    await page.waitForTimeout(60);
    await page.mouse.up();
    chooser = await waiting;
    if (!chooser) console.log(`(no file chooser after click ${attempt})`);
  }
  check(chooser !== null, 'clicking "Open photo…" opens the browser\'s file chooser');
  await chooser.setFiles({ name: 'kick_clothed.png', mimeType: 'image/png', buffer: PNG.sync.write(photo) });
  let p = (await waitFor((s) => s.photo.fits > fitsBefore || (s.photo.state === 'failed' && s.photo.name === 'kick_clothed.png'), 'the photo fit', 300000)).photo;
  jobs.push(['photo: detection and fit', jPhoto, await pageNow()]);
  console.log(`photo → body in ${((Date.now() - tPhoto) / 1000).toFixed(1)} s (detection ${(p.detect_ms / 1000).toFixed(1)} s, fit ${(p.fit_ms / 1000).toFixed(1)} s, ${p.steps_total} steps): ${p.message}`);
  check(p.state === 'fitted' && p.missing_joints.length === 0 && p.people === 1, `the person is found (${p.people} in the photo) and fitted (${p.state}: ${p.message})`);
  check(p.relative_to_height <= 0.03, `keypoint residual ${(100 * p.relative_to_height).toFixed(2)} % of the person's height (≤ 3 %; ${p.mean_px.toFixed(1)} px)`);
  const masks = await page.evaluate(() => window.getavatar.photoMasks());
  const alphaIou = (bits) => maskIou(masks, bits, (u, v) => render.data[pixelAt(render.width, render.height, u, v) * 4 + 3] >= 128);
  const personIou = alphaIou(masks.person), bodyIou = alphaIou(masks.body);
  // MediaPipe's probability read from the mask's alpha (www/pose_worker.js): 0.954 here; red
  // alone (every pixel of any probability) gave a ring around the person: 0.85 on the people
  // e2e's composites of this render.
  check(personIou >= 0.92, `the fit's person mask vs the photo's alpha: IoU ${personIou.toFixed(3)} (≥ 0.92)`);
  check(bodyIou >= 0.7, `the fitted bare body vs the clothed alpha: IoU ${bodyIou.toFixed(3)} (≥ 0.7)`);
  s = await status();
  check(s.pose === 'photo fit' && s.photo_view[2] > 100, `the fit is the app's pose, the photo is shown (${s.photo_view.map(Math.round)})`);
  await page.screenshot({ path: path.join(out, 'photo_fit.png') });
  const dls = [];
  const fitFiles = new Promise((resolve) => page.on('download', (d) => { dls.push(d); if (dls.length === 2) resolve(); }));
  await page.evaluate(() => window.getavatar.command({ photo_fit: 'download' }));
  await Promise.race([fitFiles, page.waitForTimeout(20000)]);
  const files = {};
  for (const d of dls) { const f = path.join(out, d.suggestedFilename()); await d.saveAs(f); files[d.suggestedFilename()] = JSON.parse(fs.readFileSync(f, 'utf8')); }
  const fj = files['fit.json'], kj = files['kp.json'];
  check(fj?.format === 'getavatar-body-fit/1' && fj.body_pose.length === 69 && fj.camera.length === 16 && kj?.poseLandmarks?.length === 33,
    `Download fit: fit.json (${fj?.format}, ${fj?.body_pose?.length} pose numbers) and kp.json (${kj?.poseLandmarks?.length} landmarks)`);
  // --- instant: the photo encoder's guess as the avatar ------------------------------
  // The default start (the shipped encoder), no steps, in the worker on its WebGPU device.
  // The photo never leaves the page: no request at all while it runs but the worker's own
  // module files (GET, same origin: its script, the wasm module and the JS glue it imports).
  const own = /\/(reconstruct_worker\.js|getavatar_web\.js|getavatar_web_bg\.wasm|pose_detect\.js|video_frames\.js)$/;
  const origin = new URL(url).origin;
  const requests = [];
  const onRequest = (r) => requests.push([r.url(), r.method()]);
  page.on('request', onRequest);
  const tInstant = Date.now();
  // PROFILE_INSTANT=1: a CPU profile of the page over `instant`'s job, for
  // `node profile_tasks.mjs app_instant` (out/long_tasks/; needs a build with names,
  // GETAVATAR_KEEP_NAMES=1 cargo xtask build-web).
  const prof = process.env.PROFILE_INSTANT ? await context.newCDPSession(page) : null;
  if (prof) { await prof.send('Profiler.enable'); await prof.send('Profiler.setSamplingInterval', { interval: 1000 }); await prof.send('Profiler.start'); }
  const jInstant = await pageNow();
  const instErr = await page.evaluate(() => window.getavatar.command({ reconstruct: { preset: 'instant' } }));
  check(instErr === '' || instErr == null, `the instant reconstruct command is accepted (${instErr})`);
  let rec = (await waitFor((s) => ['done', 'failed', 'cancelled'].includes(s.reconstruct.state), 'the instant reconstruction', 600000)).reconstruct;
  jobs.push(['reconstruction, instant', jInstant, await pageNow()]);
  if (prof) {
    const { profile } = await prof.send('Profiler.stop');
    const [, from, to] = jobs.at(-1);
    const lt = (await page.evaluate(() => window.__longTasks)).filter(([t, d]) => t + d > from && t < to);
    const dir = new URL('./out/long_tasks/', import.meta.url);
    fs.mkdirSync(dir, { recursive: true });
    fs.writeFileSync(new URL('app_instant.cpuprofile', dir), JSON.stringify(profile));
    fs.writeFileSync(new URL('app_instant.lt.json', dir), JSON.stringify({ pt0: from, lt }));
  }
  console.log(`instant reconstruction: first avatar ${(rec.first_avatar_ms / 1000).toFixed(1)} s after the command (start ${(rec.start_ms / 1000).toFixed(1)} s in the worker on ${rec.device}; finish ${(rec.finish_ms / 1000).toFixed(1)} s: ${rec.finish_detail}); wall ${((Date.now() - tInstant) / 1000).toFixed(1)} s; ${rec.message}`);
  check(rec.preset === 'instant', `the panel's quality buttons show the preset that ran (${rec.preset})`);
  check(rec.state === 'done' && rec.start === "the encoder's guess" && rec.losses.length === 0,
    `instant: the avatar is the shipped encoder's guess, no step (${rec.state}, start "${rec.start}", ${rec.losses.length} steps: ${rec.message})`);
  // On a software adapter (SwiftShader here) `auto` runs a job on NdArray in the worker, the
  // faster there (docs/benchmarks.md); on a hardware one on WebGPU.
  const software = /Cpu/.test(s.adapter);
  check(rec.runs_in === 'worker' && (software ? /^CPU \(burn NdArray in the worker; the WebGPU adapter is a software one/ : /^WebGPU/).test(rec.device),
    `the guess is made in the worker on ${software ? 'NdArray, the adapter being a software one' : 'its WebGPU device'} (${rec.runs_in}: ${rec.device})`);
  // The guess on the body as first fitted is on screen first (unmeasured: its figures are
  // null), then the start (the guess or a garment code's outline) on the body refitted to
  // its outline; the worker hands that over and renders it for the figures while the page
  // rigs and shows it.
  check(rec.first_avatar_ms > 0 && rec.first_avatar_ms < rec.total_ms && rec.first_mask_iou === null && /after it: figures/.test(rec.finish_detail),
    `instant: the guess is on screen before the refit and the figures (${(rec.first_avatar_ms / 1000).toFixed(1)} s, figures at ${(rec.total_ms / 1000).toFixed(1)} s: ${rec.finish_detail})`);
  // The stage after the guess weighed the encoder file's garment codes against its outline.
  // (None when the guess's outline already overlaps the person well.)
  // The worker kept the guess's avatar from the first job: the codes are weighed against it
  // without generating it again.
  check(rec.garment_codes >= 8 && [0, rec.garment_codes].includes(rec.garments_weighed) && typeof rec.garment === 'string'
    && rec.garment_guess_reused === true,
    `instant: the refitted stage had the encoder file's ${rec.garment_codes} garment codes and weighed ${rec.garments_weighed} against the guess (chosen: ${rec.garment || 'the guess\'s own outline'}; the first job's avatar of the guess reused: ${rec.garment_guess_reused})`);
  check(rec.first_avatar_ms <= 90000, `instant: the first avatar within 90 s of the command on SwiftShader (${(rec.first_avatar_ms / 1000).toFixed(1)} s)`);
  check(rec.mask_iou >= 0.75,
    `instant: the avatar's mask overlaps the photo's person at its camera: IoU ${rec.mask_iou.toFixed(3)} (≥ 0.75), masked PSNR ${rec.psnr_db.toFixed(1)} dB`);
  // The photo's body fit was refined on the clothed outline, and the app's body is it.
  // `instant` weighs the garment codes on the body as first fitted, so the worker refits the
  // body on the chosen outline after them (the order `trainer invert` measures), in the stage
  // that projects the photo and measures.
  check(rec.refit_beta1[0] !== rec.refit_beta1[1] && rec.refit_beta1.every(Number.isFinite) && rec.refit_on === 'worker'
    && rec.refitted_avatar_ms > rec.first_avatar_ms && rec.refitted_avatar_ms <= rec.total_ms,
    `instant: the body fit refined on the chosen outline in the ${rec.refit_on} (β₁ ${rec.refit_beta1.map((b) => b.toFixed(2)).join(' → ')}; `
    + `the refitted avatar on screen ${(rec.refitted_avatar_ms / 1000).toFixed(1)} s after the command)`);
  const foreignInstant = requests.filter(([u, method]) => method !== 'GET' || new URL(u).origin !== origin || !own.test(new URL(u).pathname));
  check(foreignInstant.length === 0, `no network request during the instant reconstruction but the worker's own module files (${requests.length} in all; others: ${foreignInstant.slice(0, 3).map((r) => r.join(' ')).join(', ')})`);
  s = await waitFor((s) => s.renders > 0 && s.showing === 'avatar', 'the instant avatar on screen');
  await page.screenshot({ path: path.join(out, 'reconstruction_instant.png') });
  requests.length = 0;
  // --- reconstruct the avatar from the fitted photo ---------------------------------
  // A short run on the worker's `auto` device (NdArray on a software adapter, 2–3 s per step
  // here; WebGPU on a hardware one): 3 W+ + 1 PTI steps at 64² from w_avg, a preview after
  // every step.
  const tRec = Date.now();
  const jRec = await pageNow();
  const recErr = await page.evaluate(() => window.getavatar.command({ reconstruct: { steps: 3, pti_steps: 1, res: 64, preview_every: 1, start: 'average' } }));
  check(recErr === '' || recErr == null, `the reconstruct command is accepted (${recErr})`);
  rec = (await waitFor((s) => s.reconstruct.steps_total === 4 && ['done', 'failed', 'cancelled'].includes(s.reconstruct.state), 'the reconstruction', 1800000)).reconstruct;
  // The steps run in the reconstruction worker: the page only shows progress and rigs the
  // result, in slices, so the job is checked like the others.
  jobs.push(['reconstruction, the first', jRec, await pageNow()]);
  page.off('request', onRequest);
  console.log(`reconstruction in ${((Date.now() - tRec) / 1000).toFixed(1)} s: start ${rec.start} (${(rec.start_ms / 1000).toFixed(1)} s), ${rec.ms_per_latent_step.toFixed(0)} ms per W+ step, ${rec.ms_per_pivotal_step.toFixed(0)} ms per PTI step, finish ${(rec.finish_ms / 1000).toFixed(1)} s (${rec.finish_detail}); losses ${rec.losses.map((l) => l.toFixed(4)).join(' ')}; ${rec.message}`);
  check(rec.state === 'done' && rec.losses.length === 4 && rec.previews >= 3, `the reconstruction finishes: ${rec.losses.length} steps, ${rec.previews} previews (${rec.state}: ${rec.message})`);
  check(rec.runs_in === 'worker' && (software ? /^CPU \(burn NdArray in the worker; the WebGPU adapter is a software one/ : /^WebGPU/).test(rec.device),
    `the reconstruction's steps ran in the reconstruction worker, off the UI thread, on ${software ? 'NdArray, the adapter being a software one' : 'its WebGPU device'} (${rec.runs_in}: ${rec.device})`);
  check(rec.losses[2] < rec.losses[0], `the loss falls over the W+ steps (${rec.losses[0]?.toFixed(4)} → ${rec.losses[2]?.toFixed(4)})`);
  check(rec.mask_iou >= 0.6, `the reconstructed avatar's mask overlaps the photo's person at its camera: IoU ${rec.mask_iou.toFixed(3)} (≥ 0.6)`);
  // Nothing may be requested, and nothing is sent.
  const foreign = requests.filter(([u, method]) => method !== 'GET' || new URL(u).origin !== origin || !own.test(new URL(u).pathname));
  check(foreign.length === 0, `no network request during the reconstruction but the worker's own module files (${requests.length} in all; others: ${foreign.slice(0, 3).map((r) => r.join(' ')).join(', ')})`);
  s = await waitFor((s) => s.renders > 0 && s.showing === 'avatar', 'the reconstructed avatar on screen');
  check(s.showing === 'avatar' && s.avatar_vertices > 1000 && consoleErrors.length === 0,
    `the reconstruction is the shown avatar (${s.avatar_vertices} vertices), no console errors (${consoleErrors.length})`);
  await page.screenshot({ path: path.join(out, 'reconstruction.png') });
  // Cancel: a second run stopped after its first step keeps the last preview's state as the
  // avatar. It runs on the worker's WebGPU device whatever the adapter, so that path's steps
  // are tested here too (SwiftShader: about a minute per step).
  const doneBefore = rec.done;
  const jRec2 = await pageNow();
  await page.evaluate(() => window.getavatar.command({ reconstruct: { steps: 40, pti_steps: 0, res: 64, preview_every: 1, start: 'average', device: 'webgpu' } }));
  // (The second run is the one with 40 steps: the status still holds the first run's until the app takes the command.)
  await waitFor((s) => s.reconstruct.steps_total === 40 && (s.reconstruct.steps_done >= 1 || s.reconstruct.state === 'failed'), 'the second reconstruction to start', 900000);
  await page.evaluate(() => window.getavatar.command({ reconstruct_cancel: true }));
  rec = (await waitFor((s) => s.reconstruct.steps_total === 40 && ['cancelled', 'done', 'failed'].includes(s.reconstruct.state), 'the cancellation', 300000)).reconstruct;
  jobs.push(['reconstruction, the second (start, a step, cancel)', jRec2, await pageNow()]);
  s = await status();
  check(rec.runs_in === 'worker' && /^WebGPU/.test(rec.device), `the second run's step ran in the worker on its WebGPU device (${rec.runs_in}: ${rec.device})`);
  check(rec.state === 'cancelled' && rec.stopped_at >= 1 && rec.done === doneBefore && s.avatar_vertices > 1000 && s.showing === 'avatar' && /last preview/.test(rec.message),
    `Cancel stops a reconstruction and keeps the last preview's state as the avatar (${rec.state} after ${rec.stopped_at} steps, ${s.avatar_vertices} vertices: ${rec.message})`);
  const vertsBefore = s.avatar_vertices;
  // Save the reconstruction (tuned generator, codes, photo) and open the file again through
  // "Open reconstruction…": the same avatar comes back, with its photo.
  const [sdl] = await Promise.all([page.waitForEvent('download', { timeout: 120000 }), page.evaluate(() => window.getavatar.command({ save_reconstruction: true }))]);
  const saved = fs.readFileSync(await sdl.path());
  const headerLen = Number(saved.readBigUInt64LE(0));
  const header = JSON.parse(saved.subarray(8, 8 + headerLen).toString());
  s = await status();
  check(sdl.suggestedFilename() === 'getavatar_reconstruction.safetensors' && s.reconstruct.saved === 1 && s.reconstruct.saved_bytes === saved.length
    && header.__metadata__['inversion/photo'] && header['inversion/photo_rgb']?.shape[2] === 3 && header['inversion/w_geo'],
    `"Save reconstruction" downloads ${sdl.suggestedFilename()} (${(saved.length / 1e6).toFixed(1)} MB: generator, codes, the photo ${header['inversion/photo_rgb']?.shape.join('×')})`);
  const openedBefore = s.reconstruct.opened;
  await command({ show: 'body' }, (s) => s.showing === 'body');
  await page.setInputFiles('#getavatar_reconstruction_input', { name: 'reconstruction.safetensors', mimeType: 'application/octet-stream', buffer: saved });
  rec = (await waitFor((s) => s.reconstruct.opened > openedBefore || s.reconstruct.state === 'failed', 'the saved reconstruction to open', 300000)).reconstruct;
  s = await waitFor((s) => s.renders > 0 && s.showing === 'avatar', 'the opened reconstruction on screen');
  check(rec.state === 'done' && rec.has_photo && s.avatar_vertices === vertsBefore && rec.done === doneBefore,
    `the saved file opens as the same avatar (${s.avatar_vertices} vertices vs ${vertsBefore}), its photo kept (${rec.message})`);
  await page.setInputFiles('#getavatar_reconstruction_input', { name: 'not_one.safetensors', mimeType: 'application/octet-stream', buffer: Buffer.from([1, 2, 3]) });
  rec = (await waitFor((s) => s.reconstruct.state === 'failed', 'the refusal of a broken file', 60000)).reconstruct;
  s = await status();
  check(/not_one\.safetensors/.test(rec.message) && s.avatar_vertices === vertsBefore && s.showing === 'avatar',
    `a broken reconstruction file is refused with one message and the avatar stays ("${rec.message}")`);

  // Two people (the photo and a smaller copy beside it), 4.7 MP: the largest is fitted, and
  // said so; the detector ran on the photo downscaled to at most 4 MP.
  const S = 3;
  const crowd = new PNG({ width: 2 * S * photo.width, height: S * photo.height });
  for (let k = 0; k < crowd.data.length; k += 4) { crowd.data[k] = crowd.data[k + 1] = crowd.data[k + 2] = 120; crowd.data[k + 3] = 255; }
  const paste = (scale, ox, oy) => {
    for (let y = 0; y < Math.floor(render.height * scale); y++) for (let x = 0; x < Math.floor(render.width * scale); x++) {
      const i = (Math.floor(y / scale) * render.width + Math.floor(x / scale)) * 4, a = render.data[i + 3] / 255;
      const o = ((oy + y) * crowd.width + ox + x) * 4;
      for (let c = 0; c < 3; c++) crowd.data[o + c] = Math.round(render.data[i + c] * a + crowd.data[o + c] * (1 - a));
    }
  };
  paste(S, 0, 0);
  paste(0.6 * S, S * (photo.width + 48), S * 150);
  const fitsCrowd = (await photoStatus()).fits;
  await page.setInputFiles('#getavatar_photo_input', { name: 'two_people.png', mimeType: 'image/png', buffer: PNG.sync.write(crowd) });
  p = (await waitFor((s) => s.photo.fits > fitsCrowd || (s.photo.state === 'failed' && s.photo.name === 'two_people.png'), 'the two-people fit', 300000)).photo;
  const crowdMasks = await page.evaluate(() => window.getavatar.photoMasks());
  let left = 0, right = 0;
  for (let k = 0; k < crowdMasks.body.length; k++) if (crowdMasks.body[k] === '1') { if (k % crowdMasks.width < crowdMasks.width / 2) left++; else right++; }
  check(p.state === 'fitted' && p.people === 2 && /largest/.test(p.message) && left > 20 * Math.max(1, right),
    `two people: ${p.people} counted, the largest fitted (${left} body pixels on its side, ${right} on the other; "${p.message}")`);
  check(p.width === crowd.width && p.detected_width * p.detected_height <= 4e6 && p.detected_width * p.detected_height > 3.9e6,
    `a ${(crowd.width * crowd.height / 1e6).toFixed(1)} MP photo is detected at ${p.detected_width}×${p.detected_height} (≤ 4 MP)`);

  // A limb corrected with the pose controls is held by the re-fit: the left shoulder turned
  // 1.5 rad from the fit's (the hand moves by more than half a metre, far from its landmarks).
  const shoulder = fj.body_pose.slice(15 * 3, 15 * 3 + 3);
  await command({ joint: 'left_shoulder', value: [shoulder[0], shoulder[1], shoulder[2] + 1.5] }, (s) => s.pose === 'custom');
  const tHeld = Date.now();
  await page.evaluate(() => window.getavatar.command({ photo_fit: 'refit' }));
  p = (await waitFor((s) => s.photo.fits > fitsCrowd + 1 || s.photo.state === 'failed', 'the corrected re-fit', 300000)).photo;
  check(p.state === 'fitted' && /held where you put it, against the detector: left arm$/.test(p.message) && p.held.join() === 'left arm',
    `a corrected arm is held by the re-fit (${((Date.now() - tHeld) / 1000).toFixed(1)} s: "${p.message}")`);
  await page.screenshot({ path: path.join(out, 'photo_refit_held.png') });

  // A re-fit from the current pose, cancelled while it runs.
  await page.evaluate(() => window.getavatar.command({ photo_fit: 'refit' }));
  await waitFor((s) => s.photo.state === 'fitting' && s.photo.steps_done > 0, 'the re-fit to start', 60000);
  await page.evaluate(() => window.getavatar.command({ photo_fit: 'cancel' }));
  p = (await waitFor((s) => s.photo.state !== 'fitting', 'the cancellation', 60000)).photo;
  check(p.state === 'cancelled' && p.fits === fitsCrowd + 2, `a re-fit can be cancelled (${p.state}, ${p.message})`);

  // --- motion: built-in clips play on the GPU re-pose; AMASS files; the animated .glb -----
  await page.evaluate(() => window.getavatar.command({ photo_fit: 'close' }));
  s = await command({ view: 'mask' }, (s) => s.view === 'mask');
  check(['walk', 'turn', 'wave'].every((c) => s.motion.clips.includes(c)), `built-in clips: ${s.motion.clips.join(', ')}`);
  s = await command({ motion: { clip: 'walk', time: 0 } }, (s) => s.motion.clip === 'walk' && s.pose === 'motion walk');
  const walk0 = maskOf(await grab('motion_walk_0'), (p) => p[0] > 128);
  s = await command({ motion: { time: 0.55 } }, (s) => Math.abs(s.motion.time - 0.55) < 1e-3);
  const walk1 = maskOf(await grab('motion_walk_half'), (p) => p[0] > 128);
  const walkIou = iou(walk0, walk1);
  check(walkIou < 0.97 && coverage(walk1) > 0.02, `scrubbing the walk moves the ${s.showing} (mask IoU ${walkIou.toFixed(3)} between 0 s and 0.55 s)`);
  const rendersBefore = s.renders;
  await command({ motion: { play: true, speed: 1 } }, (s) => s.motion.playing);
  // Five frames, waited for up to 8 s: SwiftShader's frame rate on a loaded CI machine varies.
  const tPlay = Date.now();
  do {
    await page.waitForTimeout(500);
    s = await status();
  } while (!(s.renders - rendersBefore >= 5 && s.motion.time !== 0.55) && Date.now() - tPlay < 8000);
  check(s.motion.playing && s.renders - rendersBefore >= 5 && s.motion.time !== 0.55,
    `playing re-poses every frame: ${s.renders - rendersBefore} renders in ${((Date.now() - tPlay) / 1000).toFixed(1)} s, now at ${s.motion.time.toFixed(2)} s of ${s.motion.duration.toFixed(2)} s`);
  // Re-pose at the cost of a plain draw. What must hold is structural: while the walk
  // plays (a new pose every frame), a frame of the avatar uploads no mesh and writes exactly
  // the bytes a frame of the bare body writes (24 joint transforms and the uniforms).
  // The frame times are a measurement, printed (docs/benchmarks.md), not a check: host times
  // are tenths of a millisecond here and SwiftShader shares the 2 cores with everything else.
  // Median at 1024² of the time from a frame's start to its GPU work done, and of its host
  // time; body and avatar alternate (3 rounds of 9 frames) so a drifting load weighs on both.
  async function frames(show, n) {
    // The frame that switches what is shown uploads its buffers: sample only after two
    // frames of the new one are drawn (a frame takes about a second here).
    const before = (await status()).renders;
    await page.evaluate((v) => window.getavatar.command({ show: v }), show);
    await waitFor((s) => s.showing === show && s.renders >= before + 3, `three frames of the ${show}`);
    const out = { frame: [], host: [], bytes: new Set(), uploads: new Set() };
    for (let k = 0; k < n; k++) {
      await page.waitForTimeout(120);
      const st = await status();
      out.frame.push(st.last_frame_ms);
      out.host.push(st.last_render_ms);
      out.bytes.add(st.last_frame_upload_bytes);
      out.uploads.add(st.mesh_uploads);
    }
    out.showing = (await status()).showing;
    return out;
  }
  const median = (t) => { const v = [...t].sort((a, b) => a - b); return v[v.length >> 1]; };
  await command({ res: 1024 }, (s) => s.res === 1024);
  const runs = { body: [], avatar: [] };
  for (let round = 0; round < 3; round++) {
    for (const who of ['body', 'avatar']) runs[who].push(await frames(who, 9));
  }
  const flat = (who, key) => runs[who].flatMap((r) => r[key]);
  const bytesOf = (who) => [...new Set(runs[who].flatMap((r) => [...r.bytes]))];
  const steady = (who) => runs[who].every((r) => r.uploads.size === 1 && r.showing === who);
  check(steady('body') && steady('avatar'),
    `re-posing uploads no mesh: mesh uploads per 9-frame run ${['body', 'avatar'].map((w) => w + ' ' + runs[w].map((r) => r.uploads.size - 1).join('/')).join(', ')} (0 each)`);
  check(bytesOf('body').length === 1 && bytesOf('avatar').length === 1 && bytesOf('body')[0] === bytesOf('avatar')[0] && bytesOf('body')[0] < 4096,
    `a re-posed frame writes the same bytes to the GPU for the avatar as for the body: ${bytesOf('avatar').join('/')} vs ${bytesOf('body').join('/')} bytes (joint transforms and uniforms)`);
  const bodyMs = median(flat('body', 'frame')), avatarMs = median(flat('avatar', 'frame'));
  const bodyHost = median(flat('body', 'host')), avatarHost = median(flat('avatar', 'host'));
  const ratio = avatarMs / bodyMs;
  console.log(`re-pose per frame at 1024² (start to GPU done): body ${bodyMs.toFixed(1)} ms, avatar ${avatarMs.toFixed(1)} ms (ratio ${ratio.toFixed(2)}, target ≤ 1.5: ${ratio <= 1.5 ? 'met' : 'missed'}); host: body ${bodyHost.toFixed(1)} ms, avatar ${avatarHost.toFixed(1)} ms`);
  check(bodyMs > 0 && avatarMs > 0, `frames' GPU completion is timed (body ${bodyMs.toFixed(1)} ms, avatar ${avatarMs.toFixed(1)} ms)`);
  s = await command({ motion: { play: false } }, (s) => !s.motion.playing);
  const amass = fs.readFileSync(new URL('../fixtures/motion/amass_sample.npz', import.meta.url));
  const loadedBefore = s.motion.files_loaded;
  await page.evaluate((b) => window.getavatar.motion(new Uint8Array(b), 'amass_sample.npz'), [...amass]);
  s = await waitFor((s) => s.motion.files_loaded > loadedBefore, 'the motion file');
  check(s.motion.clip === 'amass_sample' && s.motion.frames === 16 && s.motion.notes.some((n) => /resampled/.test(n)),
    `an AMASS .npz loads as a clip (${s.motion.clip}, ${s.motion.frames} frames; ${s.motion.notes.join('; ')})`);
  const errorsBefore = s.errors_total;
  await page.evaluate(() => window.getavatar.motion(new Uint8Array([1, 2, 3]), 'broken.npz'));
  s = await waitFor((s) => s.errors_total > errorsBefore, 'the message about broken.npz');
  check(/broken\.npz/.test(s.errors[s.errors.length - 1]) && s.motion.clip === 'amass_sample',
    `a bad motion file gets one message and changes nothing ("${s.errors[s.errors.length - 1]}")`);
  await page.evaluate(() => window.getavatar.command({ motion: { include: ['walk', 'wave'] } }));
  await waitFor((s) => s.motion.include.join() === 'walk,wave', 'the clips of the animated download');
  const [adl] = await Promise.all([page.waitForEvent('download'), page.evaluate(() => window.getavatar.command({ download_animated: true }))]);
  const animFile = path.join(out, adl.suggestedFilename());
  await adl.saveAs(animFile);
  const anim = new Uint8Array(fs.readFileSync(animFile));
  const animRep = await validator.validateBytes(anim);
  check(animRep.issues.numErrors === 0 && animRep.issues.numWarnings === 0 && animRep.info.animationCount === 2 && animRep.info.hasSkins,
    `animated .glb ${adl.suggestedFilename()}: ${animRep.issues.numErrors} errors, ${animRep.issues.numWarnings} warnings, ${animRep.info.animationCount} animations, skinned ${animRep.info.hasSkins}`);
  check(/animated_walk\+wave\.glb$/.test(adl.suggestedFilename()), `the file name says what it holds (${adl.suggestedFilename()})`);
  // Textured downloads: the avatar's texture baked at 256² (small for SwiftShader), then
  // the posed and the animated file carry it.
  await page.evaluate(() => window.getavatar.command({ texture_res: 256 }));
  const bakesBefore = (await status()).motion.bakes;
  const [tdl] = await Promise.all([page.waitForEvent('download', { timeout: 240000 }), page.evaluate(() => window.getavatar.command({ download: true }))]);
  const texFile = path.join(out, tdl.suggestedFilename());
  await tdl.saveAs(texFile);
  const tex = new Uint8Array(fs.readFileSync(texFile));
  const texRep = await validator.validateBytes(tex);
  s = await status();
  const texJson = glbPositions(tex).json;
  check(texRep.issues.numErrors === 0 && texRep.issues.numWarnings === 0 && texRep.info.hasTextures && texJson.images?.length === 1 && s.motion.last_textured && s.motion.bakes === bakesBefore + 1,
    `posed .glb with a ${s.motion.texture_res}² baked texture (${s.motion.last_bake_ms.toFixed(0)} ms; atlas ${s.motion.atlas_vertices} vertices): ${texRep.issues.numErrors} errors, ${texRep.issues.numWarnings} warnings, ${texJson.images?.length} image`);
  // The avatar shown is the opened reconstruction: on a software adapter the worker computes
  // its texture field from the file (bench_bake.mjs compares both devices' textures).
  check(softwareGen ? /^the worker's CPU/.test(s.motion.last_bake_on) : /^the page's WebGPU/.test(s.motion.last_bake_on),
    `the bake's texture-field queries ran on ${softwareGen ? "the worker's CPU" : "the page's WebGPU device"} (${s.motion.last_bake_on})`);
  const [tadl] = await Promise.all([page.waitForEvent('download'), page.evaluate(() => window.getavatar.command({ download_animated: true }))]);
  const texAnim = new Uint8Array(fs.readFileSync(await tadl.path()));
  const texAnimRep = await validator.validateBytes(texAnim);
  s = await status();
  check(texAnimRep.issues.numErrors === 0 && texAnimRep.info.hasTextures && texAnimRep.info.animationCount === 2 && s.motion.bakes === bakesBefore + 1,
    `animated .glb reuses the bake (${s.motion.bakes - bakesBefore} bake): textured ${texAnimRep.info.hasTextures}, ${texAnimRep.info.animationCount} animations, ${texAnimRep.issues.numErrors} errors`);
  // VRM 1.0: "⬇ .vrm" saves the avatar shown (its 256² bake) with the humanoid map and no
  // animations, its licence by origin; "⬇ .vrma" saves each chosen clip (walk, wave).
  const [vdl] = await Promise.all([page.waitForEvent('download'), page.evaluate(() => window.getavatar.command({ download_vrm: true }))]);
  const vrmBytes = new Uint8Array(fs.readFileSync(await vdl.path()));
  const vrmRep = await validator.validateBytes(vrmBytes);
  const vrmJson = glbPositions(vrmBytes).json;
  const vrmExt = vrmJson.extensions?.VRMC_vrm;
  const photoMade = /reconstruction/.test(vdl.suggestedFilename());
  s = await status();
  check(vrmRep.issues.numErrors === 0 && vrmExt?.specVersion === '1.0' && vrmExt.humanoid?.humanBones?.hips && vrmExt.humanoid.humanBones.leftUpperArm
    && !(vrmJson.animations?.length) && vrmJson.images?.length === 1 && s.motion.vrm_downloads === 1 && /\.vrm$/.test(vdl.suggestedFilename())
    && vrmExt.meta?.avatarPermission === (photoMade ? 'onlyAuthor' : 'everyone'),
    `⬇ .vrm ${vdl.suggestedFilename()} (${(vrmBytes.length / 1e6).toFixed(2)} MB): ${vrmRep.issues.numErrors} errors, VRM ${vrmExt?.specVersion}, ${Object.keys(vrmExt?.humanoid?.humanBones ?? {}).length} humanoid bones, ${vrmJson.animations?.length ?? 0} animations, ${vrmJson.images?.length} image, avatarPermission ${vrmExt?.meta?.avatarPermission}`);
  const vrmas = [];
  const twoVrmas = new Promise((resolve) => {
    const on = (d) => { vrmas.push(d); if (vrmas.length === 2) { page.off('download', on); resolve(); } };
    page.on('download', on);
  });
  await page.evaluate(() => window.getavatar.command({ download_vrma: true }));
  await twoVrmas;
  for (const d of vrmas) {
    const bytes = new Uint8Array(fs.readFileSync(await d.path()));
    const rep = await validator.validateBytes(bytes);
    const j = glbJson(bytes).json;
    check(rep.issues.numErrors === 0 && j.extensions?.VRMC_vrm_animation?.humanoid?.humanBones?.hips && j.animations?.length === 1 && !j.meshes,
      `⬇ .vrma ${d.suggestedFilename()}: ${rep.issues.numErrors} errors, ${j.animations?.length} animation, hips node ${j.extensions?.VRMC_vrm_animation?.humanoid?.humanBones?.hips?.node}`);
  }
  s = await status();
  check(vrmas.map((d) => d.suggestedFilename()).sort().join() === 'getavatar_walk.vrma,getavatar_wave.vrma' && s.motion.vrma_downloads === 2,
    `one .vrma per chosen clip: ${vrmas.map((d) => d.suggestedFilename()).join(', ')}`);
  await page.screenshot({ path: path.join(out, 'motion.png') });

  check(consoleErrors.length === 0, `zero console errors (${consoleErrors.length}: ${consoleErrors.slice(0, 3).join(' | ')})`);
  fs.writeFileSync(path.join(out, 'status.json'), JSON.stringify(await status(), null, 1));
  await page.screenshot({ path: path.join(out, 'app.png') });
  // No job blocks the UI thread over 100 ms at a time (PerformanceObserver long tasks
  // overlapping each job's window), but for one task of at most 200 ms: two fresh-clone CI
  // runs on a slow day had one such task in `instant`'s 13 s (151 and 104 ms). Its pieces
  // found so far are sliced; a warm run still had one of 93 ms, a later one none over 50 ms
  // (docs/reliability.md, "Not done yet"). Over the whole run they include 1024² frames drawn
  // by SwiftShader, which are no job's.
  const long = await page.evaluate(() => window.__longTasks);
  const sorted = long.map(([, d]) => d).sort((a, b) => b - a);
  console.log(`long tasks on the UI thread, whole run: ${long.length} over 50 ms, ${sorted.filter((d) => d > 100).length} over 100 ms, longest ${sorted.slice(0, 5).map((d) => d.toFixed(0)).join(', ')} ms`);
  for (const [name, from, to, exempt] of jobs) {
    const inJob = long.filter(([t, d]) => t + d > from && t < to).map(([, d]) => d).sort((a, b) => b - a);
    const longest = inJob[0] ?? 0;
    const what = `${name}: ${((to - from) / 1000).toFixed(1)} s, ${inJob.length} tasks over 50 ms, longest ${inJob.slice(0, 5).map((d) => d.toFixed(0)).join(', ') || '–'} ms`;
    if (exempt) console.log(`(measured, not checked: ${exempt}) ${what}`);
    else check(longest <= 200 && inJob.filter((d) => d > 100).length <= 1, `no task of the job over 100 ms but one under 200 ms: ${what}`);
  }

  // GPU device loss, last since it ends the app: the page says so over the canvas and
  // offers a reload instead of a frozen canvas.
  const devices = await page.evaluate(() => { window.__gpuDevices.forEach((d) => d.destroy()); return window.__gpuDevices.length; });
  const box = await page.waitForSelector('#fatal', { state: 'visible', timeout: 30000 });
  const said = await box.innerText();
  const covers = await page.evaluate(() => {
    const r = document.getElementById('fatal').getBoundingClientRect();
    return r.width >= window.innerWidth && r.height >= window.innerHeight;
  });
  check(devices === 1 && /GPU device was lost/.test(said) && /Reload/.test(said) && covers,
    `a destroyed GPU device (${devices}) gets a message over the whole canvas with a Reload button ("${said.split('\n')[0]}")`);
  await page.screenshot({ path: path.join(out, 'device_lost.png') });

  // Reload, as the message offers: the new page's worker reads the body's context its
  // predecessor kept in the Cache API instead of building it again.
  if (builtContext) {
    await page.reload();
    s = await waitFor((s) => typeof s.worker_body_context === 'string' && s.worker_body_context !== '', "the reloaded page's worker warm-up", 180000);
    check(/^read from the browser's cache in \d+ ms \(\d+\.\d MB\)$/.test(s.worker_body_context),
      `after a reload the worker reads the body's context from the Cache API ("${s.worker_body_context}"; the first page's: "${builtContext}")`);
  }
} catch (e) {
  console.log(`FAIL ${e.stack ?? e}`);
  failures++;
} finally {
  if (failures) await page.screenshot({ path: path.join(out, 'failure.png') }).catch(() => {});
  await browser.close();
}
console.log(failures ? `browser e2e: ${failures} check(s) failed` : 'browser e2e: all checks passed');
process.exit(failures ? 1 : 0);
