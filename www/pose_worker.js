// Person detection for the photo → body fit, in a dedicated worker so that
// MediaPipe's synchronous WebGL inference (seconds on a software GPU) never holds the page's UI
// thread. A classic worker: MediaPipe's legacy solutions load their runtimes with
// importScripts, which module workers lack. `pose_detect.js` is the page's side.
//
// MediaPipe Pose (BlazePose GHUM, Apache-2.0, see NOTICE) from the pinned npm package
// `@mediapipe/pose`, whose runtime and models `cargo xtask build-web` copies into
// dist/mediapipe/ (nothing is fetched from a CDN), and MediaPipe Selfie Segmentation
// (`@mediapipe/selfie_segmentation`, Apache-2.0, in dist/mediapipe/selfie_segmentation/),
// which sees everyone: each connected region of its mask is a person candidate.
//
// Finding the person tries before it fails: Pose runs on a crop around every region (largest
// first), then on the whole photo, until a reading agrees with its region (most landmarks in
// it, spanning it) and is upright; last, on a square with room around every region that
// touches the photo's edge, padded with the photo's border colour. With one region, the whole photo comes first, judged
// against that region: Pose's 3D reading of a person alone in a photo is better from the
// whole photo than from a crop around them (docs/benchmarks.md, "Body fit"). When no reading
// is upright and agrees, the same candidates are tried on the photo
// turned 180°, 90° and 270° (a person read lying or upside down first at the turn that makes
// them upright). A turned reading is returned in the turned photo's frame: the preview, the
// sizes, the landmarks and the mask are all of the turned photo, and `rotation` says by how
// much it was turned, so the fit sees an upright person and its camera is that of the turned
// photo (the original's camera rolled by `rotation`, docs/conventions.md). A found reading with
// limb landmarks off its own person mask, or with one arm read twice, is read again on the
// mirrored photo, and the mirrored reading wins when it agrees with the person and puts fewer of
// them off, or sees the hands apart (`secondOpinion`).
//
// Messages: {id, bytes: Uint8Array, previewSide, person?} in (person: 0-based region to read,
// the largest first; absent: search all); {id, json, preview?} out, where json is
//   {"width", "height", "detectedWidth", "detectedHeight", "rotation": 0|90|180|270,
//    "poseLandmarks": [33 × {x, y, z, visibility}], "poseWorldLandmarks": [...],
//    "segmentationMask": {"width", "height", "data": [0..1]},
//    "people": <number of regions selfie segmentation sees; absent when it could not tell>,
//    "persons": [{x, y, w, h} per region, normalised, largest first], "person": <the fitted
//    region's index or null>, "tries": <Pose runs>, "mirrored": <the landmarks are the reading
//    of the mirrored photo (`secondOpinion`)>, "mirrorWhy": <what sent the reading to the
//    mirror: "offMask", "doubledArms" or null>, "offMask": [<limb landmarks off the person mask
//    in the first reading>, <in the mirrored one, or null when it was not read>]}
//   or {"error": "<one sentence for the user>"},
// {id, bytes, track: 'first' | 'next'} in: a video's frame in order (see `track`), answered
// with the same json (plus "tracked": true when the tracker read it; no preview);
// and preview (on success) is the detected (turned) photo at most previewSide on its long side:
// {width, height, data: Uint8Array RGBA, row-major from the top left}.
// Landmarks are normalised to the (turned) photo, so they hold for its original size, also
// after the downscale above 4 MP; the mask is at most 256 px on its long side.

const MAX_PIXELS = 40e6; // refused above this
const DETECT_PIXELS = 4e6; // downscaled above this before detection
const MASK_SIDE = 256;
const MODEL_DIR = 'mediapipe/';
const SELFIE_DIR = 'mediapipe/selfie_segmentation/';

let posePromise = null;

// MediaPipe's legacy solutions have a worker path, but it is broken in these releases (it runs
// importScripts on the model files too and never loads its packed assets). Their page path
// works in a worker given the little of the DOM it touches: `window` (this scope), scripts
// (loaded with importScripts), canvases (OffscreenCanvas, which has WebGL2) and a few
// listeners it registers and never needs.
self.window = self;
const noop = () => {};
function fakeScript() {
  const listeners = { load: [], error: [] };
  return {
    setAttribute(k, v) { this[k] = v; },
    addEventListener(type, f) { listeners[type]?.push(f); },
    load() {
      let ok = true;
      try {
        importScripts(this.src);
      } catch (e) {
        ok = false;
        console.error(`the person detector could not load ${this.src}: ${e.message ?? e}`);
      }
      setTimeout(() => listeners[ok ? 'load' : 'error'].forEach((f) => f()));
    },
  };
}
const fakeBody = { appendChild(el) { el.load?.(); return el; } };
self.document = {
  body: fakeBody,
  head: fakeBody,
  currentScript: null,
  title: '',
  addEventListener: noop,
  removeEventListener: noop,
  getElementById: () => null,
  querySelector: () => null,
  createElement(tag) {
    if (tag === 'canvas') return new OffscreenCanvas(1, 1);
    if (tag === 'script') return fakeScript();
    throw new Error(`the person detector's worker has no <${tag}>`);
  },
};

