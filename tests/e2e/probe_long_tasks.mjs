// Long tasks on the UI thread per job, with optional CPU profiles to find what
// holds the thread: phases run in order on one page, each reporting its wall time and the
// PerformanceObserver long tasks (> 50 ms) that fell in it.
//
//   cargo xtask serve --no-build      # another shell (GETAVATAR_KEEP_NAMES=1 cargo xtask build-web
//                                     # first keeps wasm function names in the profiles)
//   cd tests/e2e && PHASES=generate,photo,reconstruct,generate2 [PROFILE=1] node probe_long_tasks.mjs
//
// Phases: generate*, photo, instant* (the `instant` preset), reconstruct* (3 W+ + 1 PTI steps at 64²), download*, betas* (a new shape),
// texres* (256² texture for the downloads), show* (the avatar), cmdN (the N-th of CMDS='{…}|{…}'). With PROFILE set,
// each phase's CPU profile (Chrome's .cpuprofile) and its long tasks ([start, duration] in
// page time, `pt0` = the profile's start) go to out/long_tasks/ (GETAVATAR_URL as for app.e2e.mjs).
import { launchChromium, appStatus, greyPhoto } from './browser.mjs';
import fs from 'node:fs';
const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const outDir = new URL('./out/long_tasks/', import.meta.url);
if (process.env.PROFILE) fs.mkdirSync(outDir, { recursive: true });
const browser = await launchChromium();
const context = await browser.newContext({ viewport: { width: 1280, height: 800 } });
const page = await context.newPage();
await page.addInitScript(() => {
  window.__lt = [];
  new PerformanceObserver((list) => { for (const e of list.getEntries()) window.__lt.push([e.startTime, e.duration]); }).observe({ type: 'longtask', buffered: true });
});
page.on('console', (m) => { if (m.type() === 'error' || m.type() === 'warning') console.log('console:', m.text().slice(0, 300)); });
const { status, waitFor } = appStatus(page, { intervalMs: 100 });
await page.goto(url);
await waitFor((s) => s.ready && !/loading/.test(s.model), 'ready');
const phase = async (name, fn, done) => {
  await page.evaluate(() => { window.__lt = []; });
  const t0 = Date.now();
  await fn();
  if (done) await waitFor(done, name);
  await page.waitForTimeout(500);
  const lt = await page.evaluate(() => window.__lt);
  globalThis.__lastLt = lt;
  const d = lt.map(([, x]) => x).sort((a, b) => b - a);
  console.log(`${name}: ${((Date.now() - t0) / 1000).toFixed(1)} s, ${d.length} long tasks, longest ${d.slice(0, 8).map((x) => x.toFixed(0)).join(', ')}`);
};
const cmd = (c) => page.evaluate((c) => window.getavatar.command(c), c);
await phase('idle 2s', () => page.waitForTimeout(2000));
await phase('camera', () => cmd({ yaw: 0.5 }));
const which = (process.env.PHASES ?? 'generate,photo').split(',');
let prof = null;
if (process.env.PROFILE) { prof = await context.newCDPSession(page); await prof.send('Profiler.enable'); await prof.send('Profiler.setSamplingInterval', { interval: 1000 }); }
for (const [k, w] of which.entries()) {
  let pt0 = 0;
  if (prof) { await prof.send('Profiler.start'); pt0 = await page.evaluate(() => performance.now()); }
  if (w.startsWith('generate')) {
    const seed = 5 + which.indexOf(w);
    const g = (await status()).generations;
    await phase(w, () => cmd({ generate: { seed_geo: seed, seed_tex: seed + 1, psi: 0.7 } }), (s) => s.generations > g && !s.generating);
  } else if (w === 'photo') {
    const photo = greyPhoto();
    await phase('photo', () => page.evaluate(([b, n]) => window.getavatar.photo(new Uint8Array(b), n), [[...photo], 'p.png']), (s) => s.photo.fits > 0 || s.photo.failures > 0);
    console.log(JSON.stringify((await status()).photo).slice(0, 300));
  } else if (w.startsWith('instant')) {
    const before = (await status()).reconstruct.done;
    await phase(w, () => cmd({ reconstruct: { preset: 'instant' } }), (s) => s.reconstruct.done > before || ['failed', 'cancelled'].includes(s.reconstruct.state));
    const r = (await status()).reconstruct;
    console.log(r.state, r.message, r.finish_detail);
  } else if (w.startsWith('reconstruct')) {
    const before = (await status()).reconstruct.done;
    await phase(w, () => cmd({ reconstruct: { steps: 3, pti_steps: 1, res: 64, preview_every: 1, start: 'average' } }), (s) => s.reconstruct.done > before || ['failed', 'cancelled'].includes(s.reconstruct.state));
    const r = (await status()).reconstruct;
    console.log(r.state, r.message, r.ms_per_latent_step, r.ms_per_pivotal_step);
  } else if (w.startsWith('download')) {
    const before = (await status()).downloads;
    await phase(w, () => cmd({ download: true }), (s) => s.downloads > before);
  } else if (w.startsWith('texres')) {
    await phase(w, () => cmd({ texture_res: 256 }));
  } else if (w.startsWith('show')) {
    await phase(w, () => cmd({ show: 'avatar' }));
  } else if (/^cmd\d+$/.test(w)) {
    // CMDS='{"betas":[1,2]}|{"show":"body"}': phase cmd0 sends the first, cmd1 the second, …
    await phase(w, () => cmd(JSON.parse(process.env.CMDS.split('|')[Number(w.slice(3))])));
  } else if (w.startsWith('hugebetas')) {
    await phase(w, () => cmd({ betas: [3.4e38, -1e6, 7] }));
  } else if (w.startsWith('betas')) {
    await phase(w, () => cmd({ betas: [1.5 - which.indexOf(w) * 0.3, -1, 0.5] }));
  }
  if (prof) { const { profile } = await prof.send('Profiler.stop'); fs.writeFileSync(new URL(`${w}${k}.cpuprofile`, outDir), JSON.stringify(profile)); fs.writeFileSync(new URL(`${w}${k}.lt.json`, outDir), JSON.stringify({ pt0, lt: globalThis.__lastLt })); }
}
await browser.close();
