//! Background tasks of the app (photo detection, body fit, reconstruction): async futures on
//! the page's event loop that report through an event queue the app drains every frame, and
//! stop at their next step when asked to (Cancel).

use std::cell::{Cell, RefCell};
use std::collections::VecDeque;
use std::rc::Rc;

use eframe::egui;
use wasm_bindgen::JsValue;
use wasm_bindgen_futures::JsFuture;

/// How the event queue treats an event.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum EventKind {
    /// Only the newest matters (progress, previews): it replaces the queue's last event when
    /// that is of this kind too.
    Latest,
    /// Kept, in order (a step's report).
    Log,
    /// The task's outcome (result, failure, cancellation): the task is finished.
    Outcome,
}

/// An event a task reports.
pub trait TaskEvent {
    fn kind(&self) -> EventKind;
}

/// What a task runs when it is cancelled.
type CancelHook = Box<dyn Fn()>;

/// A running task: its events, and the flag that cancels it.
pub struct Task<E> {
    events: Rc<RefCell<VecDeque<E>>>,
    cancel: Rc<Cell<bool>>,
    /// Told of a cancellation at once (a task running elsewhere: the reconstruction worker).
    on_cancel: Rc<RefCell<Option<CancelHook>>>,
    done: Rc<Cell<bool>>,
}

impl<E> Clone for Task<E> {
    fn clone(&self) -> Self {
        Self {
            events: self.events.clone(),
            cancel: self.cancel.clone(),
            on_cancel: self.on_cancel.clone(),
            done: self.done.clone(),
        }
    }
}

impl<E> Default for Task<E> {
    fn default() -> Self {
        Self {
            events: Default::default(),
            cancel: Default::default(),
            on_cancel: Default::default(),
            done: Default::default(),
        }
    }
}

impl<E: TaskEvent> Task<E> {
    /// Report `e` and ask for a repaint, so the app sees it on its next frame.
    pub fn push(&self, e: E, repaint: &egui::Context) {
        let mut q = self.events.borrow_mut();
        match e.kind() {
            EventKind::Latest => {
                if q.back().is_some_and(|b| b.kind() == EventKind::Latest) {
                    q.pop_back();
                }
            }
            EventKind::Log => {}
            EventKind::Outcome => self.done.set(true),
        }
        q.push_back(e);
        repaint.request_repaint();
    }
}

impl<E> Task<E> {
    /// Events since the last call.
    pub fn drain(&self) -> Vec<E> {
        self.events.borrow_mut().drain(..).collect()
    }

    /// Ask the task to stop at its next step (it reports its cancellation).
    pub fn cancel(&self) {
        self.cancel.set(true);
        if let Some(f) = self.on_cancel.borrow().as_ref() {
            f();
        }
    }

    /// Run `f` when the task is cancelled (it runs where [`Task::cancelled`] cannot be polled).
    pub fn on_cancel(&self, f: impl Fn() + 'static) {
        *self.on_cancel.borrow_mut() = Some(Box::new(f));
    }

    /// Cancel was asked for.
    pub fn cancelled(&self) -> bool {
        self.cancel.get()
    }

    /// The same task (not a clone of another's state).
    pub fn same(&self, other: &Task<E>) -> bool {
        Rc::ptr_eq(&self.done, &other.done)
    }

    /// It has reported its outcome (result, failure or cancellation).
    pub fn finished(&self) -> bool {
        self.done.get()
    }
}

/// Resolve on the browser's next task (`setTimeout(0)`, which browsers clamp to 4 ms when
/// nested), letting it render and handle input. Not `scheduler.yield()`: its continuations run
/// ahead of the page's other tasks, so a long job starved the frames that carry Cancel.
pub async fn yield_to_browser() {
    sleep_ms(0).await
}

/// Wait `ms` milliseconds (a timer task; at once if no timer can be set).
pub async fn sleep_ms(ms: i32) {
    let promise = js_sys::Promise::new(&mut |resolve, _reject| {
        // A failed setTimeout leaves the promise pending: resolve at once instead.
        if crate::platform::set_timeout(&resolve, ms).is_err() {
            let _ = resolve.call0(&JsValue::NULL);
        }
    });
    // The promise only resolves.
    let _ = JsFuture::from(promise).await;
}

/// How long, in milliseconds, a background stage keeps the UI thread before giving it back at
/// its next checkpoint. The app bounds a task at 100 ms: a task is this plus the stretch to
/// the next checkpoint (up to ~60 ms on the test machine: a fit step's silhouette edges).
pub const SLICE_MS: f64 = 10.0;

/// The reconstruction worker's slice: it draws nothing, so it yields only to let Cancel in (a
/// yield costs a clamped `setTimeout`, ≥ 4 ms).
pub const WORKER_SLICE_MS: f64 = 200.0;

thread_local! {
    /// When the last paused stage resumed: no task that runs a stage started before it.
    static SLICE_START: Cell<f64> = const { Cell::new(f64::NEG_INFINITY) };
}

/// Give the thread back if the current slice is over: core's checkpoint, which the app's own
/// loops (the fit's steps) use too, under the hook of [`install_time_slicing`].
pub use getavatar_core::util::cooperative::checkpoint;

/// Make core's checkpoints (`getavatar_core::util::cooperative`) yield to the browser once a slice
/// has run `slice_ms` ([`SLICE_MS`] on the page): the template SDF, the posed grid, generation
/// and the fits then run in slices between frames instead of freezing the page.
pub fn install_time_slicing(slice_ms: f64) {
    getavatar_core::util::cooperative::install(Rc::new(move || {
        if crate::platform::now_ms() - SLICE_START.with(Cell::get) < slice_ms {
            return None;
        }
        Some(Box::pin(async {
            yield_to_browser().await;
            SLICE_START.with(|s| s.set(crate::platform::now_ms()));
        }))
    }));
}
