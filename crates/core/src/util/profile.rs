//! Stage timings of a generation: per stage, the milliseconds of our own code on
//! the CPU or in wasm (`host_ms`), the milliseconds spent awaiting GPU→CPU read-backs
//! (`gpu_wait_ms`), the read-backs themselves, and in the browser the time given back to the
//! page between slices ([`crate::util::cooperative`], `yield_ms`: neither host nor GPU work of ours).
//!
//! Recording is per thread and off unless [`start`] was called: a caller starts it with its
//! clock (natively `std::time::Instant`, in the browser `performance.now()`; this crate has no
//! clock of its own on wasm32), marks each stage with [`stage`] before its work, and takes the
//! table with [`finish`]. [`crate::generator::readback::read_f32`] and [`crate::util::cooperative::checkpoint`]
//! report their waits to it.
//!
//! With the `wgpu` feature, each stage also counts the GPU dispatches (kernel launches) issued
//! while it was open, through cubecl's launch observer. The observer is process-wide, so
//! launches of other threads during a recording count too.
//!
//! burn queues GPU work lazily, so a stage's GPU time shows up as the wait of the stage whose
//! read-back forces it (the triplanes' synthesis is waited for in the grid decode's read-back),
//! or as host time of a later stage whose launches block until cubecl's queue drains (seen on
//! an H200 at the paper config). [`start_synced`] waits for the device at each stage's end instead, so each stage carries its
//! own GPU time (at the cost of host and GPU no longer overlapping).
//! On one thread, work of another task that overlaps a recording (a texture bake running
//! while a generation does) is counted in it.

use std::cell::RefCell;

use serde::{Deserialize, Serialize};

/// Milliseconds since some fixed instant.
pub type Clock = fn() -> f64;

/// One stage's times.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StageTime {
    pub stage: String,
    /// Wall time minus GPU waits and yields.
    pub host_ms: f64,
    pub gpu_wait_ms: f64,
    pub yield_ms: f64,
    /// GPU→CPU read-backs awaited.
    pub readbacks: u32,
    /// GPU kernel launches issued (0 without the `wgpu` feature, and on NdArray).
    #[serde(default)]
    pub dispatches: u64,
}

/// The stages of one recording, in order.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StageProfile {
    pub stages: Vec<StageTime>,
}

impl StageProfile {
    pub fn host_ms(&self) -> f64 {
        self.stages.iter().map(|s| s.host_ms).sum()
    }

    pub fn gpu_wait_ms(&self) -> f64 {
        self.stages.iter().map(|s| s.gpu_wait_ms).sum()
    }

    pub fn readbacks(&self) -> u32 {
        self.stages.iter().map(|s| s.readbacks).sum()
    }

    pub fn dispatches(&self) -> u64 {
        self.stages.iter().map(|s| s.dispatches).sum()
    }

    /// A Markdown table: stage, host ms, GPU wait ms, read-backs, GPU dispatches, and the
    /// totals.
    pub fn table(&self) -> String {
        let mut out =
            String::from("| stage | host ms | GPU wait ms | read-backs | dispatches |\n|---|---|---|---|---|\n");
        for s in &self.stages {
            out += &format!(
                "| {} | {:.1} | {:.1} | {} | {} |\n",
                s.stage, s.host_ms, s.gpu_wait_ms, s.readbacks, s.dispatches
            );
        }
        out += &format!(
            "| total | {:.1} | {:.1} | {} | {} |\n",
            self.host_ms(),
            self.gpu_wait_ms(),
            self.readbacks(),
            self.dispatches()
        );
        out
    }
}

/// Waits for the device's queued work to finish (`Device::sync`), for a recording that
/// charges each stage with its own GPU time ([`start_synced`]).
pub type StageSync = Box<dyn FnMut()>;

struct Recorder {
    clock: Clock,
    /// Called as each stage ends, its time counted as the stage's GPU wait.
    sync: Option<StageSync>,
    /// The open stage, when it began, and the dispatch count then.
    current: Option<(StageTime, f64, u64)>,
    done: Vec<StageTime>,
    /// Counts launches while the recording lives.
    _dispatches: dispatch_count::Observation,
}