/** A classic script into this worker (MediaPipe's solutions are not modules). */
async function loadScript(src) {
  importScripts(src);
}

/** A 2-D canvas of this size (workers have no DOM: an OffscreenCanvas). */
function newCanvas(width, height) {
  return new OffscreenCanvas(width, height);
}

async function poseSolution() {
  if (!posePromise) {
    posePromise = (async () => {
      await loadScript(`${MODEL_DIR}pose.js`);
      const pose = new self.Pose({ locateFile: (file) => `${MODEL_DIR}${file}` });
      pose.setOptions({
        modelComplexity: 1,
        smoothLandmarks: false,
        enableSegmentation: true,
        smoothSegmentation: false,
        selfieMode: false,
        minDetectionConfidence: 0.5,
      });
      await pose.initialize();
      return pose;
    })();
    posePromise.catch(() => { posePromise = null; });
  }
  return posePromise;
}

const fail = (error) => JSON.stringify({ error });
// A failed detection's reply.
const failed = (error) => ({ json: fail(error) });

let selfiePromise = null;

async function selfieSolution() {
  if (!selfiePromise) {
    selfiePromise = (async () => {
      await loadScript(`${SELFIE_DIR}selfie_segmentation.js`);
      const seg = new self.SelfieSegmentation({ locateFile: (file) => `${SELFIE_DIR}${file}` });
      seg.setOptions({ modelSelection: 0, selfieMode: false });
      await seg.initialize();
      return seg;
    })();
    selfiePromise.catch(() => { selfiePromise = null; });
  }
  return selfiePromise;
}

/** One image through a MediaPipe solution (state reset: every photo is a new scene). */
function runSolution(solution, image) {
  return new Promise((resolve, reject) => {
    solution.reset();
    solution.onResults(resolve);
    solution.send({ image }).catch(reject);
  });
}

/**
 * The probability from which a pixel of selfie segmentation's mask joins a person's region:
 * any (1/255). Regions are for counting and framing people, where a limb joined to its body
 * by a faint band must not count as another person (at 0.5 the people e2e's upside-down kick
 * counted as two people, and one of its three people went uncounted); the fit's mask is the
 * probability itself.
 */
const REGION_PROBABILITY = 1 / 255;

/**
 * The people in a photo: connected regions of selfie segmentation's mask (at ≤ MASK_SIDE),
 * largest first, as boxes {x, y, w, h, area} in `canvas` pixels; regions under a fifth of
 * the largest are noise, not people.
 */
async function personRegions(canvas) {
  const seg = await selfieSolution();
  const results = await runSolution(seg, canvas);
  const { width: w, height: h, data } = maskValues(results.segmentationMask);
  const label = new Int32Array(w * h).fill(-1);
  const regions = [];
  for (let start = 0; start < w * h; start++) {
    if (label[start] >= 0 || data[start] < REGION_PROBABILITY) continue;
    const id = regions.length;
    const r = { x0: w, y0: h, x1: 0, y1: 0, area: 0 };
    const stack = [start];
    label[start] = id;
    while (stack.length) {
      const i = stack.pop();
      const x = i % w, y = (i - x) / w;
      r.area++;
      r.x0 = Math.min(r.x0, x); r.x1 = Math.max(r.x1, x); r.y0 = Math.min(r.y0, y); r.y1 = Math.max(r.y1, y);
      for (const [nx, ny] of [[x - 1, y], [x + 1, y], [x, y - 1], [x, y + 1]]) {
        const j = ny * w + nx;
        if (nx >= 0 && ny >= 0 && nx < w && ny < h && label[j] < 0 && data[j] >= REGION_PROBABILITY) {
          label[j] = id;
          stack.push(j);
        }
      }
    }
    regions.push(r);
  }
  regions.sort((a, b) => b.area - a.area);
  const big = regions.filter((r) => r.area >= 0.2 * (regions[0]?.area ?? 0) && r.area >= 0.002 * w * h);
  const kx = canvas.width / w, ky = canvas.height / h;
  return big.map((r) => ({ x: r.x0 * kx, y: r.y0 * ky, w: (r.x1 + 1 - r.x0) * kx, h: (r.y1 + 1 - r.y0) * ky, area: r.area }));
}

