// Hard photos made from the project's own render (fixtures/kick_clothed.png, RGBA: a clothed
// avatar in a kick, alpha = the person): people composited over backgrounds at known places,
// sizes and turns, so the person finder's choice can be checked against the truth.
//
//   cases() → [{name, png: Buffer, truth, expect}], where truth is the people's coverage
//     (alpha, row-major over the photo: {width, height, data: Float32Array}) and expect is
//     {people, person (1-based, the fitted one by size), rotation, chooses?, missing?: RegExp
//     (joints named as unseen), mirrored?: the mirrored photo's reading is the one fitted}
//     or {error: RegExp}.
//   node people_cases.mjs DIR   writes the PNGs into DIR (to look at them, or for
//                               tools/mediapipe_fixtures.mjs).

import fs from 'node:fs';
import path from 'node:path';
import { createRequire } from 'node:module';

const require = createRequire(import.meta.url);
const { PNG } = require('pngjs');

const defaultRender = PNG.sync.read(fs.readFileSync(new URL('./fixtures/kick_clothed.png', import.meta.url)));
// A held-out synthetic person (`trainer synth-scans --count 12 --seed 1`, `prepare --views 4
// --res 512 --seed 1`: person 0011, view 003): arms raised, seen from the side.
const armsUp = PNG.sync.read(fs.readFileSync(new URL('./fixtures/arms_up_side.png', import.meta.url)));
// Person 0006, view 000 of the same set: running, seen from the side.
const runner = PNG.sync.read(fs.readFileSync(new URL('./fixtures/runner_side.png', import.meta.url)));
// The bare body from its left side (`trainer body-photos`: side_reach_view2 and
// jumping_jack_view2, the white background made transparent): leaning to its left with the
// right arm over the head and the left hand at the waist; and a jumping jack, both arms raised
// in the plane of the body, one behind the other.
const sideReach = PNG.sync.read(fs.readFileSync(new URL('./fixtures/side_reach_side.png', import.meta.url)));
const jumpingJack = PNG.sync.read(fs.readFileSync(new URL('./fixtures/jumping_jack_side.png', import.meta.url)));

/** A deterministic pseudo-random stream in [0, 1). */
function rng(seed) {
  let s = seed >>> 0;
  return () => {
    s = (s * 1664525 + 1013904223) >>> 0;
    return s / 2 ** 32;
  };
}

/** A w × h photo filled by `f(x, y) → [r, g, b]`. */
function background(w, h, f) {
  const png = new PNG({ width: w, height: h });
  png.truth = new Float32Array(w * h);
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      const o = (y * w + x) * 4;
      const [r, g, b] = f(x, y);
      png.data[o] = r; png.data[o + 1] = g; png.data[o + 2] = b; png.data[o + 3] = 255;
    }
  }
  return png;
}

/** Grey ground with soft noise (a plain wall). */
function wall(w, h, seed) {
  const rand = rng(seed);
  return background(w, h, () => { const v = 115 + Math.round(20 * rand()); return [v, v + 3, v + 6]; });
}

/**
 * The render (`src`, default the kick) pasted at (ox, oy), scaled by `scale` (nearest) and
 * turned `turn` (0, 90, 180, 270) clockwise, blended as `tone(rgb, bg) → rgb` (default: as
 * rendered).
 */
function paste(photo, { src: render = defaultRender, scale, ox, oy, turn = 0, tone = (c) => c }) {
  const sw = Math.floor(render.width * scale), sh = Math.floor(render.height * scale);
  const [tw, th] = turn % 180 ? [sh, sw] : [sw, sh];
  for (let y = 0; y < th; y++) {
    for (let x = 0; x < tw; x++) {
      // (x, y) in the turned paste → (u, v) in the scaled render.
      const [u, v] = { 0: [x, y], 90: [y, th - 1 - x], 180: [sw - 1 - x, sh - 1 - y], 270: [tw - 1 - y, x] }[turn];
      const i = (Math.min(render.height - 1, Math.floor(v / scale)) * render.width + Math.min(render.width - 1, Math.floor(u / scale))) * 4;
      const a = render.data[i + 3] / 255;
      const px = ox + x, py = oy + y;
      if (a === 0 || px < 0 || py < 0 || px >= photo.width || py >= photo.height) continue;
      const o = (py * photo.width + px) * 4;
      photo.truth[py * photo.width + px] = Math.max(photo.truth[py * photo.width + px], a);
      const bg = [photo.data[o], photo.data[o + 1], photo.data[o + 2]];
      const fg = tone([render.data[i], render.data[i + 1], render.data[i + 2]], bg);
      for (let c = 0; c < 3; c++) photo.data[o + c] = Math.round(fg[c] * a + bg[c] * (1 - a));
    }
  }
}