impl Recorder {
    fn close(&mut self) {
        if let Some((mut s, t0, d0)) = self.current.take() {
            if let Some(sync) = self.sync.as_mut() {
                let t = (self.clock)();
                sync();
                s.gpu_wait_ms += (self.clock)() - t;
            }
            let wall = (self.clock)() - t0;
            s.host_ms = (wall - s.gpu_wait_ms - s.yield_ms).max(0.0);
            s.dispatches = dispatch_count::total() - d0;
            self.done.push(s);
        }
    }
}

/// GPU dispatches, counted by cubecl's launch observer while a recording is installed.
#[cfg(feature = "wgpu")]
pub mod dispatch_count {
    use std::collections::BTreeMap;
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::sync::{Arc, Mutex};

    use cubecl_runtime::logging::{LaunchObservation, LaunchObserver};

    static LAUNCHES: AtomicU64 = AtomicU64::new(0);
    static BY_KERNEL: Mutex<BTreeMap<&'static str, u64>> = Mutex::new(BTreeMap::new());

    struct Count;

    impl LaunchObserver for Count {
        fn launched(&self, kernel: &'static str) {
            LAUNCHES.fetch_add(1, Ordering::Relaxed);
            *BY_KERNEL.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).entry(kernel).or_default() += 1;
        }
    }

    /// Launches counted since the process started (only while an observation was live).
    pub fn total() -> u64 {
        LAUNCHES.load(Ordering::Relaxed)
    }

    /// Launches counted so far per kernel name (as the kernel names itself), most first.
    pub fn by_kernel() -> Vec<(&'static str, u64)> {
        // A panic while counting cannot leave the map half-written: take it as it is.
        let m = BY_KERNEL.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        let mut v: Vec<_> = m.iter().map(|(k, n)| (*k, *n)).collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(b.0)));
        v
    }

    /// Counting, until dropped.
    pub struct Observation(#[allow(dead_code)] LaunchObservation);

    pub fn observe() -> Observation {
        Observation(LaunchObservation::new(Arc::new(Count)))
    }
}

/// Without the `wgpu` feature nothing dispatches GPU kernels.
#[cfg(not(feature = "wgpu"))]
pub mod dispatch_count {
    pub fn total() -> u64 {
        0
    }

    pub fn by_kernel() -> Vec<(&'static str, u64)> {
        Vec::new()
    }

    pub struct Observation;

    pub fn observe() -> Observation {
        Observation
    }
}

thread_local! {
    static RECORDER: RefCell<Option<Recorder>> = const { RefCell::new(None) };
}

/// Start recording on this thread (a recording already running is dropped).
pub fn start(clock: Clock) {
    install(clock, None);
}

/// Start recording with `sync` called as each stage ends: each stage's GPU work then counts
/// as its own wait instead of the wait of the read-back that forces it. This serialises host
/// and GPU (a pipelined generation overlaps them), so the total is a bound, not the app's time.
pub fn start_synced(clock: Clock, sync: StageSync) {
    install(clock, Some(sync));
}

fn install(clock: Clock, sync: Option<StageSync>) {
    RECORDER.with(|r| {
        // The old recording's observation ends before the new one begins (one slot).
        r.borrow_mut().take();
        *r.borrow_mut() =
            Some(Recorder { clock, sync, current: None, done: Vec::new(), _dispatches: dispatch_count::observe() })
    });
}

/// End the open stage and begin `name` (no-op when not recording).
pub fn stage(name: &str) {
    RECORDER.with(|r| {
        if let Some(rec) = r.borrow_mut().as_mut() {
            rec.close();
            let t0 = (rec.clock)();
            let d0 = dispatch_count::total();
            rec.current = Some((StageTime { stage: name.to_string(), ..StageTime::default() }, t0, d0));
        }
    });
}