/** A person's box grown by 15 % on every side, clamped to the photo, in whole pixels. */
function padded(r, width, height) {
  const px = 0.15 * r.w, py = 0.15 * r.h;
  const x = Math.max(0, Math.floor(r.x - px)), y = Math.max(0, Math.floor(r.y - py));
  const x1 = Math.min(width, Math.ceil(r.x + r.w + px)), y1 = Math.min(height, Math.ceil(r.y + r.h + py));
  return { x, y, w: x1 - x, h: y1 - y };
}

/**
 * The sides of the squares with room around a person at the photo's edge, in their box's long
 * side, tried in this order: of the held-out views that need one, arms raised with the face
 * hidden (0011/000) reads only at 1.5 (at 2 Pose reads it upside down in the photo turned
 * 180°, at 1.25 not at all), and the same person seen from behind (0011/003) at 2.
 */
const ROOM = [1.5, 2];

/**
 * For a person's box that touches the photo's edge (within 1 % of its long side), the square
 * around it, `room` times its long side, centred on it and not clamped: `readCandidate` fills
 * its part past the photo's edge with the photo's border colour. Null for a box clear of the
 * edges (the padded crop has given that person room).
 */
function roomy(r, width, height, room) {
  const m = 0.01 * Math.max(width, height);
  const touches = r.x <= m || r.y <= m || r.x + r.w >= width - m || r.y + r.h >= height - m;
  if (!touches) return null;
  const side = Math.ceil(room * Math.max(r.w, r.h));
  return { x: Math.floor(r.x + r.w / 2 - side / 2), y: Math.floor(r.y + r.h / 2 - side / 2), w: side, h: side };
}

/** The mean colour of a canvas's outermost pixels, as a CSS colour. */
function borderColour(canvas) {
  const ctx = canvas.getContext('2d', { willReadFrequently: true });
  const { width: w, height: h } = canvas;
  const strips = [[0, 0, w, 1], [0, h - 1, w, 1], [0, 0, 1, h], [w - 1, 0, 1, h]];
  const sum = [0, 0, 0];
  let n = 0;
  for (const [x, y, sw, sh] of strips) {
    const d = ctx.getImageData(x, y, sw, sh).data;
    for (let i = 0; i < d.length; i += 4) { sum[0] += d[i]; sum[1] += d[i + 1]; sum[2] += d[i + 2]; n++; }
  }
  const [r, g, b] = sum.map((v) => Math.round(v / Math.max(1, n)));
  return `rgb(${r}, ${g}, ${b})`;
}

/** An image (canvas / ImageBitmap) drawn at most `maxSide` on its long side: {width, height, rgba}. */
function pixelsAtMost(image, maxSide) {
  const k = Math.min(1, maxSide / Math.max(image.width, image.height));
  const w = Math.max(1, Math.round(image.width * k));
  const h = Math.max(1, Math.round(image.height * k));
  const c = newCanvas(w, h);
  const ctx = c.getContext('2d', { willReadFrequently: true });
  ctx.drawImage(image, 0, 0, w, h);
  return { width: w, height: h, rgba: ctx.getImageData(0, 0, w, h).data };
}

/** Read a mask image (canvas / ImageBitmap) as person probabilities at ≤ MASK_SIDE. */
function maskValues(mask) {
  const { width: w, height: h, rgba } = pixelsAtMost(mask, MASK_SIDE);
  const data = new Array(w * h);
  // The solution's mask carries the probability in alpha over an opaque red (as SwiftShader
  // gives it: getImageData un-premultiplies, so red reads 255 wherever alpha is above 0), or
  // in red over an opaque alpha: alpha where it is not opaque, else red. (Red alone made
  // every pixel of probability ≥ 1/255 a person pixel: a mask about a pixel at 256² wider
  // than the person all round, mask IoU against the rendered silhouette 0.87 on the fit's
  // fixtures where the probability read right gives 0.965 at 0.5.)
  for (let i = 0; i < w * h; i++) data[i] = (rgba[4 * i + 3] < 255 ? rgba[4 * i + 3] : rgba[4 * i]) / 255;
  return { width: w, height: h, data };
}

/**
 * A canvas turned `deg` (0, 90, 180, 270) clockwise, and the map of a point of the original
 * (pixels) into it.
 */
