//! Time slicing for long CPU stages on a host where one thread does everything: the browser's
//! UI thread, which must not be held for more than a few tens of milliseconds at a time (the
//! page stops drawing and answering input while it is).
//!
//! Core cannot yield to the browser itself (it knows no event loop), so a stage that loops over
//! many items calls [`checkpoint`] every few hundred of them, and the host installs a [`Hook`]
//! that decides at each checkpoint whether to give the thread back (the web app: when its
//! current slice has run longer than its budget, it resolves on the browser's next task).
//! Without a hook (native code, tests) a checkpoint is a no-op that completes at once, so the
//! same `async` stage runs natively under `readback::block_on_ready` or [`run_blocking`].
//!
//! Inside [`run_blocking`] (and `block_on_ready`) checkpoints never pause, whatever the hook:
//! a synchronous caller cannot wait for the browser.

use std::cell::{Cell, RefCell};
use std::future::Future;
use std::pin::Pin;
use std::rc::Rc;

/// A pause: resolves once the host has run its other work.
pub type Pause = Pin<Box<dyn Future<Output = ()>>>;

/// Asked at every [`checkpoint`]: `Some(pause)` to give the thread back, `None` to go on.
pub type Hook = Rc<dyn Fn() -> Option<Pause>>;

thread_local! {
    static HOOK: RefCell<Option<Hook>> = const { RefCell::new(None) };
    static BLOCKING: Cell<u32> = const { Cell::new(0) };
}

/// Install the host's hook for this thread (replacing any earlier one).
pub fn install(hook: Hook) {
    HOOK.with(|h| *h.borrow_mut() = Some(hook));
}

/// Remove the hook: checkpoints complete at once again.
pub fn uninstall() {
    HOOK.with(|h| *h.borrow_mut() = None);
}

/// A point where a long stage may give the thread back to the host (see the module docs).
pub async fn checkpoint() {
    if BLOCKING.with(Cell::get) > 0 {
        return;
    }
    // The hook is cloned out first: it may be replaced while the pause is awaited.
    let hook = HOOK.with(|h| h.borrow().clone());
    if let Some(pause) = hook.and_then(|h| h()) {
        let since = crate::util::profile::now();
        pause.await;
        crate::util::profile::yield_done(since);
    }
}

/// While alive, checkpoints on this thread complete at once.
pub(crate) struct BlockingScope;

impl BlockingScope {
    pub(crate) fn enter() -> Self {
        BLOCKING.with(|b| b.set(b.get() + 1));
        Self
    }
}

impl Drop for BlockingScope {
    fn drop(&mut self) {
        BLOCKING.with(|b| b.set(b.get() - 1));
    }
}

/// Run a CPU-only `async` stage (one that awaits nothing but checkpoints) to its end, on any
/// platform. Panics if it awaits anything else, which would be a bug in the caller: such a
/// future cannot finish without the host's event loop.
pub fn run_blocking<F: Future>(fut: F) -> F::Output {
    let _scope = BlockingScope::enter();
    let mut fut = std::pin::pin!(fut);
    let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
    match fut.as_mut().poll(&mut cx) {
        std::task::Poll::Ready(v) => v,
        std::task::Poll::Pending => panic!("run_blocking: the stage awaited something other than a checkpoint"),
    }
}

/// Call `each` on consecutive chunks of `items` (at most `chunk` long), with a [`checkpoint`]
/// after each: the usual shape of a sliced loop.
pub async fn for_chunks<T>(items: &[T], chunk: usize, mut each: impl FnMut(&[T])) {
    for c in items.chunks(chunk.max(1)) {
        each(c);
        checkpoint().await;
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::task::{Context, Poll, Waker};

    /// A pause that is pending once (as a browser's next task would be), then ready.
    pub(crate) struct PendingOnce(pub bool);

    impl Future for PendingOnce {
        type Output = ();
        fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
            if self.0 {
                Poll::Ready(())
            } else {
                self.0 = true;
                cx.waker().wake_by_ref();
                Poll::Pending
            }
        }
    }

    /// Install a hook that pauses at every checkpoint; returns the count of pauses taken.
    pub(crate) fn pause_always() -> Rc<Cell<usize>> {
        let n = Rc::new(Cell::new(0));
        let count = n.clone();
        install(Rc::new(move || {
            count.set(count.get() + 1);
            Some(Box::pin(PendingOnce(false)) as Pause)
        }));
        n
    }

    /// Poll `fut` to its end as an event loop would; returns the output and how many times it
    /// was pending (gave the thread back).
    pub(crate) fn drive<F: Future>(fut: F) -> (F::Output, usize) {
        let mut fut = std::pin::pin!(fut);
        let mut cx = Context::from_waker(Waker::noop());
        let mut pending = 0;
        loop {
            match fut.as_mut().poll(&mut cx) {
                Poll::Ready(v) => return (v, pending),
                Poll::Pending => pending += 1,
            }
        }
    }

    #[test]
    fn checkpoints_pause_only_under_a_hook_and_never_inside_run_blocking() {
        let sum = || async {
            let mut s = 0u64;
            for_chunks(&(0..1000u64).collect::<Vec<_>>(), 100, |c| s += c.iter().sum::<u64>()).await;
            s
        };
        // No hook: never pending.
        assert_eq!(drive(sum()), (499_500, 0));
        let pauses = pause_always();
        // A hook: one pause per chunk, same result.
        assert_eq!(drive(sum()), (499_500, 10));
        assert_eq!(pauses.get(), 10);
        // run_blocking: the hook is not even asked.
        assert_eq!(run_blocking(sum()), 499_500);
        assert_eq!(pauses.get(), 10);
        uninstall();
        assert_eq!(drive(sum()), (499_500, 0));
    }
}