/// End the recording; `None` when none was running.
pub fn finish() -> Option<StageProfile> {
    RECORDER.with(|r| {
        r.borrow_mut().take().map(|mut rec| {
            rec.close();
            StageProfile { stages: rec.done }
        })
    })
}

/// The recording's clock, when recording.
pub(crate) fn now() -> Option<f64> {
    RECORDER.with(|r| r.borrow().as_ref().map(|rec| (rec.clock)()))
}

fn add(f: impl FnOnce(&mut StageTime)) {
    RECORDER.with(|r| {
        if let Some((s, _, _)) = r.borrow_mut().as_mut().and_then(|rec| rec.current.as_mut()) {
            f(s);
        }
    });
}

/// A read-back that began at `since` (from [`now`]) has completed. (Its callers, the
/// read-backs, come with the tensor features.)
#[cfg_attr(not(any(feature = "ndarray", feature = "autodiff", feature = "wgpu")), allow(dead_code))]
pub(crate) fn readback_done(since: Option<f64>) {
    if let (Some(t0), Some(t1)) = (since, now()) {
        add(|s| {
            s.gpu_wait_ms += t1 - t0;
            s.readbacks += 1;
        });
    }
}

/// A pause that began at `since` has resumed.
pub(crate) fn yield_done(since: Option<f64>) {
    if let (Some(t0), Some(t1)) = (since, now()) {
        add(|s| s.yield_ms += t1 - t0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;

    thread_local! {
        static T: Cell<f64> = const { Cell::new(0.0) };
    }
    fn fake_clock() -> f64 {
        T.with(Cell::get)
    }
    fn advance(ms: f64) {
        T.with(|t| t.set(t.get() + ms));
    }

    #[test]
    fn stages_split_wall_time_into_host_gpu_waits_and_yields() {
        assert!(finish().is_none(), "nothing recorded unless started");
        stage("ignored");
        readback_done(Some(0.0));
        start(fake_clock);
        stage("a");
        advance(3.0);
        let t = now();
        advance(5.0); // a read-back
        readback_done(t);
        advance(2.0);
        stage("b");
        let t = now();
        advance(4.0); // a yield
        yield_done(t);
        advance(1.0);
        let t = now();
        advance(6.0);
        readback_done(t);
        let p = finish().unwrap();
        assert_eq!(p.stages.len(), 2);
        let (a, b) = (&p.stages[0], &p.stages[1]);
        assert_eq!((a.stage.as_str(), a.host_ms, a.gpu_wait_ms, a.yield_ms, a.readbacks), ("a", 5.0, 5.0, 0.0, 1));
        assert_eq!((b.stage.as_str(), b.host_ms, b.gpu_wait_ms, b.yield_ms, b.readbacks), ("b", 1.0, 6.0, 4.0, 1));
        assert_eq!((p.host_ms(), p.gpu_wait_ms(), p.readbacks()), (6.0, 11.0, 2));
        assert!(p.table().contains("| total | 6.0 | 11.0 | 2 | 0 |"), "{}", p.table());
        assert!(finish().is_none(), "finish ends the recording");
    }

    #[test]
    fn a_synced_recording_charges_each_stage_with_its_sync() {
        T.with(|t| t.set(0.0));
        let calls = std::rc::Rc::new(Cell::new(0));
        let seen = calls.clone();
        start_synced(
            fake_clock,
            Box::new(move || {
                seen.set(seen.get() + 1);
                advance(7.0); // the device draining
            }),
        );
        stage("a");
        advance(2.0);
        stage("b");
        advance(1.0);
        let p = finish().unwrap();
        assert_eq!(calls.get(), 2, "one sync per stage end");
        let (a, b) = (&p.stages[0], &p.stages[1]);
        assert_eq!((a.host_ms, a.gpu_wait_ms, a.readbacks), (2.0, 7.0, 0));
        assert_eq!((b.host_ms, b.gpu_wait_ms, b.readbacks), (1.0, 7.0, 0));
    }
}