function turned(canvas, deg) {
  const W = canvas.width, H = canvas.height;
  const map = {
    0: (x, y) => [x, y],
    90: (x, y) => [H - y, x],
    180: (x, y) => [W - x, H - y],
    270: (x, y) => [y, W - x],
  }[deg];
  if (deg === 0) return { canvas, map };
  const swap = deg % 180 !== 0;
  const c = newCanvas(swap ? H : W, swap ? W : H);
  const ctx = c.getContext('2d');
  ctx.translate(c.width / 2, c.height / 2);
  ctx.rotate((deg * Math.PI) / 180);
  ctx.drawImage(canvas, -W / 2, -H / 2);
  return { canvas: c, map };
}

/** A box {x, y, w, h} of the original through a turn's point map. */
function turnedBox(r, map) {
  const [ax, ay] = map(r.x, r.y);
  const [bx, by] = map(r.x + r.w, r.y + r.h);
  return { x: Math.min(ax, bx), y: Math.min(ay, by), w: Math.abs(bx - ax), h: Math.abs(by - ay) };
}

// A reading counts when at least this share of the landmarks Pose saw lies in its person's
// box (grown 10 %), the landmarks span this share of the box's long side, and the torso
// (mid-hip → mid-shoulder) points within UPRIGHT_DEG of up: the fit and the framing assume an
// upright person, so one seen lying or upside down is read again on the turned photo.
const IN_BOX = 0.7;
const SPAN = 0.35;
const UPRIGHT_DEG = 50;
const SEEN = 0.5;
const OUTSIDE_VISIBILITY = 0.1;

/**
 * How Pose's landmarks (photo pixels, `pts`) agree with a person's box: {ok, why, turn},
 * where turn is the clockwise turn (90, 180, 270) that would make a non-upright reading upright.
 */
function judge(pts, vis, box) {
  const seen = pts.filter((_, i) => vis[i] >= SEEN);
  if (seen.length < 8) return { ok: false, why: 'too few landmarks seen' };
  if (box) {
    const gx = 0.1 * box.w, gy = 0.1 * box.h;
    const inside = seen.filter(([x, y]) => x >= box.x - gx && x <= box.x + box.w + gx && y >= box.y - gy && y <= box.y + box.h + gy);
    if (inside.length < IN_BOX * seen.length) return { ok: false, why: 'the landmarks are outside the person' };
    const xs = seen.map((p) => p[0]), ys = seen.map((p) => p[1]);
    const span = Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys));
    if (span < SPAN * Math.max(box.w, box.h)) return { ok: false, why: 'the landmarks cover a small part of the person' };
  }
  const mid = (a, b) => [(pts[a][0] + pts[b][0]) / 2, (pts[a][1] + pts[b][1]) / 2];
  const [sx, sy] = mid(11, 12), [hx, hy] = mid(23, 24);
  // Image y points down: "up" is −y. Angle of the torso from up, clockwise positive.
  const angle = (Math.atan2(sx - hx, hy - sy) * 180) / Math.PI;
  if (Math.abs(angle) <= UPRIGHT_DEG) return { ok: true };
  // Turning the photo by −angle (rounded to a quarter) makes the torso point up.
  const turn = (((Math.round(-angle / 90) * 90) % 360) + 360) % 360;
  return { ok: false, why: `the person is not upright (torso ${Math.round(angle)}° from up)`, turn };
}

/**
 * The image of one candidate: `source` (the turned photo, a canvas) cut to `crop` (a box of it)
 * or all of it when crop is null; `fill` colours a crop's part past the photo's edge.
 */
function candidateImage(source, crop, fill) {
  if (!crop) return source;
  const image = newCanvas(crop.w, crop.h);
  const ctx = image.getContext('2d');
  if (fill) {
    ctx.fillStyle = fill;
    ctx.fillRect(0, 0, crop.w, crop.h);
    ctx.drawImage(source, -crop.x, -crop.y);
  } else {
    ctx.drawImage(source, crop.x, crop.y, crop.w, crop.h, 0, 0, crop.w, crop.h);
  }
  return image;
}

/**
 * Pose on one candidate: `source` is the turned photo (a canvas), `crop` a box of it or null
 * for all of it, `box` the person's box in it (for the agreement) or null, `fill` the colour
 * of a crop's part past the photo's edge (a `roomy` crop). Returns
 * {results, crop, verdict, pts, vis, image} or null when Pose saw no one.
 */
