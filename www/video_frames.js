// A video's frames in the page, for "Motion from video…": the browser's own decoder (a
// <video> element on a Blob URL of the file's bytes: the video never leaves the page) seeks
// to each frame read, draws it on a canvas, and MediaPipe Pose reads it in its tracking mode
// in the detector worker (pose_detect.js → pose_worker.js), off the UI thread.
//
// openVideo(bytes) → JSON {width, height, seconds} (seconds may be null: the file does not
//   say), or {"error": "<one sentence>"}; closes the previous video.
// detectVideoAt(seconds, first, maxSide) → pose_detect.js's detectVideoFrame answer (JSON)
//   for the frame shown at `seconds`, drawn at most `maxSide` pixels on its long side; `first`
//   starts the tracker afresh.
// closeVideo() → lets the video and its bytes go.

import { detectVideoFrame } from './pose_detect.js';

const fail = (error) => JSON.stringify({ error });
/// How long the decoder may take to open a file or to reach a frame, ms.
const OPEN_MS = 30000;
const SEEK_MS = 10000;

let video = null;
let url = null;
let canvas = null;

/** Resolve with the first of `events` on `target` (null), or the error's text, or a timeout's. */
function once(target, events, ms, timeoutText) {
  return new Promise((resolve) => {
    const done = (v) => {
      clearTimeout(timer);
      for (const e of events) target.removeEventListener(e, ok);
      target.removeEventListener('error', bad);
      resolve(v);
    };
    const ok = () => done(null);
    const bad = () => done(target.error ? `error ${target.error.code}` : 'error');
    const timer = setTimeout(() => done(timeoutText), ms);
    for (const e of events) target.addEventListener(e, ok);
    target.addEventListener('error', bad);
  });
}

export async function openVideo(bytes) {
  closeVideo();
  if (!bytes || bytes.length === 0) return fail('the file is empty');
  url = URL.createObjectURL(new Blob([bytes]));
  const v = document.createElement('video');
  v.muted = true;
  v.playsInline = true;
  v.preload = 'auto';
  const loaded = once(v, ['loadeddata'], OPEN_MS, 'timeout');
  v.src = url;
  const why = await loaded;
  if (why !== null) {
    closeVideo();
    return fail(why === 'timeout'
      ? `the browser could not open it within ${OPEN_MS / 1000} s`
      : 'it is not a video this browser can decode (MP4 with H.264, WebM or MOV are)');
  }
  video = v;
  const seconds = Number.isFinite(v.duration) ? v.duration : null;
  return JSON.stringify({ width: v.videoWidth, height: v.videoHeight, seconds });
}

export async function detectVideoAt(seconds, first, maxSide) {
  const v = video;
  if (!v) return fail('no video is open');
  const seeked = once(v, ['seeked'], SEEK_MS, 'timeout');
  v.currentTime = seconds;
  const why = await seeked;
  if (why !== null) return fail(`the browser could not show the frame at ${seconds.toFixed(2)} s (${why})`);
  const s = Math.min(1, maxSide / Math.max(v.videoWidth, v.videoHeight));
  const w = Math.max(1, Math.round(v.videoWidth * s));
  const h = Math.max(1, Math.round(v.videoHeight * s));
  if (!canvas || canvas.width !== w || canvas.height !== h) canvas = new OffscreenCanvas(w, h);
  const ctx = canvas.getContext('2d');
  ctx.drawImage(v, 0, 0, w, h);
  const blob = await canvas.convertToBlob({ type: 'image/jpeg', quality: 0.92 });
  return detectVideoFrame(new Uint8Array(await blob.arrayBuffer()), first);
}

export function closeVideo() {
  if (video) {
    video.removeAttribute('src');
    video.load();
  }
  video = null;
  if (url) URL.revokeObjectURL(url);
  url = null;
  canvas = null;
}
