// Person detection for the photo → body fit (issue #20): MediaPipe Pose (BlazePose GHUM,
// Apache-2.0, see NOTICE) from the pinned npm package `@mediapipe/pose`, whose runtime and
// models `cargo xtask build-web` copies into dist/mediapipe/ (nothing is fetched from a CDN).
//
// detectPose(bytes) → JSON string, one of
//   {"width", "height", "detectedWidth", "detectedHeight", "poseLandmarks": [33 × {x, y, z, visibility}],
//    "poseWorldLandmarks": [...], "segmentationMask": {"width", "height", "data": [0..1]}}
//   {"error": "<one sentence for the user>"}
// Landmarks are normalised to the photo (so they hold for the original size, also after the
// downscale above 4 MP); the mask is at most 256 px on its long side.

const MAX_PIXELS = 40e6; // refused above this
const DETECT_PIXELS = 4e6; // downscaled above this before detection
const MASK_SIDE = 256;
const MODEL_DIR = 'mediapipe/';

let posePromise = null;
// The last photo that went to the detector (a canvas), for photoPreview().
let lastPhoto = null;

function loadScript(src) {
  return new Promise((resolve, reject) => {
    const s = document.createElement('script');
    s.src = src;
    s.onload = () => resolve();
    s.onerror = () => reject(new Error(`could not load ${src}`));
    document.head.appendChild(s);
  });
}

async function poseSolution() {
  if (!posePromise) {
    posePromise = (async () => {
      await loadScript(`${MODEL_DIR}pose.js`);
      const pose = new window.Pose({ locateFile: (file) => `${MODEL_DIR}${file}` });
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

/** An image (canvas / ImageBitmap) drawn at most `maxSide` on its long side: {width, height, rgba}. */
function pixelsAtMost(image, maxSide) {
  const k = Math.min(1, maxSide / Math.max(image.width, image.height));
  const w = Math.max(1, Math.round(image.width * k));
  const h = Math.max(1, Math.round(image.height * k));
  const c = document.createElement('canvas');
  c.width = w;
  c.height = h;
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

export async function detectPose(bytes) {
  if (!bytes || bytes.length === 0) return fail('the file is empty');
  let bitmap;
  try {
    bitmap = await createImageBitmap(new Blob([bytes]));
  } catch (e) {
    return fail('the file is not an image the browser can read (or it is corrupt)');
  }
  const { width, height } = bitmap;
  if (width * height > MAX_PIXELS) {
    return fail(`the photo is ${width}×${height} pixels, over the 40 MP limit`);
  }
  if (width < 32 || height < 32) return fail(`the photo is ${width}×${height} pixels, too small to find a person in`);
  const k = Math.min(1, Math.sqrt(DETECT_PIXELS / (width * height)));
  const canvas = document.createElement('canvas');
  canvas.width = Math.max(1, Math.round(width * k));
  canvas.height = Math.max(1, Math.round(height * k));
  canvas.getContext('2d').drawImage(bitmap, 0, 0, canvas.width, canvas.height);
  bitmap.close();
  lastPhoto = null;
  let pose;
  try {
    pose = await poseSolution();
  } catch (e) {
    return fail(`the person detector could not start: ${e.message ?? e}`);
  }
  const results = await new Promise((resolve, reject) => {
    pose.onResults(resolve);
    pose.send({ image: canvas }).catch(reject);
  }).catch((e) => ({ error: e }));
  if (results.error) return fail(`the person detector failed: ${results.error.message ?? results.error}`);
  if (!results.poseLandmarks || results.poseLandmarks.length !== 33) return fail('no person found in the photo');
  const plain = (list) => (list ?? []).map((l) => ({ x: l.x, y: l.y, z: l.z, visibility: l.visibility ?? 1 }));
  const out = {
    width,
    height,
    detectedWidth: canvas.width,
    detectedHeight: canvas.height,
    poseLandmarks: plain(results.poseLandmarks),
    poseWorldLandmarks: plain(results.poseWorldLandmarks),
  };
  if (out.poseWorldLandmarks.length !== 33) delete out.poseWorldLandmarks;
  if (results.segmentationMask) out.segmentationMask = maskValues(results.segmentationMask);
  lastPhoto = canvas;
  return JSON.stringify(out);
}

/**
 * The last detected photo at most `maxSide` pixels on its long side, for the app to show:
 * {width, height, data: Uint8Array (RGBA, row-major from the top left)}, or null before any.
 */
export function photoPreview(maxSide) {
  if (!lastPhoto) return null;
  const { width, height, rgba } = pixelsAtMost(lastPhoto, maxSide);
  return { width, height, data: new Uint8Array(rgba.buffer) };
}
