// The page's side of person detection: the photo's bytes go to a dedicated worker
// (`pose_worker.js`, MediaPipe Pose + Selfie Segmentation), so detection never blocks the UI
// thread; the app awaits the answer.
//
// detectPose(bytes, previewSide, person = -1) → JSON string: the detector's answer (see
//   pose_worker.js) or {"error": "<one sentence for the user>"}; person ≥ 0 reads only that
//   region (0 = the largest).
// detectVideoFrame(bytes, first) → the same JSON for a video's frame, read by Pose's tracking
//   mode (frames in order; `first` starts a clip).
// photoPreview() → the last successfully detected photo at most previewSide pixels on its long
//   side, {width, height, data: Uint8Array (RGBA, row-major from the top left)}, or null.

const fail = (error) => JSON.stringify({ error });

let worker = null;
let nextId = 1;
const pending = new Map();
let lastPreview = null;

/** The worker (started on first use; started again after it failed). */
function detector() {
  if (worker) return worker;
  const w = new Worker(new URL('./pose_worker.js', import.meta.url));
  w.onmessage = (e) => {
    const p = pending.get(e.data.id);
    pending.delete(e.data.id);
    p?.(e.data);
  };
  // The script failed to load or threw outside a detection: answer everything in flight and
  // start a fresh worker next time.
  const stop = (why) => {
    for (const p of pending.values()) p({ json: fail(`the person detector stopped: ${why}`) });
    pending.clear();
    w.terminate();
    if (worker === w) worker = null;
  };
  w.onerror = (e) => { e.preventDefault?.(); stop(e.message || 'its script failed'); };
  w.onmessageerror = () => stop('a message could not be read');
  worker = w;
  return w;
}

/** The worker's reply to `message` plus the image's bytes (copied, then transferred), or a
 * reply with the error when the worker cannot start. */
async function ask(bytes, message) {
  let w;
  try {
    w = detector();
  } catch (e) {
    return { json: fail(`the person detector could not start: ${e.message ?? e}`) };
  }
  const copy = bytes.slice();
  const id = nextId++;
  return new Promise((resolve) => {
    pending.set(id, resolve);
    w.postMessage({ id, bytes: copy, ...message }, [copy.buffer]);
  });
}

export async function detectPose(bytes, previewSide, person = -1) {
  if (!bytes || bytes.length === 0) return fail('the file is empty');
  lastPreview = null;
  const reply = await ask(bytes, { previewSide, person });
  lastPreview = reply.preview ?? null;
  return reply.json;
}

/** A video's frame (PNG/JPEG bytes) through Pose's tracking mode, in order: `first` starts a
 * new clip. → JSON string as detectPose's (no preview). */
export async function detectVideoFrame(bytes, first) {
  if (!bytes || bytes.length === 0) return fail('the frame is empty');
  return (await ask(bytes, { track: first ? 'first' : 'next' })).json;
}

export function photoPreview() {
  return lastPreview;
}
