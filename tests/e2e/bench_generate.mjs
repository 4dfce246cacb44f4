// Browser benchmark of a new identity: the app's generation stage table (host ms,
// waits on GPU read-backs, read-backs, dispatches) for several seed pairs after a warm-up,
// and the median host time per new identity.
//
//   cargo xtask serve            # another shell; or any server of dist/
//   cd tests/e2e && node bench_generate.mjs [identities, default 5]
//
// GETAVATAR_URL (default http://127.0.0.1:8080/) and GETAVATAR_CHROMIUM as for app.e2e.mjs.
// PROFILE=1 also samples the page's CPU over the measured generations and prints the
// functions with the most self time (names need GETAVATAR_KEEP_NAMES=1 cargo xtask build-web).
// Headless Chromium runs WebGPU on SwiftShader (a CPU): the host column is wasm's own work
// plus what each GPU command costs to record and submit; on a real GPU re-measure.

import { appStatus, launchChromium } from './browser.mjs';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const count = Number(process.argv[2] ?? 5);
if (!(count >= 1)) {
  console.error('usage: node bench_generate.mjs [identities ≥ 1]');
  process.exit(2);
}
const browser = await launchChromium();
const context = await browser.newContext({ viewport: { width: 1280, height: 800 } });
const page = await context.newPage();
const { status, waitFor } = appStatus(page, { timeoutMs: 900000 });
await page.goto(url);
const st = await waitFor((s) => s.ready, 'the app');
await waitFor((s) => s.model && !s.model.startsWith('loading'), 'generator weights');

async function generate(seedGeo, seedTex) {
  const before = (await status()).generations;
  const err = await page.evaluate(([g, t]) => window.getavatar.command({ generate: { seed_geo: g, seed_tex: t } }), [seedGeo, seedTex]);
  if (err) throw new Error(err);
  const s = await waitFor((s) => s.generations > before && !s.generating, `generation ${seedGeo}/${seedTex}`);
  return s.last_generation_stages?.stages ?? [];
}

await generate(100, 101); // warm-up: shader compilation, first allocations
const prof = process.env.PROFILE ? await context.newCDPSession(page) : null;
if (prof) {
  await prof.send('Profiler.enable');
  await prof.send('Profiler.setSamplingInterval', { interval: 200 });
  await prof.send('Profiler.start');
}
const runs = [];
for (let k = 0; k < count; k++) runs.push(await generate(2 * k + 1, 2 * k + 2));
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
  const top = [...self].filter(([n]) => n !== '(idle)' && n !== '(program)').sort((a, b) => b[1] - a[1]).slice(0, 40);
  console.log(`CPU self time over ${count} generations (ms), top functions:`);
  for (const [n, ms] of top) console.log(`${ms.toFixed(1).padStart(9)}  ${n.slice(0, 150)}`);
}
const median = (xs) => [...xs].sort((a, b) => a - b)[Math.floor(xs.length / 2)];
console.log(`a new identity in the browser (${st.adapter}, ${st.backend}), median of ${count} seed pairs after a warm-up:`);
console.log('stage               host ms   GPU wait ms   read-backs   dispatches');
for (const [i, row] of runs[0].entries()) {
  const col = (f) => median(runs.map((r) => f(r[i])));
  console.log(`${row.stage.padEnd(18)} ${col((x) => x.host_ms).toFixed(1).padStart(8)} ${col((x) => x.gpu_wait_ms).toFixed(1).padStart(13)} ${String(row.readbacks).padStart(12)} ${String(row.dispatches).padStart(12)}`);
}
const totals = runs.map((r) => r.reduce((a, x) => a + x.host_ms, 0));
console.log(`host ms per new identity: ${totals.map((t) => t.toFixed(0)).join(', ')} (median ${median(totals).toFixed(1)}; target ≤ 50)`);
await browser.close();
