// Random-action soak of the GETAvatar web app in headless Chromium (WebGPU on SwiftShader).
//
//   cargo xtask serve            # another shell; or any server of dist/
//   cd tests/e2e && node soak.e2e.mjs [actions, default 300] [seed, default 1]
//
// Seeded and reproducible: the same seed gives the same action list. Actions are drawn from:
// poses, joints (extreme values, and numbers JSON cannot carry finitely), camera (extreme
// values), views, resolutions (valid and not), betas, generate, retexture, show, downloads,
// photo bytes (random, and the e2e photo's PNG), motion files (random bytes, the AMASS
// fixture), motion playback, malformed JSON. After each action the app must answer: a refused
// command carrying a fresh marker must come back among its messages within 120 s. At the end:
//  - zero panics (no overlay from `getavatarFatal`), zero console errors, zero page errors;
//  - after a warm-up that does every kind of action once, the JS heap, the wasm memory and the live GPU buffers
//    (created − destroyed, counted by wrapping GPUDevice.createBuffer and GPUBuffer.destroy)
//    at the end are at most 1.2 × their values after the warm-up (+ 4 MB of slack for the heap).
// Prints the action counts per kind, peak memory and the longest UI-thread tasks.
// GETAVATAR_URL (default http://127.0.0.1:8080/), GETAVATAR_CHROMIUM and GETAVATAR_OUT as
// for app.e2e.mjs.

import { appStatus, launchChromium } from './browser.mjs';
import fs from 'node:fs';
import path from 'node:path';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const out = process.env.GETAVATAR_OUT ?? 'out';
fs.mkdirSync(out, { recursive: true });
const N = Number(process.argv[2] ?? 300);
const SEED = Number(process.argv[3] ?? 1);

let failures = 0;
function check(cond, msg) {
  console.log(`${cond ? 'ok  ' : 'FAIL'} ${msg}`);
  if (!cond) failures++;
}

// mulberry32: a small seeded generator (the action list depends on the seed only).
function rng(seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}
const rand = rng(SEED);
const pick = (xs) => xs[Math.floor(rand() * xs.length)];
const extreme = () => pick([0, 1e-30, -1e-30, 1, -1, 3.1416, -7, 1e6, -1e6, 3.4e38, -3.4e38, rand() * 20 - 10]);

const POSES = ['standing', 'a_pose', 'walking', 'sitting', 'arms_up', 'kick', 'no_such_pose'];
const JOINTS = ['left_elbow', 'right_knee', 'spine1', 'neck', 'left_hip', 'pelvis', 'nope'];
const photoPng = fs.readFileSync(new URL('./fixtures/kick_clothed.png', import.meta.url));
const amass = fs.readFileSync(new URL('../fixtures/motion/amass_sample.npz', import.meta.url));
const randomBytes = (n) => Array.from({ length: n }, () => Math.floor(rand() * 256));

// Each kind: a weight and a function that returns what to send ({cmd} JSON, {raw} text,
// {photo} or {motion} bytes). Expensive GPU work (generation, photo fits) is rare.
const KINDS = {
  pose: [10, () => ({ cmd: { pose: pick(POSES) } })],
  joint: [12, () => ({ cmd: { joint: pick(JOINTS), value: [extreme(), extreme(), extreme()] } })],
  joint_nonfinite: [3, () => ({ raw: `{"joint":"${pick(JOINTS)}","value":[${pick(['1e999', '-1e999', 'NaN', 'null'])},0,0]}` })],
  camera: [12, () => ({ cmd: { yaw: extreme(), pitch: extreme(), radius: pick([0, 0.01, 2.3, 50, -1, 1e9]) } })],
  view: [8, () => ({ cmd: { view: pick(['rgb', 'normal', 'mask', 'bogus']) } })],
  res: [4, () => ({ cmd: { res: pick([512, 1024, 0, 7, 100000]) } })],
  betas: [6, () => ({ cmd: { betas: Array.from({ length: pick([0, 1, 10, 300]) }, extreme) } })],
  show: [4, () => ({ cmd: { show: pick(['body', 'avatar', 'nothing']) } })],
  reset_camera: [2, () => ({ cmd: { reset_camera: true } })],
  download: [3, () => ({ cmd: { download: true } })],
  generate: [2, () => ({ cmd: { generate: { seed_geo: Math.floor(rand() * 1e9), seed_tex: Math.floor(rand() * 1e9), psi: pick([0, 0.7, 1, -5, 100]) } } })],
  retexture: [2, () => ({ cmd: { retexture: { seed_tex: Math.floor(rand() * 1e9) } } })],
  photo_random: [4, () => ({ photo: randomBytes(pick([0, 1, 64, 4096])), name: pick(['x.png', 'y.jpg', 'z.webp']) })],
  photo_real: [1, () => ({ photo: [...photoPng], name: 'kick_clothed.png' })],
  photo_fit: [2, () => ({ cmd: { photo_fit: pick(['cancel', 'refit', 'close', 'bogus']) } })],
  motion_random: [3, () => ({ motion: randomBytes(pick([0, 22, 512])), name: 'm.npz' })],
  motion_real: [1, () => ({ motion: [...amass], name: 'amass_sample.npz' })],
  motion_play: [6, () => ({ cmd: { motion: { clip: pick(['walk', 'wave', 'amass_sample', 'none']), play: rand() < 0.5, time: extreme(), speed: extreme() } } })],
  texture_res: [2, () => ({ cmd: { texture_res: pick([64, 256, 0, 1 << 20]) } })],
  reconstruct_cancel: [1, () => ({ cmd: { reconstruct_cancel: true } })],
  malformed: [4, () => ({ raw: pick(['', '{', '[]', 'null', '{"pose":', '{"yaw":"x"}', '{"unknown":1}', '\u0000']) })],
};
const kinds = Object.entries(KINDS);
const total = kinds.reduce((s, [, [w]]) => s + w, 0);
function drawKind() {
  let r = rand() * total;
  for (const [k, [w]] of kinds) {
    if ((r -= w) < 0) return k;
  }
  return kinds[0][0];
}
// The warm-up does every kind once (the allocations a session makes at all: an avatar, a
// fitted photo, a motion clip, a texture bake), then N seeded random actions follow.
const warmup = [
  { kind: 'generate', cmd: { generate: { seed_geo: 1, seed_tex: 2, psi: 0.7 } } },
  { kind: 'texture_res', cmd: { texture_res: 256 } },
  { kind: 'show', cmd: { show: 'avatar' } },
  { kind: 'download', cmd: { download: true } },
  ...Object.keys(KINDS).map((kind) => ({ kind, ...KINDS[kind][1]() })),
];
const actions = [...warmup, ...Array.from({ length: N }, () => {
  const kind = drawKind();
  return { kind, ...KINDS[kind][1]() };
})];
const WARMUP = warmup.length;