export function cases() {
  const out = [];
  const add = (name, photo, expect) => out.push({
    name,
    png: PNG.sync.write(photo),
    truth: { width: photo.width, height: photo.height, data: photo.truth },
    expect,
  });

  // Two people: the larger upside down (a handstand, a fall), the smaller upright.
  let p = wall(1100, 640, 1);
  paste(p, { scale: 1.15, ox: 20, oy: 20, turn: 180 });
  paste(p, { scale: 0.8, ox: 640, oy: 160 });
  add('upside_down_and_upright.png', p, { people: 2, person: 2, rotation: 0 });

  // One person, upside down: read through the photo turned 180°.
  p = wall(640, 640, 2);
  paste(p, { scale: 1.05, ox: 40, oy: 40, turn: 180 });
  add('upside_down.png', p, { people: 1, person: 1, rotation: 180 });

  // One person lying (turned 90° clockwise): read through the photo turned back by 270°.
  p = wall(720, 560, 3);
  paste(p, { scale: 0.95, ox: 90, oy: 40, turn: 90 });
  add('lying.png', p, { people: 1, person: 1, rotation: 270 });

  // Three people of different sizes: the largest is fitted; choosing the 3rd refits on it.
  p = wall(1400, 620, 4);
  paste(p, { scale: 1.1, ox: 0, oy: 30 });
  paste(p, { scale: 0.8, ox: 560, oy: 180 });
  paste(p, { scale: 0.62, ox: 1000, oy: 260 });
  add('three_people.png', p, { people: 3, person: 1, rotation: 0, chooses: 3 });

  // Against the light: a bright, strong gradient (sky to a sun at the top right), the person
  // dimmed and washed towards it (low contrast).
  p = background(560, 640, (x, y) => {
    const sun = Math.max(0, 1 - Math.hypot(x - 470, y - 60) / 260);
    const t = y / 640;
    return [Math.min(255, 250 - 50 * t + 5 * sun), Math.min(255, 245 - 80 * t + 10 * sun), Math.min(255, 230 - 120 * t + 25 * sun)];
  });
  paste(p, { scale: 1.05, ox: 20, oy: 60, tone: (c, bg) => c.map((v, k) => 0.45 * v * 0.7 + 0.55 * bg[k]) });
  add('backlit.png', p, { people: 1, person: 1, rotation: 0 });

  // Cut off by the photo's bottom edge below the knees: fitted, the unseen joints named.
  p = wall(560, 400, 6);
  paste(p, { scale: 1.05, ox: 20, oy: 40 });
  add('cut_off.png', p, { people: 1, person: 1, rotation: 0, missing: /ankle/ });

  // Arms raised seen from the side, the raised arm before the face, the hands and feet at the
  // photo's top and bottom edges: Pose reads this person only through the square with room
  // around them (padded past the photo's edges with its border colour).
  p = wall(512, 512, 7);
  paste(p, { src: armsUp, scale: 1, ox: 0, oy: 0 });
  add('arms_up_at_the_edge.png', p, { people: 1, person: 1, rotation: 0 });

  // A runner seen from the side over a grey-blue gradient (tools/heldout_photos.mjs): Pose
  // reads both legs together in the gap between them, off the person; the mirrored photo's
  // reading puts them on the legs.
  p = background(512, 512, (x, y) => { const t = y / 511; return [150 - 60 * t, 160 - 50 * t, 185 - 35 * t]; });
  paste(p, { src: runner, scale: 1, ox: 0, oy: 0 });
  add('runner_from_the_side.png', p, { people: 1, person: 1, rotation: 0, mirrored: true });

  // The side reach from its side: Pose reads the hand at the waist over the head, on the far
  // hand (both arms in one place); the mirrored photo's reading sees the arms apart and is fitted.
  p = wall(512, 600, 8);
  paste(p, { src: sideReach, scale: 1, ox: 0, oy: 40 });
  add('side_reach_from_the_side.png', p, { people: 1, person: 1, rotation: 0, mirrored: true });

  // Two raised arms from the side, one behind the other, are also one arm's place twice: read
  // again mirrored, they stay as first read.
  p = wall(512, 600, 9);
  paste(p, { src: jumpingJack, scale: 1, ox: 0, oy: 60 });
  add('arms_raised_from_the_side.png', p, { people: 1, person: 1, rotation: 0 });

  // No person: only a background (the wall with a bright window).
  p = wall(640, 480, 5);
  for (let y = 80; y < 300; y++) for (let x = 380; x < 560; x++) { const o = (y * 640 + x) * 4; p.data[o] = 230; p.data[o + 1] = 235; p.data[o + 2] = 240; }
  add('no_person.png', p, { error: /no person/ });
  return out;
}

if (process.argv[1] && path.resolve(process.argv[1]) === path.resolve(new URL(import.meta.url).pathname)) {
  const dir = path.resolve(process.argv[2] ?? '.');
  fs.mkdirSync(dir, { recursive: true });
  for (const c of cases()) fs.writeFileSync(path.join(dir, c.name), c.png);
  console.log(`wrote ${cases().length} photos to ${dir}`);
}