async function readCandidate(pose, source, crop, box, fill) {
  const image = candidateImage(source, crop, fill);
  const results = await runSolution(pose, image);
  if (!results.poseLandmarks || results.poseLandmarks.length !== 33) return null;
  const { pts, vis } = photoPoints(results.poseLandmarks, source, crop);
  return { results, crop, verdict: judge(pts, vis, box), pts, vis, image };
}

/** Crop-normalised landmarks as photo pixels `pts` and their visibilities `vis`. */
function photoPoints(landmarks, source, crop) {
  const [ox, oy] = crop ? [crop.x, crop.y] : [0, 0];
  const [sw, sh] = crop ? [crop.w, crop.h] : [source.width, source.height];
  return { pts: landmarks.map((l) => [ox + l.x * sw, oy + l.y * sh]), vis: landmarks.map((l) => l.visibility ?? 1) };
}

// The second opinion of a mirrored photo. Pose sometimes reads a limb where the person is not:
// a runner seen from the side read with both legs together in the gap between them (its knees,
// ankles and feet off the person's mask, which the fit then has to place from the mask alone).
// A reading with limb landmarks off Pose's own person mask is read again on the candidate's
// mirror image, and the mirrored reading (mapped back, left and right swapped) replaces it when
// it agrees with the person and has fewer landmarks off the mask (docs/benchmarks.md, "Person
// finding on hard photos").
//
// MIRROR: each landmark's counterpart on the person's other side (MediaPipe Pose's 33).
const MIRROR = [0, 4, 5, 6, 1, 2, 3, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15, 18, 17, 20, 19, 22, 21, 24, 23, 26, 25, 28, 27, 30, 29, 32, 31];
// A limb landmark (elbows to feet) is off the mask when no person pixel (probability ≥ 0.5) lies
// within OFF_MASK of the person's long side: about the fit's own limit (`OFF_PERSON`, 3 % of
// its crop, which is wider than the person).
const OFF_MASK = 0.04;
// Pose also reads one arm twice: seen from the side, a hand hanging at the waist in front of the
// torso read over the head, on the far hand raised there (both wrists within DOUBLED of the
// person's long side of each other). Two hands in one place is also what two raised arms look
// like from the side, and what crossed arms or clasped hands are, so the mirrored reading wins
// here only when it sees the hands apart: its wrists at least APART of the person's long side
// from each other (docs/benchmarks.md, "Body fit": the side reach from its side; two arms
// raised from the side stay as read).
const DOUBLED = 0.03;
const APART = 0.1;

/** How many seen limb landmarks (crop-normalised) lie off `mask` ({width, height, data}). */
function offMask(landmarks, mask) {
  const { width: w, height: h, data } = mask;
  let x0 = w, x1 = -1, y0 = h, y1 = -1;
  for (let i = 0; i < w * h; i++) {
    if (data[i] < 0.5) continue;
    const x = i % w, y = (i - x) / w;
    x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
  }
  if (x1 < 0) return 0;
  const r = Math.max(1, Math.ceil(OFF_MASK * Math.max(x1 - x0 + 1, y1 - y0 + 1)));
  const near = (cx, cy) => {
    for (let y = Math.max(0, cy - r); y <= Math.min(h - 1, cy + r); y++) {
      for (let x = Math.max(0, cx - r); x <= Math.min(w - 1, cx + r); x++) {
        if ((x - cx) ** 2 + (y - cy) ** 2 <= r * r && data[y * w + x] >= 0.5) return true;
      }
    }
    return false;
  };
  let off = 0;
  for (let i = 13; i < 33; i++) {
    const l = landmarks[i];
    if ((l.visibility ?? 1) < SEEN || l.x < 0 || l.x > 1 || l.y < 0 || l.y > 1) continue;
    if (!near(Math.min(w - 1, Math.floor(l.x * w)), Math.min(h - 1, Math.floor(l.y * h)))) off++;
  }
  return off;
}

/**
 * How far apart a reading's wrists are, as a share of the person's long side (the seen
 * landmarks' span). `pts` are photo pixels, `vis` their visibilities.
 */
function wristsApart(pts, vis) {
  const seen = pts.filter((_, i) => vis[i] >= SEEN);
  if (seen.length < 2) return Infinity;
  const xs = seen.map((p) => p[0]), ys = seen.map((p) => p[1]);
  const side = Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys), 1);
  return Math.hypot(pts[15][0] - pts[16][0], pts[15][1] - pts[16][1]) / side;
}

