// CPU profile of the reconstruction worker during its W+ steps (NdArray or WebGPU), for a wasm
// built with names (GETAVATAR_KEEP_NAMES=1 cargo xtask build-web):
//   cargo xtask serve            # another shell
//   cd tests/e2e && node profile_worker.mjs [device cpu|webgpu, default cpu] [res, default 64] [seconds, default 90]
// fits the e2e photo, starts a 20-step W+ run on that device, attaches to the worker once its
// first step is done (Chrome DevTools Protocol through the browser's session), samples it for
// the given seconds, writes out/worker.cpuprofile (open it in Chrome's DevTools) and prints
// the functions with the most self time and with the most total (inclusive) time.
// GETAVATAR_URL (default http://127.0.0.1:8080/) and GETAVATAR_CHROMIUM as for app.e2e.mjs.
import { appStatus, greyPhoto, launchChromium } from './browser.mjs';
import fs from 'node:fs';

const url = process.env.GETAVATAR_URL ?? 'http://127.0.0.1:8080/';
const [device = 'cpu', res = '64', seconds = '90'] = process.argv.slice(2);
const browser = await launchChromium();
const page = await (await browser.newContext({ viewport: { width: 1280, height: 800 } })).newPage();
const { waitFor } = appStatus(page);
await page.goto(url);
await waitFor((s) => s.ready && !/loading/.test(s.model), 'the app and its model');
const bytes = [...greyPhoto()];
await page.evaluate((b) => window.getavatar.command({
  photo: { url: URL.createObjectURL(new Blob([new Uint8Array(b)], { type: 'image/png' })) },
}), bytes);
await waitFor((s) => s.photo.fits > 0 || s.photo.state === 'failed', 'the fit');
const cdp = await browser.newBrowserCDPSession();
const e = await page.evaluate(([res, device]) => window.getavatar.command({
  reconstruct: { res, steps: 20, pti_steps: 0, preview_every: 0, device },
}), [Number(res), device]);
if (e) throw new Error(e);
let worker = null;
for (let k = 0; k < 600 && !worker; k++) {
  const { targetInfos } = await cdp.send('Target.getTargets');
  worker = targetInfos.find((t) => t.type === 'worker' && /reconstruct/.test(t.url));
  if (!worker) await page.waitForTimeout(100);
}
if (!worker) throw new Error('no reconstruction worker');
const { sessionId } = await cdp.send('Target.attachToTarget', { targetId: worker.targetId, flatten: false });
let id = 0;
const pending = new Map();
cdp.on('Target.receivedMessageFromTarget', (m) => {
  const msg = JSON.parse(m.message);
  if (msg.id && pending.has(msg.id)) { pending.get(msg.id)(msg); pending.delete(msg.id); }
});
const send = (method, params = {}) => new Promise((resolve) => {
  const mid = ++id;
  pending.set(mid, resolve);
  cdp.send('Target.sendMessageToTarget', { sessionId, message: JSON.stringify({ id: mid, method, params }) });
});
await waitFor((s) => s.reconstruct.steps_done >= 1, 'the first W+ step', 3600000);
console.log('profiling…');
await send('Profiler.enable');
await send('Profiler.setSamplingInterval', { interval: 1000 });
await send('Profiler.start');
await page.waitForTimeout(Number(seconds) * 1000);
const { result } = await send('Profiler.stop');
const profile = result.profile;
fs.mkdirSync('out', { recursive: true });
fs.writeFileSync('out/worker.cpuprofile', JSON.stringify(profile));
const byId = new Map(profile.nodes.map((n) => [n.id, n]));
const parent = new Map();
for (const n of profile.nodes) for (const c of n.children ?? []) parent.set(c, n.id);
const self = new Map(), total = new Map();
for (const sid of profile.samples) {
  const f = byId.get(sid).callFrame.functionName || '(anon)';
  self.set(f, (self.get(f) ?? 0) + 1);
  const seen = new Set();
  for (let x = sid; x !== undefined; x = parent.get(x)) {
    const g = byId.get(x).callFrame.functionName || '(anon)';
    if (!seen.has(g)) { seen.add(g); total.set(g, (total.get(g) ?? 0) + 1); }
  }
}
const n = profile.samples.length;
const top = (m, k) => [...m].sort((a, b) => b[1] - a[1]).slice(0, k);
console.log(`${n} samples`);
console.log('self:');
for (const [f, c] of top(self, 40)) console.log(`${(100 * c / n).toFixed(1).padStart(5)} %  ${f.slice(0, 200)}`);
console.log('total:');
for (const [f, c] of top(total, 80)) console.log(`${(100 * c / n).toFixed(1).padStart(5)} %  ${f.slice(0, 200)}`);
await browser.close();
