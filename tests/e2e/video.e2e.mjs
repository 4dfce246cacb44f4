// Browser end-to-end test of "Motion from video…", as a user runs it: headless Chromium,
// WebGPU on SwiftShader, the video chosen in the page's file input, decoded by the browser,
// MediaPipe Pose (tracking mode) in the page's worker, the clip's fit on the page's CPU.
//
//  - bad input: a 0-byte file, a text file named .mp4, a 20-minute video, a 4K video, a
//    video without a person → one clear message each, no clip added, the app as it was;
//  - fixtures/video/dance.webm (2 s at 30 fps, 384², the synthetic dance of
//    tests/tests/video_motion.rs: a squat, a jump with a quarter turn, swinging arms): the
//    clip "dance" appears among the motions and plays on the body; no request leaves the page
//    while the video is read and fitted (only the app's own files, GET);
//  - the animated .glb with the clip passes the Khronos validator, and three.js
//    (GLTFLoader + AnimationMixer) plays it: the pelvis rises in the jump and the body turns
//    by about a quarter; the .vrma of the clip downloads and validates;
//  - Cancel while fitting (the dance again, by URL at 10 frames/s) keeps the frames fitted so
//    far as a shorter clip;
//  - no console error. Prints the reading and fitting rates (docs/benchmarks.md).
//
//   cargo xtask serve --port 8765 --no-build &
//   cd tests/e2e && GETAVATAR_URL=http://127.0.0.1:8765/ node video.e2e.mjs

import fs from 'node:fs';
import path from 'node:path';
import validator from 'gltf-validator';
import { launchChromium, appStatus } from './browser.mjs';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const out = path.join(process.env.GETAVATAR_OUT ?? 'out', 'video');
fs.mkdirSync(out, { recursive: true });
const fixture = (f) => fs.readFileSync(new URL(`./fixtures/video/${f}`, import.meta.url));

let failures = 0;
function check(cond, msg) {
  console.log(`${cond ? 'ok  ' : 'FAIL'} ${msg}`);
  if (!cond) failures++;
}

const browser = await launchChromium();
const context = await browser.newContext({ viewport: { width: 1280, height: 800 }, deviceScaleFactor: 1, acceptDownloads: true });
const page = await context.newPage();
const consoleErrors = [];
page.on('console', (m) => { if (m.type() === 'error') consoleErrors.push(m.text()); });
page.on('pageerror', (e) => consoleErrors.push(`pageerror: ${e.message}`));
const requests = [];
context.on('request', (r) => requests.push({ url: r.url(), method: r.method() }));
await page.goto(url);
const origin = new URL(url).origin;
const { status, waitFor } = appStatus(page);
await waitFor((s) => s.ready, 'the app', 300000);

// Videos by URL (the automation hook's way), as if they were files next to the page.
await page.route('**/videos/*', (route) => {
  const name = decodeURIComponent(route.request().url().split('/').pop());
  return route.fulfill({ status: 200, contentType: 'video/webm', body: fixture(name) });
});

/** The outcome of the video started after `before` (the status' video counters then). */
async function outcome(before, name, timeout = 900000) {
  return (await waitFor((s) => s.video.clips_made > before.clips_made || s.video.failures > before.failures,
    `the video ${name}`, timeout, (s) => JSON.stringify(s?.video))).video;
}

/** Choose a file in "Motion from video…"'s input (read at the panel's rate, 15 frames/s). */
async function chooseVideo(name, buffer, mimeType = 'video/webm') {
  const before = (await status()).video;
  await page.setInputFiles('#getavatar_video_input', { name, mimeType, buffer });
  return outcome(before, name);
}

/** `{"video":{"url":"videos/<name>","fps":10}}`. */
async function commandVideo(name) {
  const before = (await status()).video;
  await page.evaluate((n) => window.getavatar.command({ video: { url: `videos/${n}`, fps: 10 } }), name);
  return outcome(before, name);
}