const browser = await launchChromium(['--enable-precise-memory-info']);
const context = await browser.newContext({ viewport: { width: 1280, height: 800 }, acceptDownloads: true });
const page = await context.newPage();
await page.addInitScript(() => {
  window.__soak = { buffers: 0, bufferBytes: 0, longTasks: [] };
  new PerformanceObserver((list) => {
    for (const e of list.getEntries()) window.__soak.longTasks.push([e.startTime, e.duration]);
  }).observe({ type: 'longtask', buffered: true });
  if (window.GPUDevice) {
    const create = GPUDevice.prototype.createBuffer;
    GPUDevice.prototype.createBuffer = function (desc) {
      const b = create.call(this, desc);
      window.__soak.buffers++;
      window.__soak.bufferBytes += desc.size;
      const destroy = b.destroy.bind(b);
      let live = true;
      b.destroy = () => {
        if (live) {
          live = false;
          window.__soak.buffers--;
          window.__soak.bufferBytes -= desc.size;
        }
        return destroy();
      };
      return b;
    };
  }
});
const consoleErrors = [];
page.on('console', (m) => { if (m.type() === 'error') consoleErrors.push(m.text()); });
page.on('pageerror', (e) => consoleErrors.push(`pageerror: ${e.message}`));
page.on('download', (d) => d.cancel().catch(() => {}));

const { status, waitFor: poll } = appStatus(page, { intervalMs: 100, timeoutMs: 600000 });
// On a timeout, what the app was doing.
const waitFor = (pred, what, timeout) => poll(pred, what, timeout, (s) => JSON.stringify(s && {
  generating: s.generating, photo: s.photo.state, showing: s.showing, renders: s.renders, fps: s.fps, errors: s.errors.slice(-3),
}));
const memory = () => page.evaluate(() => ({
  heap: performance.memory?.usedJSHeapSize ?? 0,
  wasm: window.getavatar.wasmMemoryBytes?.() ?? 0,
  buffers: window.__soak.buffers,
  bufferBytes: window.__soak.bufferBytes,
}));
const gc = async () => {
  const cdp = await context.newCDPSession(page);
  await cdp.send('HeapProfiler.collectGarbage');
  await cdp.detach();
};

