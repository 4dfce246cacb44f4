// Real-detector fixtures of the body fit: runs the app's person detector
// (www/pose_detect.js: MediaPipe Pose from the pinned npm package, in headless Chromium on
// SwiftShader, exactly as the app runs it) on every PNG of a folder and writes, per photo,
// `<name>.kp.json` (MediaPipe's result object without the mask) and `<name>.mask.png`
// (the person mask, grey).
//
//   trainer body-photos --out trainer/tests/fixtures/mediapipe
//   (cd www && npm ci) && (cd tests/e2e && npm ci)
//   node tools/mediapipe_fixtures.mjs trainer/tests/fixtures/mediapipe
//   rm trainer/tests/fixtures/mediapipe/*_yaw?.png trainer/tests/fixtures/mediapipe/*_view?.png   # the tests re-render them
//
// Needs Chromium (/usr/bin/chromium or GETAVATAR_CHROMIUM), as the browser e2e test does.
//
// With `--front` the PNGs are front renders (`trainer variety` writes them to `seeds/` and
// `subjects/`; the model card's faces figure): a photo without a person is a finding, not a
// failure, and the script ends with how many renders MediaPipe found a person in and how
// many of those it saw facing the camera — the person's left shoulder and hip on the image's
// right of their right ones, which a detector gets right only where the face and front tell
// front from back — and writes it to `front.json` in the folder.

import http from 'node:http';
import fs from 'node:fs';
import path from 'node:path';
import { fileURLToPath } from 'node:url';
import { createRequire } from 'node:module';

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), '..');
const require = createRequire(path.join(root, 'tests/e2e/package.json'));
const { chromium } = require('playwright-core');
const { PNG } = require('pngjs');

