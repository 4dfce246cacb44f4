// Real-detector fixtures of the body fit (issue #20): runs the app's person detector
// (www/pose_detect.js: MediaPipe Pose from the pinned npm package, in headless Chromium on
// SwiftShader, exactly as the app runs it) on every PNG of a folder and writes, per photo,
// `<name>.kp.json` (MediaPipe's result object without the mask) and `<name>.mask.png`
// (the person mask, grey).
//
//   trainer body-photos --out trainer/tests/fixtures/mediapipe
//   (cd www && npm ci) && (cd tests/e2e && npm ci)
//   node tools/mediapipe_fixtures.mjs trainer/tests/fixtures/mediapipe
//   rm trainer/tests/fixtures/mediapipe/*_yaw?.png   # the test re-renders the photos
//
// Needs Chromium (/usr/bin/chromium or GETAVATAR_CHROMIUM), as the browser e2e test does.

import http from 'node:http';
import fs from 'node:fs';
import path from 'node:path';
import { fileURLToPath } from 'node:url';
import { createRequire } from 'node:module';

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), '..');
const require = createRequire(path.join(root, 'tests/e2e/package.json'));
const { chromium } = require('playwright-core');
const { PNG } = require('pngjs');

const dir = path.resolve(process.argv[2] ?? '.');
const photos = fs.readdirSync(dir).filter((f) => f.endsWith('.png') && !f.endsWith('.mask.png')).sort();
const mime = { '.js': 'text/javascript', '.wasm': 'application/wasm', '.html': 'text/html', '.png': 'image/png' };
const page = `<!DOCTYPE html><html><body><script type="module">
import { detectPose } from './pose_detect.js';
window.detect = async (name) => detectPose(new Uint8Array(await (await fetch('photos/' + name)).arrayBuffer()));
window.ready = true;
</script></body></html>`;
const server = http.createServer((req, res) => {
  const url = decodeURIComponent(req.url.split('?')[0]);
  let file = null;
  if (url === '/' || url === '/index.html') { res.writeHead(200, { 'content-type': 'text/html' }); return res.end(page); }
  if (url === '/pose_detect.js') file = path.join(root, 'www/pose_detect.js');
  else if (url.startsWith('/mediapipe/')) file = path.join(root, 'www/node_modules/@mediapipe/pose', path.basename(url));
  else if (url.startsWith('/photos/')) file = path.join(dir, path.basename(url));
  if (!file || !fs.existsSync(file)) { res.writeHead(404); return res.end(); }
  res.writeHead(200, { 'content-type': mime[path.extname(file)] ?? 'application/octet-stream' });
  fs.createReadStream(file).pipe(res);
});
await new Promise((r) => server.listen(0, '127.0.0.1', r));
const browser = await chromium.launch({
  executablePath: process.env.GETAVATAR_CHROMIUM ?? '/usr/bin/chromium',
  headless: true,
  args: ['--no-sandbox', '--use-angle=swiftshader', '--disable-background-networking', '--no-first-run'],
});
const tab = await browser.newPage();
tab.on('pageerror', (e) => console.error('pageerror', e.message));
await tab.goto(`http://127.0.0.1:${server.address().port}/`);
await tab.waitForFunction(() => window.ready);
let failed = 0;
for (const name of photos) {
  const r = JSON.parse(await tab.evaluate((n) => window.detect(n), name));
  const stem = name.replace(/\.png$/, '');
  if (r.error) { console.error(`${name}: ${r.error}`); failed++; continue; }
  const m = r.segmentationMask;
  delete r.segmentationMask;
  fs.writeFileSync(path.join(dir, `${stem}.kp.json`), JSON.stringify(r) + '\n');
  const png = new PNG({ width: m.width, height: m.height, colorType: 0, inputColorType: 0, inputHasAlpha: false });
  png.data = Buffer.from(m.data.map((v) => Math.round(v * 255)));
  fs.writeFileSync(path.join(dir, `${stem}.mask.png`), PNG.sync.write(png, { colorType: 0, inputColorType: 0, inputHasAlpha: false }));
  const vis = r.poseLandmarks.filter((l) => l.visibility >= 0.5).length;
  console.log(`${name}: ${vis}/33 landmarks visible, mask ${m.width}×${m.height}`);
}
await browser.close();
server.close();
process.exit(failed ? 1 : 0);
