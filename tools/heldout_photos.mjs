// Photos for the end-to-end reconstruction figures (docs/benchmarks.md, "Single-image
// reconstruction"): every view of a `trainer prepare` folder (RGBA renders of held-out
// people) composited over a grey-blue vertical gradient, as a photo has no alpha, written to
// `<out>/<person>_<view>.png`. Then `node tools/mediapipe_fixtures.mjs <out>` reads them
// as the app does.
//
//   (cd tests/e2e && npm ci)
//   node tools/heldout_photos.mjs data/heldout512 photos [--views 000,002]

import fs from 'node:fs';
import path from 'node:path';
import { fileURLToPath } from 'node:url';
import { createRequire } from 'node:module';

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), '..');
const require = createRequire(path.join(root, 'tests/e2e/package.json'));
const { PNG } = require('pngjs');

const args = process.argv.slice(2);
const flag = (name) => { const i = args.indexOf(name); return i >= 0 ? args.splice(i, 2)[1] : undefined; };
const only = flag('--views')?.split(',');
const [data, out] = args;
if (!data || !out) {
  console.error('usage: node tools/heldout_photos.mjs <prepared dataset folder> <out folder> [--views 000,001]');
  process.exit(2);
}
fs.mkdirSync(out, { recursive: true });
let n = 0;
for (const person of fs.readdirSync(data).filter((d) => /^\d+$/.test(d)).sort()) {
  for (const f of fs.readdirSync(path.join(data, person)).filter((f) => /^\d+\.png$/.test(f)).sort()) {
    const view = f.slice(0, -4);
    if (only && !only.includes(view)) continue;
    const img = PNG.sync.read(fs.readFileSync(path.join(data, person, f)));
    const photo = new PNG({ width: img.width, height: img.height });
    for (let y = 0; y < img.height; y++) {
      const t = y / Math.max(1, img.height - 1);
      const bg = [150 - 60 * t, 160 - 50 * t, 185 - 35 * t];
      for (let x = 0; x < img.width; x++) {
        const k = (y * img.width + x) * 4;
        const a = img.data[k + 3] / 255;
        for (let c = 0; c < 3; c++) photo.data[k + c] = Math.round(img.data[k + c] * a + bg[c] * (1 - a));
        photo.data[k + 3] = 255;
      }
    }
    fs.writeFileSync(path.join(out, `${person}_${view}.png`), PNG.sync.write(photo));
    n++;
  }
}
console.log(`wrote ${n} photos to ${out}`);