try {
  // --- bad input: one message each, nothing added -----------------------------------
  const clipsBefore = (await status()).motion.clips;
  const bad = [
    ['empty.mp4', Buffer.alloc(0), 'video/mp4', /empty/],
    ['notes.mp4', Buffer.from('these are not the frames you are looking for\n'.repeat(50)), 'video/mp4', /not a video/],
    ['long.webm', fixture('long.webm'), 'video/webm', /20:00 long.*60 s/],
    ['uhd.webm', fixture('uhd.webm'), 'video/webm', /3840×2160/],
    // 0.4 s of a noisy wall, read at 10 frames/s.
    ['nobody.webm', null, null, /no person was found in any of its 4 frames/],
  ];
  for (const [name, bytes, mime, want] of bad) {
    const errorsBefore = (await status()).errors_total;
    const t0 = Date.now();
    const v = bytes ? await chooseVideo(name, bytes, mime) : await commandVideo(name);
    const s = await status();
    check(v.state === 'failed' && want.test(v.message) && v.message.includes(name),
      `${name}: "${v.message}" (${((Date.now() - t0) / 1000).toFixed(1)} s)`);
    check(s.errors_total === errorsBefore + 1 && s.ready && JSON.stringify(s.motion.clips) === JSON.stringify(clipsBefore),
      `${name}: one message, no clip added (${s.errors_total - errorsBefore} messages, clips ${s.motion.clips.join(', ')})`);
  }

  // --- the dance: a clip that plays ------------------------------------------------------
  const mark = requests.length;
  const t0 = Date.now();
  const v = await chooseVideo('dance.webm', fixture('dance.webm'));
  const wall = (Date.now() - t0) / 1000;
  const during = requests.slice(mark);
  const foreign = during.filter((r) => r.method !== 'GET' || !(r.url.startsWith(origin) || r.url.startsWith(`blob:${origin}`)));
  check(foreign.length === 0, `no request leaves the page while the video is processed (${during.length} requests, all GETs of the app's files: ${[...new Set(during.map((r) => r.url.replace(origin, '').split('?')[0]))].slice(0, 6).join(' ')})`);
  check(v.state === 'done' && v.frames === 30 && v.fitted === 30 && v.lost <= 3,
    `dance.webm: ${v.frames} frames read at ${v.read_fps} fps, ${v.fitted} fitted, ${v.lost} lost (≤ 3): "${v.message}"`);
  console.log(`video rates: reading ${(v.frames / (v.read_ms / 1000)).toFixed(2)} frames/s (${(v.read_ms / 1000).toFixed(1)} s), `
    + `fitting ${(v.fitted / (v.fit_ms / 1000)).toFixed(2)} frames/s (${(v.fit_ms / 1000).toFixed(1)} s), ${wall.toFixed(0)} s in all`);
  let s = await status();
  check(s.motion.clips.includes('dance') && s.motion.clip === 'dance' && s.motion.playing,
    `the clip "dance" is among the motions and plays (clip ${s.motion.clip}, playing ${s.motion.playing})`);
  check(Math.abs(s.motion.duration - 2.0) <= 0.1 && s.motion.frames >= 58,
    `it lasts as long as the video (${s.motion.duration.toFixed(2)} s, ${s.motion.frames} frames at 30 fps)`);
  // SwiftShader on a loaded CI machine draws a frame every 0.3–0.5 s: wait for four frames
  // (up to 8 s) rather than counting the frames of a fixed 1.5 s.
  const r0 = s.renders;
  const t1 = s.motion.time;
  const tPlay = Date.now();
  do {
    await page.waitForTimeout(500);
    s = await status();
  } while (!(s.renders > r0 + 3 && s.motion.time !== t1) && Date.now() - tPlay < 8000);
  check(s.renders > r0 + 3 && s.motion.time !== t1 && s.pose === 'motion dance',
    `the body plays it (${s.renders - r0} renders in ${((Date.now() - tPlay) / 1000).toFixed(1)} s, time ${t1.toFixed(2)} → ${s.motion.time.toFixed(2)} s, pose "${s.pose}")`);

  // --- the downloads ---------------------------------------------------------------
  await page.evaluate(() => window.getavatar.command({ motion: { include: ['dance'], play: false } }));
  const [dl] = await Promise.all([page.waitForEvent('download'), page.evaluate(() => window.getavatar.command({ download_animated: true }))]);
  const glbPath = path.join(out, dl.suggestedFilename());
  await dl.saveAs(glbPath);
  check(/dance/.test(dl.suggestedFilename()), `the animated download is named after the clip: ${dl.suggestedFilename()}`);
  const glb = fs.readFileSync(glbPath);
  const report = await validator.validateBytes(new Uint8Array(glb));
  check(report.issues.numErrors === 0, `glTF-Validator: ${report.issues.numErrors} errors, ${report.info?.animationCount} animations`);
  const [dlv] = await Promise.all([page.waitForEvent('download'), page.evaluate(() => window.getavatar.command({ download_vrma: true }))]);
  const vrmaPath = path.join(out, dlv.suggestedFilename());
  await dlv.saveAs(vrmaPath);
  const vr = await validator.validateBytes(new Uint8Array(fs.readFileSync(vrmaPath)));
  check(dlv.suggestedFilename() === 'getavatar_dance.vrma' && vr.issues.numErrors === 0,
    `the clip's VRM animation: ${dlv.suggestedFilename()}, ${vr.issues.numErrors} validator errors`);

  // three.js plays the clip: the pelvis rises in the jump, the body turns by about a quarter.
  const three = path.resolve('node_modules/three');
  const tp = await context.newPage();
  await tp.route('http://getavatar.test/**', (route) => {
    const u = new URL(route.request().url());
    if (u.pathname === '/index.html') {
      return route.fulfill({ contentType: 'text/html', body: '<!doctype html><script type="importmap">{"imports":{"three":"/three/build/three.module.js","three/addons/":"/three/examples/jsm/"}}</script><body></body>' });
    }
    if (u.pathname.startsWith('/three/')) return route.fulfill({ contentType: 'text/javascript', body: fs.readFileSync(path.join(three, u.pathname.slice(7))) });
    if (u.pathname === '/clip.glb') return route.fulfill({ contentType: 'model/gltf-binary', body: glb });
    return route.fulfill({ status: 404, body: 'not found' });
  });
  await tp.goto('http://getavatar.test/index.html');
  const played = await tp.evaluate(async () => {
    const THREE = await import('three');
    const { GLTFLoader } = await import('three/addons/loaders/GLTFLoader.js');
    const gltf = await new GLTFLoader().loadAsync('/clip.glb');
    const clip = gltf.animations.find((a) => a.name === 'dance');
    if (!clip) return { names: gltf.animations.map((a) => a.name) };
    let pelvis = null;
    gltf.scene.traverse((o) => { if (o.isBone && o.name === 'pelvis') pelvis = o; });
    const mixer = new THREE.AnimationMixer(gltf.scene);
    mixer.clipAction(clip).play();
    const ys = [];
    const yaws = [];
    const p = new THREE.Vector3();
    const q = new THREE.Quaternion();
    const fwd = new THREE.Vector3();
    for (let t = 0; t <= clip.duration; t += 1 / 30) {
      mixer.setTime(t);
      gltf.scene.updateMatrixWorld(true);
      pelvis.getWorldPosition(p);
      pelvis.getWorldQuaternion(q);
      fwd.set(0, 0, 1).applyQuaternion(q);
      ys.push(p.y);
      yaws.push(Math.atan2(fwd.x, fwd.z));
    }
    return { duration: clip.duration, ys, yaws };
  });
  await tp.close();
  if (!played.ys) {
    check(false, `three.js finds the clip "dance" (animations: ${played.names})`);
  } else {
    const rise = Math.max(...played.ys) - played.ys[0];
    const dip = played.ys[0] - Math.min(...played.ys);
    let turn = 0;
    for (const y of played.yaws) {
      let d = y - played.yaws[0];
      d = Math.atan2(Math.sin(d), Math.cos(d));
      turn = Math.max(turn, Math.abs(d));
    }
    check(Math.abs(played.duration - 2.0) < 0.1, `three.js: the clip lasts ${played.duration.toFixed(2)} s`);
    check(rise >= 0.05 && dip >= 0.05, `three.js: the pelvis squats ${(100 * dip).toFixed(1)} cm and jumps ${(100 * rise).toFixed(1)} cm (≥ 5 each)`);
    check(turn >= 1.0 && turn <= 1.9, `three.js: the body turns ${(turn * 180 / Math.PI).toFixed(0)}° (a quarter turn in the dance: 57–109°)`);
  }

  // --- Cancel while fitting keeps the frames fitted ---------------------------------------
  const before = (await status()).video;
  await page.route('**/videos/dance_cut.webm', (route) => route.fulfill({ status: 200, contentType: 'video/webm', body: fixture('dance.webm') }));
  await page.evaluate(() => window.getavatar.command({ video: { url: 'videos/dance_cut.webm', fps: 10 } }));
  await waitFor((st) => st.video.state === 'fitting' && st.video.fitted >= 6, 'the second fit to pass 6 frames', 900000,
    (st) => JSON.stringify(st?.video));
  await page.evaluate(() => window.getavatar.command({ video_cancel: true }));
  const c = await outcome(before, 'dance_cut.webm', 120000);
  s = await status();
  check(c.state === 'done' && c.fitted >= 6 && c.fitted < 20 && s.motion.clip === 'dance_cut'
      && s.motion.frames < 58 && s.motion.notes.some((n) => n.includes('cancelled')),
    `Cancel keeps the ${c.fitted} frames fitted as the clip "${s.motion.clip}" (${s.motion.frames} frames at 30 fps; "${s.motion.notes[0]}")`);
} catch (e) {
  console.log(`FAIL ${e.stack ?? e}`);
  failures++;
}
check(consoleErrors.length === 0, `no console error (${consoleErrors.slice(0, 3).join(' | ')})`);
await browser.close();
console.log(failures ? `video e2e: ${failures} check(s) failed` : 'video e2e: all checks passed');
process.exit(failures ? 1 : 0);