/**
 * A found reading `r` (of `source`, judged against `box`), checked against its own person mask
 * and, when limb landmarks lie off it or it reads one arm twice, against Pose's reading of the
 * mirrored candidate. Returns {read, tries, mirrored, why, off: [first, mirrored]}: `read` is
 * `r` or the mirrored reading, with the first reading's mask either way (copied before the
 * second run reuses Pose's canvas); `why` is what sent it to the mirror ('offMask',
 * 'doubledArms' or null).
 */
async function secondOpinion(pose, r, source, box) {
  const m = r.results.segmentationMask;
  if (!m) return { read: r, tries: 0, mirrored: false, why: null };
  const mask = newCanvas(m.width, m.height);
  mask.getContext('2d').drawImage(m, 0, 0);
  const values = maskValues(mask);
  const own = { ...r, results: { poseLandmarks: r.results.poseLandmarks, poseWorldLandmarks: r.results.poseWorldLandmarks, segmentationMask: mask } };
  const off = offMask(r.results.poseLandmarks, values);
  const doubled = wristsApart(r.pts, r.vis) < DOUBLED;
  if (off === 0 && !doubled) return { read: own, tries: 0, mirrored: false, why: null };
  const why = off > 0 ? 'offMask' : 'doubledArms';
  const image = newCanvas(r.image.width, r.image.height);
  const ctx = image.getContext('2d');
  ctx.translate(image.width, 0);
  ctx.scale(-1, 1);
  ctx.drawImage(r.image, 0, 0);
  const again = await runSolution(pose, image);
  const lms = again.poseLandmarks;
  if (!lms || lms.length !== 33) return { read: own, tries: 1, mirrored: false, why, off: [off, null] };
  const back = MIRROR.map((k) => ({ ...lms[k], x: 1 - lms[k].x }));
  const world = again.poseWorldLandmarks?.length === 33 ? MIRROR.map((k) => ({ ...again.poseWorldLandmarks[k], x: -again.poseWorldLandmarks[k].x })) : undefined;
  const offAgain = offMask(back, values);
  const { pts, vis } = photoPoints(back, source, r.crop);
  const verdict = judge(pts, vis, box);
  // Fewer landmarks off the mask; or, for an arm read twice, none more and the hands apart.
  const better = offAgain < off || (doubled && offAgain <= off && wristsApart(pts, vis) >= APART);
  if (!verdict.ok || !better) return { read: own, tries: 1, mirrored: false, why, off: [off, offAgain] };
  const read = { ...r, verdict, pts, vis, results: { poseLandmarks: back, poseWorldLandmarks: world, segmentationMask: mask } };
  return { read, tries: 1, mirrored: true, why, off: [off, offAgain] };
}

/** The region (index) most of a reading's seen landmarks fall in, or -1. */
function regionOf(pts, vis, boxes) {
  let best = -1, most = 0;
  boxes.forEach((b, k) => {
    const n = pts.filter(([x, y], i) => vis[i] >= SEEN && x >= b.x && x <= b.x + b.w && y >= b.y && y <= b.y + b.h).length;
    if (n > most) { most = n; best = k; }
  });
  return best;
}

/**
 * Find the person: Pose on every selfie-segmentation region (largest first), then on the
 * whole photo (first, against the region, when there is one region; Pose runs once on it),
 * then, when nothing upright was read, on the same candidates turned 180°, 90°
 * and 270° (a reading seen lying or upside down is tried at the turn that makes it upright
 * first). `want` (0-based) restricts the search to that region. Returns
 * {found: {results, crop, turn, region}, boxes, tried, seen} or {error}.
 */
