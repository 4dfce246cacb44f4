// Browser benchmark of a new identity (Generate: mapping, synthesis, the posed grid, DMTet,
// normals and colours, rigging) on each device: `cpu` in the reconstruction worker on burn's
// NdArray, `webgpu` on the page's WebGPU device (`auto`, the app's default, takes the first on
// a software adapter). Per device, one generation first (a fresh worker starts and builds its
// body context and posed grid; the page compiles its kernels), then N seed pairs: the stage
// table's medians (host ms, waits on GPU read-backs, read-backs, dispatches), the median
// milliseconds per new identity and the devices' ratio, all in one run. Also the page's own
// start-up line (the model's loading, the body's context, the kernels' warm-up).
//
//   cargo xtask serve            # another shell; or any server of dist/
//   cd tests/e2e && node bench_generate.mjs [identities per device, default 5] [devices, default cpu,webgpu]
//
// GETAVATAR_URL (default http://127.0.0.1:8080/) and GETAVATAR_CHROMIUM as for app.e2e.mjs.
// PROFILE=1 also samples the page's CPU over the measured generations and prints the
// functions with the most self time (names need GETAVATAR_KEEP_NAMES=1 cargo xtask build-web).
// Headless Chromium runs WebGPU on SwiftShader (a CPU); on a real GPU re-measure.

import { appStatus, launchChromium } from './browser.mjs';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const count = Number(process.argv[2] ?? 5);
const devices = (process.argv[3] ?? 'cpu,webgpu').split(',');
if (!(count >= 1) || devices.some((d) => !['auto', 'cpu', 'webgpu'].includes(d))) {
  console.error('usage: node bench_generate.mjs [identities ≥ 1] [devices: auto,cpu,webgpu]');
  process.exit(2);
}
const browser = await launchChromium();
const context = await browser.newContext({ viewport: { width: 1280, height: 800 } });
const page = await context.newPage();
page.on('console', (m) => {
  if (m.type() === 'error') console.log(`console error: ${m.text()}`);
  if (/^the model: /.test(m.text())) console.log(m.text());
});
const { status, waitFor } = appStatus(page, { timeoutMs: 900000 });
const t0 = Date.now();
await page.goto(url);
const st = await waitFor((s) => s.ready && s.model && !s.model.startsWith('loading'), 'the app and its model');
console.log(`model ready ${((Date.now() - t0) / 1000).toFixed(1)} s after the page was opened: ${st.model}`);

async function generate(seedGeo, seedTex, device) {
  const before = (await status()).generations;
  const err = await page.evaluate(([g, t, device]) => window.getavatar.command({ generate: { seed_geo: g, seed_tex: t, device } }), [seedGeo, seedTex, device]);
  if (err) throw new Error(err);
  const s = await waitFor((s) => s.generations > before && !s.generating, `generation ${seedGeo}/${seedTex} on ${device}`);
  return { ms: s.last_generation_ms, on: s.last_generation_on, stages: s.last_generation_stages?.stages ?? [] };
}

const prof = process.env.PROFILE ? await context.newCDPSession(page) : null;
const median = (xs) => [...xs].sort((a, b) => a - b)[Math.floor(xs.length / 2)];
const results = {};
for (const device of devices) {
  const first = await generate(100, 101, device);
  if (prof) {
    await prof.send('Profiler.enable');
    await prof.send('Profiler.setSamplingInterval', { interval: 200 });
    await prof.send('Profiler.start');
  }
  const runs = [];
  for (let k = 0; k < count; k++) runs.push(await generate(2 * k + 1, 2 * k + 2, device));
  if (prof) {
    // Self time by function over the measured generations (idle and the status polls included).
    const { profile } = await prof.send('Profiler.stop');
    const self = new Map();
    const dt = new Map();
    profile.samples.forEach((id, i) => dt.set(id, (dt.get(id) ?? 0) + (profile.timeDeltas[i] ?? 0) / 1000));
    for (const n of profile.nodes) {
      const name = n.callFrame.functionName || `(${n.callFrame.url.split('/').pop() || 'anonymous'})`;
      self.set(name, (self.get(name) ?? 0) + (dt.get(n.id) ?? 0));
    }
    const top = [...self].filter(([n]) => n !== '(idle)' && n !== '(program)').sort((a, b) => b[1] - a[1]).slice(0, 30);
    console.log(`${device}: the page's CPU self time over ${count} generations (ms), top functions:`);
    for (const [n, ms] of top) console.log(`${ms.toFixed(1).padStart(9)}  ${n.slice(0, 150)}`);
  }
  results[device] = { first, runs, median: median(runs.map((r) => r.ms)) };
  console.log(`\n${device}: on ${first.on}; the first ${first.ms.toFixed(0)} ms, then ${runs.map((r) => r.ms.toFixed(0)).join(', ')} ms (median ${results[device].median.toFixed(0)})`);
  console.log('stage               host ms   GPU wait ms   read-backs   dispatches   (medians)');
  for (const [i, row] of runs[0].stages.entries()) {
    const col = (f) => median(runs.map((r) => f(r.stages[i] ?? row)));
    console.log(`${row.stage.padEnd(18)} ${col((x) => x.host_ms).toFixed(1).padStart(8)} ${col((x) => x.gpu_wait_ms).toFixed(1).padStart(13)} ${String(row.readbacks).padStart(12)} ${String(row.dispatches).padStart(12)}`);
  }
}
console.log(`\na new identity in the browser (page adapter ${st.adapter}, ${st.backend}), ${count} per device after one each:`);
console.log('| device | ran on | first ms | median ms |');
console.log('|---|---|---|---|');
for (const device of devices) {
  const r = results[device];
  console.log(`| ${device} | ${r.first.on} | ${r.first.ms.toFixed(0)} | ${r.median.toFixed(0)} |`);
}
if (results.cpu && results.webgpu) {
  console.log(`WebGPU / CPU: the first ${(results.webgpu.first.ms / results.cpu.first.ms).toFixed(1)}×, the median ${(results.webgpu.median / results.cpu.median).toFixed(1)}×`);
}
await browser.close();