try {
  await page.goto(url);
  await waitFor((s) => s.ready && !/loading/.test(s.model), 'the app and its model');
  const counts = {};
  let warm = null;
  let peak = { heap: 0, wasm: 0, buffers: 0, bufferBytes: 0 };
  let marker = 0;
  const t0 = Date.now();
  const spans = []; // [kind, page time at the action's start]
  for (let i = 0; i < actions.length; i++) {
    const a = actions[i];
    spans.push([a.kind, await page.evaluate(() => performance.now())]);
    counts[a.kind] = (counts[a.kind] ?? 0) + 1;
    if (a.cmd) await page.evaluate((c) => window.getavatar.command(c), a.cmd);
    else if (a.raw !== undefined) await page.evaluate((r) => window.getavatar.commandJson(r), a.raw);
    else if (a.photo) await page.evaluate(([b, n]) => window.getavatar.photo(new Uint8Array(b), n), [a.photo, a.name]);
    else if (a.motion) await page.evaluate(([b, n]) => window.getavatar.motion(new Uint8Array(b), n), [a.motion, a.name]);
    // The app answers: a command it refuses, with a fresh marker in it, comes back among
    // its messages through the frame loop (a yaw would not: the photo's camera holds the
    // view while a fitted photo is shown).
    marker++;
    await page.evaluate((m) => window.getavatar.commandJson(`{"soak_marker":${m}}`), marker);
    // A panic stops the frame loop, so the marker would never come back: stop waiting then.
    await waitFor((s) => s.errors.some((e) => e.includes(`"soak_marker":${marker}}`))
      || consoleErrors.some((e) => e.includes('panicked')),
    `the app's answer after action ${i} (${a.kind})`, 120000);
    if (await page.$('#fatal')) throw new Error(`the app stopped after action ${i} (${a.kind}): ${await page.innerText('#fatal')}`);
    // The warm-up's avatar exists before its download, so that download bakes a texture.
    if (i < WARMUP && a.kind === 'generate') await waitFor((s) => !s.generating && s.generations > 0, 'the warm-up generation', 300000);
    const m = await memory();
    for (const k of Object.keys(peak)) peak[k] = Math.max(peak[k], m[k]);
    if (i + 1 === WARMUP) {
      await waitFor((s) => !s.generating && s.photo.state !== 'fitting', 'a quiet app after the warm-up');
      await gc();
      warm = await memory();
      console.log(`after ${WARMUP} warm-up actions: ${JSON.stringify(warm)}`);
    }
    if ((i + 1) % 50 === 0) console.log(`${i + 1}/${actions.length} actions, ${((Date.now() - t0) / 1000).toFixed(0)} s, ${JSON.stringify(m)}`);
  }
  await waitFor((s) => !s.generating && s.photo.state !== 'fitting', 'a quiet app at the end');
  await gc();
  const end = await memory();
  const s = await status();
  console.log(`actions per kind: ${JSON.stringify(counts)}`);
  console.log(`end: ${JSON.stringify(end)}; peak: ${JSON.stringify(peak)}; ${s.errors_total} messages in all, ${s.generations} generations`);
  const long = await page.evaluate(() => window.__soak.longTasks);
  const durations = long.map(([, d]) => d).sort((a, b) => b - a);
  console.log(`long tasks: ${long.length} over 50 ms, longest ${durations.slice(0, 5).map((d) => d.toFixed(0)).join(', ')} ms`);
  // Which actions they fell in (the last action started before each task): longest per kind.
  const byKind = {};
  for (const [start, d] of long) {
    let k = 'before the first action';
    for (const [kind, t] of spans) if (t <= start) k = kind;
    byKind[k] = [Math.max(byKind[k]?.[0] ?? 0, d), (byKind[k]?.[1] ?? 0) + 1];
  }
  console.log(`long tasks by the action they fell in (longest ms, count): ${Object.entries(byKind).sort((a, b) => b[1][0] - a[1][0]).map(([k, [m, n]]) => `${k} ${m.toFixed(0)} (${n})`).join(', ')}`);
  check(true, `${WARMUP} warm-up + ${N} seeded random actions (seed ${SEED}) answered, no panic`);
  check(consoleErrors.length === 0, `zero console errors (${consoleErrors.length}: ${consoleErrors.slice(0, 3).join(' | ')})`);
  check(end.heap <= 1.2 * warm.heap + 4e6, `JS heap ${(end.heap / 1e6).toFixed(1)} MB at the end vs ${(warm.heap / 1e6).toFixed(1)} MB after the warm-up (≤ 1.2× + 4 MB)`);
  check(end.wasm <= 1.2 * warm.wasm, `wasm memory ${(end.wasm / 1e6).toFixed(1)} MB vs ${(warm.wasm / 1e6).toFixed(1)} MB (≤ 1.2×)`);
  check(end.buffers <= 1.2 * warm.buffers && end.bufferBytes <= 1.2 * warm.bufferBytes,
    `live GPU buffers ${end.buffers} (${(end.bufferBytes / 1e6).toFixed(1)} MB) vs ${warm.buffers} (${(warm.bufferBytes / 1e6).toFixed(1)} MB) (≤ 1.2×)`);
} catch (e) {
  console.log(`FAIL ${e.stack ?? e}`);
  failures++;
} finally {
  await page.screenshot({ path: path.join(out, 'soak.png') }).catch(() => {});
  await browser.close();
}
console.log(failures ? `soak: ${failures} check(s) failed` : 'soak: all checks passed');
process.exit(failures ? 1 : 0);