async function findPerson(pose, canvas, regions, want) {
  const boxes = regions.map((r) => ({ x: r.x, y: r.y, w: r.w, h: r.h }));
  const order = want === null ? boxes.map((_, k) => k) : [want];
  if (want !== null && !boxes[want]) {
    return { error: `there is no person ${want + 1} in the photo (${boxes.length} found)` };
  }
  let tried = 0;
  const hints = new Set();
  const attempt = async (turn) => {
    const { canvas: src, map } = turned(canvas, turn);
    const tb = boxes.map((b) => turnedBox(b, map));
    const candidates = order.map((k) => ({ region: k, crop: padded(tb[k], src.width, src.height), box: tb[k] }));
    // The whole photo after the regions (none: the mask missed the person), and with one
    // region also before its crop, judged against it.
    if (want === null) {
      if (tb.length === 1) candidates.unshift({ region: 0, crop: null, box: tb[0] });
      candidates.push({ region: null, crop: null, box: null });
    }
    // Last, a person at the photo's edge with room around them: Pose's detector finds a face
    // or an upper body first, and a person whose feet touch the edge and whose face is hidden
    // (raised arms seen from the side, a back view) it reads only with the photo padded
    // (docs/benchmarks.md, "Person finding on hard photos").
    for (const k of order) {
      for (const room of ROOM) {
        const crop = roomy(tb[k], src.width, src.height, room);
        if (crop) candidates.push({ region: k, crop, box: tb[k], fill: true });
      }
    }
    let fill;
    let whole;
    for (const c of candidates) {
      if (c.crop === null && whole !== undefined) {
        // The whole photo, read before the region's crop, is judged again without the region,
        // and read again only when it now counts (the crop's run replaced Pose's mask).
        if (!whole || !judge(whole.pts, whole.vis, null).ok) continue;
      }
      tried++;
      if (c.fill && !fill) fill = borderColour(src);
      const r = await readCandidate(pose, src, c.crop, c.box, c.fill ? fill : undefined);
      if (c.crop === null && whole === undefined) whole = r;
      if (!r) continue;
      if (r.verdict.turn !== undefined && turn === 0) hints.add(r.verdict.turn);
      if (!r.verdict.ok) continue;
      const region = c.region ?? (tb.length ? regionOf(r.pts, r.vis, tb) : null);
      const second = await secondOpinion(pose, r, src, c.box);
      tried += second.tries;
      const { results, crop } = second.read;
      const mirror = { mirrored: second.mirrored, why: second.why, offMask: second.off ?? [0, null] };
      return { results, crop, turn, region: region === -1 ? null : region, src, boxes: tb, mirror };
    }
    return null;
  };
  let found = await attempt(0);
  if (!found) {
    const turns = [...hints, ...[180, 90, 270].filter((t) => !hints.has(t))];
    for (const t of turns) {
      found = await attempt(t);
      if (found) break;
    }
  }
  if (!found) {
    const who = want !== null ? `person ${want + 1} could not be read` : boxes.length ? `${boxes.length === 1 ? 'a person-like region was seen but' : `${boxes.length} person-like regions were seen but`} no person could be read in it, upright or turned` : 'no person found in the photo';
    return { error: `${who} (${tried} tries)` };
  }
  return { found, tried };
}

/** An image's bitmap, or null when the browser cannot read it. */
async function decode(bytes) {
  try {
    return await createImageBitmap(new Blob([bytes]));
  } catch (e) {
    return null;
  }
}

/** `bitmap` on a canvas of at most DETECT_PIXELS pixels (the bitmap is closed). */
function detectionCanvas(bitmap) {
  const { width, height } = bitmap;
  const k = Math.min(1, Math.sqrt(DETECT_PIXELS / (width * height)));
  const canvas = newCanvas(Math.max(1, Math.round(width * k)), Math.max(1, Math.round(height * k)));
  canvas.getContext('2d').drawImage(bitmap, 0, 0, canvas.width, canvas.height);
  bitmap.close();
  return canvas;
}