const args = process.argv.slice(2);
const front = args.includes('--front');
// `--video`: the PNGs are a video's frames in name order, read by Pose's tracking mode in one
// page (www/pose_detect.js detectVideoFrame), as `trainer motion-from-video` asks.
const video = args.includes('--video');
const dir = path.resolve(args.find((a) => !a.startsWith('--')) ?? '.');
// PNG photos (not the masks this script writes) and JPEG frames (what `trainer
// motion-from-video` decodes a video into).
const photos = fs.readdirSync(dir).filter((f) => (f.endsWith('.png') && !f.endsWith('.mask.png')) || f.endsWith('.jpg')).sort();
const mime = { '.js': 'text/javascript', '.wasm': 'application/wasm', '.html': 'text/html', '.png': 'image/png', '.jpg': 'image/jpeg' };
const page = `<!DOCTYPE html><html><body><script type="module">
import { detectPose, detectVideoFrame } from './pose_detect.js';
const bytesOf = async (name) => new Uint8Array(await (await fetch('photos/' + name)).arrayBuffer());
window.detect = async (name) => detectPose(await bytesOf(name), 256);
window.detectFrame = async (name, first) => detectVideoFrame(await bytesOf(name), first);
window.ready = true;
</script></body></html>`;
const server = http.createServer((req, res) => {
  const url = decodeURIComponent(req.url.split('?')[0]);
  let file = null;
  if (url === '/' || url === '/index.html') { res.writeHead(200, { 'content-type': 'text/html' }); return res.end(page); }
  // The app's layout (dist/, as xtask copies it): the detector, its worker, and the two
  // MediaPipe packages under mediapipe/ (selfie segmentation in its own folder).
  if (url === '/pose_detect.js' || url === '/pose_worker.js') file = path.join(root, 'www', url.slice(1));
  else if (url.startsWith('/mediapipe/selfie_segmentation/')) {
    file = path.join(root, 'www/node_modules/@mediapipe/selfie_segmentation', path.basename(url));
  } else if (url.startsWith('/mediapipe/')) file = path.join(root, 'www/node_modules/@mediapipe/pose', path.basename(url));
  else if (url.startsWith('/photos/')) file = path.join(dir, path.basename(url));
  if (!file || !fs.existsSync(file)) { res.writeHead(404); return res.end(); }
  res.writeHead(200, { 'content-type': mime[path.extname(file)] ?? 'application/octet-stream' });
  fs.createReadStream(file).pipe(res);
});
await new Promise((r) => server.listen(0, '127.0.0.1', r));
// Headless Chromium loses the page (or the whole browser) part way through a few dozen
// detections, so every PAGE_PHOTOS photos run on a fresh page, and a lost page or browser
// is reopened and the photo tried once more.
const PAGE_PHOTOS = 12;
const launch = () => chromium.launch({
  executablePath: process.env.GETAVATAR_CHROMIUM ?? '/usr/bin/chromium',
  headless: true,
  args: ['--no-sandbox', '--use-angle=swiftshader', '--disable-background-networking', '--no-first-run'],
});
let browser = await launch();
let tab = null;
let onTab = 0;
const openTab = async () => {
  if (tab) await tab.close().catch(() => {});
  if (!browser.isConnected()) browser = await launch();
  tab = await browser.newPage();
  tab.on('pageerror', (e) => console.error('pageerror', e.message));
  await tab.goto(`http://127.0.0.1:${server.address().port}/`);
  await tab.waitForFunction(() => window.ready);
  onTab = 0;
};
let firstFrame = true;
const detect = async (name) => {
  for (let attempt = 0; ; attempt++) {
    try {
      if (video) {
        // One page for the clip (the tracker's state lives in its worker); a new page
        // starts the tracker afresh.
        if (!tab) { await openTab(); firstFrame = true; }
        const r = JSON.parse(await tab.evaluate(([n, f]) => window.detectFrame(n, f), [name, firstFrame]));
        firstFrame = false;
        return r;
      }
      if (!tab || onTab >= PAGE_PHOTOS) await openTab();
      onTab++;
      return JSON.parse(await tab.evaluate((n) => window.detect(n), name));
    } catch (e) {
      if (attempt >= 1) throw new Error(`${name}: the page was lost twice: ${e.message}`);
      console.error(`${name}: the page was lost (${e.message.split('\n')[0]}); trying again on a fresh page`);
      tab = null;
      if (!browser.isConnected()) browser = await launch();
    }
  }
};
let failed = 0;
const seen = { renders: photos.length, person: 0, facing: 0, missed: [], backwards: [] };
for (const name of photos) {
  const r = await detect(name);
  const stem = name.replace(/\.(png|jpg)$/, '');
  if (r.error || !r.poseLandmarks) {
    console.error(`${name}: ${r.error ?? 'no landmarks'}`);
    if (front) seen.missed.push(name); else failed++;
    continue;
  }
  if (front) {
    // MediaPipe's indices: 11/12 left/right shoulder, 23/24 left/right hip (the person's own).
    const l = r.poseLandmarks;
    seen.person++;
    if (l[11].x > l[12].x && l[23].x > l[24].x) seen.facing++; else seen.backwards.push(name);
  }
  const m = r.segmentationMask;
  delete r.segmentationMask;
  fs.writeFileSync(path.join(dir, `${stem}.kp.json`), JSON.stringify(r) + '\n');
  if (m) {
    const png = new PNG({ width: m.width, height: m.height, colorType: 0, inputColorType: 0, inputHasAlpha: false });
    png.data = Buffer.from(m.data.map((v) => Math.round(v * 255)));
    fs.writeFileSync(path.join(dir, `${stem}.mask.png`), PNG.sync.write(png, { colorType: 0, inputColorType: 0, inputHasAlpha: false }));
  }
  const vis = r.poseLandmarks.filter((l) => l.visibility >= 0.5).length;
  console.log(`${name}: ${vis}/33 landmarks visible${m ? `, mask ${m.width}×${m.height}` : ''}${r.tracked ? ', tracked' : ''}${r.mirrorWhy ? `, read again mirrored (${r.mirrorWhy === 'doubledArms' ? 'one arm read twice' : `limb landmarks off the mask: ${r.offMask.join(' → ')}`}): ${r.mirrored ? 'the mirrored reading' : 'the first reading'} kept` : ''}`);
}
await browser.close();
server.close();
if (front) {
  console.log(`front renders: a person in ${seen.person} of ${seen.renders}, facing the camera in ${seen.facing} of those`);
  fs.writeFileSync(path.join(dir, 'front.json'), JSON.stringify(seen, null, 1) + '\n');
}
process.exit(failed ? 1 : 0);
