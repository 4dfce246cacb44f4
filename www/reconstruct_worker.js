// The reconstruction worker (`crates/web/src/reconstruct/worker.rs`): a module
// worker that runs a second instance of the app's wasm module, whose start-up sees no window
// and so only waits for jobs. The page posts {json, ...typed arrays}; the module answers the
// same way through this scope's postMessage. Messages that arrive while the module loads wait
// for it, in order.
import init, { reconstruct_worker_message } from './getavatar_web.js';

const ready = init();
// Said once, though every message waiting for the module (a job's files, then the job) fails.
let toldUnavailable = false;

function say(event, message) {
  self.postMessage({ json: JSON.stringify({ event, message }) });
}

self.onmessage = async (e) => {
  try {
    await ready;
  } catch (err) {
    // No module here (no WebAssembly, or its file did not load): the page reconstructs itself.
    if (!toldUnavailable) say('unavailable', `the worker could not load the app's module: ${err?.message ?? err}`);
    toldUnavailable = true;
    return;
  }
  try {
    reconstruct_worker_message(e.data);
  } catch (err) {
    // The module aborted (its panic hook has said why, where it could).
    say('fatal', `${err?.message ?? err}`);
  }
};