/** The detection itself: bytes → {json} ({json, preview} on success, see the header). */
async function detect(bytes, previewSide, person) {
  if (!bytes || bytes.length === 0) return failed('the file is empty');
  const bitmap = await decode(bytes);
  if (!bitmap) return failed('the file is not an image the browser can read (or it is corrupt)');
  const { width, height } = bitmap;
  if (width * height > MAX_PIXELS) {
    return failed(`the photo is ${width}×${height} pixels, over the 40 MP limit`);
  }
  if (width < 32 || height < 32) return failed(`the photo is ${width}×${height} pixels, too small to find a person in`);
  const canvas = detectionCanvas(bitmap);
  let pose;
  try {
    pose = await poseSolution();
  } catch (e) {
    return failed(`the person detector could not start: ${e.message ?? e}`);
  }
  // The people: connected regions of selfie segmentation's mask (it segments everyone; Pose
  // tracks one), each a candidate for Pose.
  let regions = [];
  let counted = true;
  try {
    regions = await personRegions(canvas);
  } catch (e) {
    counted = false;
    console.warn(`people count unavailable: ${e.message ?? e}`);
  }
  const want = Number.isInteger(person) && person >= 0 ? person : null;
  const search = await findPerson(pose, canvas, regions, want).catch((e) => ({ error: `the person detector failed: ${e.message ?? e}` }));
  if (search.error) return failed(search.error);
  const { results, crop, turn, region, src, boxes, mirror } = search.found;
  // Crop-normalised → normalised coordinates of the (turned) photo.
  const [ox, oy, sx, sy] = crop
    ? [crop.x / src.width, crop.y / src.height, crop.w / src.width, crop.h / src.height]
    : [0, 0, 1, 1];
  // A landmark outside the photo (a person cut off by its edge) is the detector's guess: it
  // counts as unseen (visibility at most OUTSIDE_VISIBILITY), so the fit names it missing.
  const plain = (list, toPhoto) => (list ?? []).map((l) => {
    const [x, y] = toPhoto ? [ox + l.x * sx, oy + l.y * sy] : [l.x, l.y];
    const outside = toPhoto && (x < 0 || x > 1 || y < 0 || y > 1);
    const v = l.visibility ?? 1;
    return { x, y, z: l.z, visibility: outside ? Math.min(v, OUTSIDE_VISIBILITY) : v };
  });
  const swap = turn % 180 !== 0;
  const out = {
    width: swap ? height : width,
    height: swap ? width : height,
    detectedWidth: src.width,
    detectedHeight: src.height,
    rotation: turn,
    poseLandmarks: plain(results.poseLandmarks, true),
    poseWorldLandmarks: plain(results.poseWorldLandmarks, false),
    persons: boxes.map((b) => ({ x: b.x / src.width, y: b.y / src.height, w: b.w / src.width, h: b.h / src.height })),
    person: region,
    tries: search.tried,
    mirrored: mirror.mirrored,
    mirrorWhy: mirror.why,
    offMask: mirror.offMask,
  };
  if (counted) out.people = regions.length;
  if (out.poseWorldLandmarks.length !== 33) delete out.poseWorldLandmarks;
  if (results.segmentationMask) {
    let mask = results.segmentationMask;
    if (crop) {
      // The crop's mask placed in the whole photo.
      const full = newCanvas(src.width, src.height);
      full.getContext('2d').drawImage(mask, crop.x, crop.y, crop.w, crop.h);
      mask = full;
    }
    out.segmentationMask = maskValues(mask);
  }
  const { width: pw, height: ph, rgba } = pixelsAtMost(src, previewSide);
  return { json: JSON.stringify(out), preview: { width: pw, height: ph, data: new Uint8Array(rgba.buffer) } };
}

// A video's frames: Pose in its tracking mode on the whole frame (the first frame starts a
// clip afresh). A frame the tracker finds nobody in is answered "no person in this frame";
// Pose's own detector looks for the person again on the next frame. (The photo's person
// finder is not tried: each of its candidates resets the solution, about 15 s on SwiftShader,
// where a frame costs 1.6 s.)
async function track(bytes, first) {
  if (!bytes || bytes.length === 0) return failed('the frame is empty');
  const bitmap = await decode(bytes);
  if (!bitmap) return failed('the frame is not an image the browser can read');
  const { width, height } = bitmap;
  const canvas = detectionCanvas(bitmap);
  const pose = await poseSolution();
  const results = await new Promise((resolve, reject) => {
    if (first) pose.reset();
    pose.onResults(resolve);
    pose.send({ image: canvas }).catch(reject);
  });
  if (!results.poseLandmarks) return failed('no person in this frame');
  const plain = (list, image) => (list ?? []).map((l) => {
    const outside = image && (l.x < 0 || l.x > 1 || l.y < 0 || l.y > 1);
    const v = l.visibility ?? 1;
    return { x: l.x, y: l.y, z: l.z, visibility: outside ? Math.min(v, OUTSIDE_VISIBILITY) : v };
  });
  const out = {
    width,
    height,
    detectedWidth: canvas.width,
    detectedHeight: canvas.height,
    rotation: 0,
    poseLandmarks: plain(results.poseLandmarks, true),
    poseWorldLandmarks: plain(results.poseWorldLandmarks, false),
    tracked: true,
  };
  if (out.poseWorldLandmarks.length !== 33) delete out.poseWorldLandmarks;
  if (results.segmentationMask) out.segmentationMask = maskValues(results.segmentationMask);
  return { json: JSON.stringify(out) };
}

// One detection at a time: the solutions' result callbacks are shared state.
let queue = Promise.resolve();
self.onmessage = (e) => {
  const { id, bytes, previewSide, person, track: frame } = e.data;
  queue = queue.then(async () => {
    let reply;
    try {
      reply = frame ? await track(bytes, frame === 'first') : await detect(bytes, previewSide, person);
    } catch (err) {
      reply = failed(`the person detector failed: ${err?.message ?? err}`);
    }
    const transfer = reply.preview ? [reply.preview.data.buffer] : [];
    self.postMessage({ id, ...reply }, transfer);
  });
};
