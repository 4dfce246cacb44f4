// What held the UI thread in a phase of `probe_long_tasks.mjs PROFILE=1`: reads the
// phase's CPU profile and long tasks from out/long_tasks/ and prints
//   1. the offset between the profile's clock and the page's (the samples ran 50–95 ms behind
//      `performance.now()`), found as the shift that puts the fewest idle samples inside long
//      tasks (OFF=… overrides it);
//   2. per long task, the functions (by name substring, CATS) its samples fell in, in ms;
//   3. over the whole phase, the contiguous stretches of each of those functions (the pieces
//      between two checkpoints that a slice cannot split);
//   4. with STACKS=1, per long task and clock offset (−150, −100, −50, 0 ms), the samples'
//      leaf function and the first three of the project's frames under it, most frequent
//      first. Use it when 1. finds no offset (a long task that is not JavaScript, e.g. a GPU
//      upload or the thread descheduled, samples as "(idle)" at every offset).
//
//   node profile_tasks.mjs photo1 [CATS=silhouette_pairs,AutodiffServer::backward,…] [STACKS=1]
//
// Function names need a wasm build with names (GETAVATAR_KEEP_NAMES=1 cargo xtask build-web).
import fs from 'node:fs';

const phase = process.argv[2];
if (!phase) {
  console.error('usage: node profile_tasks.mjs <phase file stem, e.g. photo1>');
  process.exit(2);
}
const dir = new URL('./out/long_tasks/', import.meta.url);
const profile = JSON.parse(fs.readFileSync(new URL(`${phase}.cpuprofile`, dir)));
const { pt0, lt } = JSON.parse(fs.readFileSync(new URL(`${phase}.lt.json`, dir)));
const cats = (process.env.CATS ?? 'silhouette_pairs,AutodiffServer::backward,VertexSet::pose,rasterize::rasterize,antialias,TriplaneSynthesis,compile,egui')
  .split(',')
  .filter(Boolean);

const byId = new Map(profile.nodes.map((n) => [n.id, n]));
const parent = new Map();
for (const n of profile.nodes) for (const c of n.children ?? []) parent.set(c, n.id);
const stackOf = new Map();
const stack = (id) => {
  if (!stackOf.has(id)) {
    const names = [];
    for (let x = id; x !== undefined; x = parent.get(x)) names.push(byId.get(x).callFrame.functionName);
    stackOf.set(id, names);
  }
  return stackOf.get(id);
};
const category = (id) => {
  const s = stack(id).join(' ');
  return cats.find((c) => s.includes(c)) ?? (stack(id)[0] === '(idle)' ? '(idle)' : 'other');
};
let t = 0;
const times = profile.timeDeltas.map((d) => (t += d) / 1000);
const long = lt.filter(([, d]) => d > 50);

// 1. Clock offset.
let best = null;
// Searched over −150…0 ms (what was seen); with few long tasks the fit is loose.
for (let off = -150; off <= 0; off += 2) {
  let idle = 0;
  let busy = 0;
  profile.samples.forEach((id, k) => {
    const ms = times[k] + pt0 + off;
    if (!long.some(([s, d]) => ms >= s && ms <= s + d)) return;
    if (byId.get(id).callFrame.functionName === '(idle)') idle++;
    else busy++;
  });
  if (!best || busy - 3 * idle > best.score) best = { score: busy - 3 * idle, off, idle, busy };
}
const off = Number(process.env.OFF ?? best?.off ?? -80);
console.log(`clock offset ${off} ms (idle samples inside long tasks: ${best?.idle ?? 0}, busy: ${best?.busy ?? 0})`);

// 2. Per long task.
for (const [s, d] of [...long].sort((a, b) => b[1] - a[1]).slice(0, 15)) {
  const ms = new Map();
  profile.samples.forEach((id, k) => {
    const at = times[k] + pt0 + off;
    if (at < s || at > s + d) return;
    const dt = k + 1 < times.length ? times[k + 1] - times[k] : 1;
    const c = category(id);
    ms.set(c, (ms.get(c) ?? 0) + dt);
  });
  const parts = [...ms].sort((a, b) => b[1] - a[1]).map(([c, v]) => `${c} ${v.toFixed(0)}`);
  console.log(`task at ${s.toFixed(0)} ms, ${d.toFixed(0)} ms: ${parts.join(', ')}`);
}

// 3. Contiguous stretches per category.
const runs = {};
let last = null;
let from = 0;
profile.samples.forEach((id, k) => {
  const c = category(id);
  if (c !== last) {
    if (last) (runs[last] ??= []).push(times[k] - from);
    last = c;
    from = times[k];
  }
});
for (const c of cats) {
  const r = (runs[c] ?? []).filter((x) => x > 3).sort((a, b) => b - a);
  if (!r.length) continue;
  console.log(`${c.padEnd(28)} ${r.length} stretches > 3 ms, longest ${r.slice(0, 6).map((x) => x.toFixed(0)).join(' ')}, median ${r[Math.floor(r.length / 2)].toFixed(1)} ms`);
}

// 4. Stacks per long task at a few offsets.
if (process.env.STACKS) {
  const ours = /getavatar|core::|web::|burn|egui|eframe|wgpu/;
  for (const [s, d] of [...long].sort((a, b) => b[1] - a[1]).slice(0, 15)) {
    for (const shift of [-150, -100, -50, 0]) {
      const counts = new Map();
      profile.samples.forEach((id, k) => {
        const at = times[k] + pt0 + shift;
        if (at < s || at > s + d) return;
        const names = stack(id).filter(Boolean);
        const key = `${(names[0] ?? '?').slice(0, 60)} || ${names.filter((f) => ours.test(f)).slice(0, 3).map((f) => f.slice(0, 60)).join(' < ')}`;
        counts.set(key, (counts.get(key) ?? 0) + 1);
      });
      console.log(`task at ${s.toFixed(0)} ms, ${d.toFixed(0)} ms, offset ${shift}:`);
      for (const [key, n] of [...counts].sort((a, b) => b[1] - a[1]).slice(0, 8)) console.log(`  ${n} ${key}`);
    }
  }
}
