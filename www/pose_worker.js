// Person detection for the photo → body fit, in a dedicated worker so that
// MediaPipe's synchronous WebGL inference (seconds on a software GPU) never holds the page's UI
// thread. A classic worker: MediaPipe's legacy solutions load their runtimes with
// importScripts, which module workers lack. `pose_detect.js` is the page's side.
//
// MediaPipe Pose (BlazePose GHUM, Apache-2.0, see NOTICE) from the pinned npm package
// `@mediapipe/pose`, whose runtime and models `cargo xtask build-web` copies into
// dist/mediapipe/ (nothing is fetched from a CDN), and MediaPipe Selfie Segmentation
// (`@mediapipe/selfie_segmentation`, Apache-2.0, in dist/mediapipe/selfie_segmentation/),
// which sees everyone: Pose tracks one person, so with several the largest is cropped out
// for Pose.
//
// Messages: {id, bytes: Uint8Array, previewSide} in; {id, json, preview?} out, where json is
//   {"width", "height", "detectedWidth", "detectedHeight", "poseLandmarks": [33 × {x, y, z, visibility}],
//    "poseWorldLandmarks": [...], "segmentationMask": {"width", "height", "data": [0..1]},
//    "people": <number of people selfie segmentation sees; with several, the largest is fitted>}
//   or {"error": "<one sentence for the user>"},
// and preview (on success) is the detected photo at most previewSide on its long side:
// {width, height, data: Uint8Array RGBA, row-major from the top left}.
// Landmarks are normalised to the photo (so they hold for the original size, also after the
// downscale above 4 MP); the mask is at most 256 px on its long side.

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
    if (label[start] >= 0 || data[start] < 0.5) continue;
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
        if (nx >= 0 && ny >= 0 && nx < w && ny < h && label[j] < 0 && data[j] >= 0.5) {
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
  // The solution's mask carries the probability in red (and alpha on some GPUs): take the larger.
  for (let i = 0; i < w * h; i++) data[i] = Math.max(rgba[4 * i], rgba[4 * i + 3] < 255 ? rgba[4 * i + 3] : 0) / 255;
  return { width: w, height: h, data };
}

/** The detection itself: bytes → {json} ({json, preview} on success, see the header). */
async function detect(bytes, previewSide) {
  if (!bytes || bytes.length === 0) return failed('the file is empty');
  let bitmap;
  try {
    bitmap = await createImageBitmap(new Blob([bytes]));
  } catch (e) {
    return failed('the file is not an image the browser can read (or it is corrupt)');
  }
  const { width, height } = bitmap;
  if (width * height > MAX_PIXELS) {
    return failed(`the photo is ${width}×${height} pixels, over the 40 MP limit`);
  }
  if (width < 32 || height < 32) return failed(`the photo is ${width}×${height} pixels, too small to find a person in`);
  const k = Math.min(1, Math.sqrt(DETECT_PIXELS / (width * height)));
  const canvas = newCanvas(Math.max(1, Math.round(width * k)), Math.max(1, Math.round(height * k)));
  canvas.getContext('2d').drawImage(bitmap, 0, 0, canvas.width, canvas.height);
  bitmap.close();
  let pose;
  try {
    pose = await poseSolution();
  } catch (e) {
    return failed(`the person detector could not start: ${e.message ?? e}`);
  }
  // How many people: the connected regions of selfie segmentation's mask (it segments
  // everyone; Pose tracks one). With several, Pose runs on a crop around the largest.
  let people = null;
  let crop = null;
  try {
    const regions = await personRegions(canvas);
    people = regions.length;
    if (regions.length > 1) crop = padded(regions[0], canvas.width, canvas.height);
  } catch (e) {
    console.warn(`people count unavailable: ${e.message ?? e}`);
  }
  let source = canvas;
  if (crop) {
    source = newCanvas(crop.w, crop.h);
    source.getContext('2d').drawImage(canvas, crop.x, crop.y, crop.w, crop.h, 0, 0, crop.w, crop.h);
  }
  const results = await runSolution(pose, source).catch((e) => ({ error: e }));
  if (results.error) return failed(`the person detector failed: ${results.error.message ?? results.error}`);
  if (!results.poseLandmarks || results.poseLandmarks.length !== 33) return failed('no person found in the photo');
  // Crop-normalised → photo-normalised coordinates.
  const [ox, oy, sx, sy] = crop
    ? [crop.x / canvas.width, crop.y / canvas.height, crop.w / canvas.width, crop.h / canvas.height]
    : [0, 0, 1, 1];
  const plain = (list, toPhoto) => (list ?? []).map((l) => ({
    x: toPhoto ? ox + l.x * sx : l.x,
    y: toPhoto ? oy + l.y * sy : l.y,
    z: l.z,
    visibility: l.visibility ?? 1,
  }));
  const out = {
    width,
    height,
    detectedWidth: canvas.width,
    detectedHeight: canvas.height,
    poseLandmarks: plain(results.poseLandmarks, true),
    poseWorldLandmarks: plain(results.poseWorldLandmarks, false),
  };
  if (people !== null) out.people = people;
  if (out.poseWorldLandmarks.length !== 33) delete out.poseWorldLandmarks;
  if (results.segmentationMask) {
    let mask = results.segmentationMask;
    if (crop) {
      // The crop's mask placed in the whole photo.
      const full = newCanvas(canvas.width, canvas.height);
      full.getContext('2d').drawImage(mask, crop.x, crop.y, crop.w, crop.h);
      mask = full;
    }
    out.segmentationMask = maskValues(mask);
  }
  const { width: pw, height: ph, rgba } = pixelsAtMost(canvas, previewSide);
  return { json: JSON.stringify(out), preview: { width: pw, height: ph, data: new Uint8Array(rgba.buffer) } };
}


// One detection at a time: the solutions' result callbacks are shared state.
let queue = Promise.resolve();
self.onmessage = (e) => {
  const { id, bytes, previewSide } = e.data;
  queue = queue.then(async () => {
    let reply;
    try {
      reply = await detect(bytes, previewSide);
    } catch (err) {
      reply = failed(`the person detector failed: ${err?.message ?? err}`);
    }
    const transfer = reply.preview ? [reply.preview.data.buffer] : [];
    self.postMessage({ id, ...reply }, transfer);
  });
};
