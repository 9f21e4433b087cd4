//! Work that can wait, done on a thread of its own and swapped in at a step fixed in
//! advance.
//!
//! A model submits a job at step `k` and takes its result at step `k + delay`, whatever
//! the clock says: if the worker has not finished by then the step waits for it (the
//! wait is counted), so that a run gives the same results — the same state hash —
//! whether it runs in real time, in lockstep or as a replay, on a fast machine or a
//! slow one. Jobs and results travel through bounded channels of one slot: submitting
//! and taking allocate nothing. A step that waits polls the channel instead of blocking
//! on it: a blocking receive registers the thread with the channel, which allocates on
//! a thread's first wait (found by tests/no_allocation.rs on a loaded machine).

use std::sync::OnceLock;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::time::{Duration, Instant};

/// What every worker thread runs first, set once per process by whoever knows how its
/// threads should be scheduled (the server puts them below its real-time threads).
static WORKER_SETUP: OnceLock<fn()> = OnceLock::new();

/// Sets what every worker thread started from now on runs first (once per process; a
/// second call is ignored and returns false). The server uses it to put work that can
/// wait in a scheduling class that any thread with deadlines preempts at once.
pub fn set_worker_setup(setup: fn()) -> bool {
    WORKER_SETUP.set(setup).is_ok()
}

/// A worker thread running `work` on the jobs it is given, one at a time.
pub struct Background<I: Send + 'static, O: Send + 'static> {
    jobs: SyncSender<I>,
    results: Receiver<O>,
    /// The step at which the pending job's result is due.
    due: Option<u64>,
    /// Times a step had to wait for a result, and for how long in all.
    pub waits: u64,
    pub waited: Duration,
    _thread: std::thread::JoinHandle<()>,
}

impl<I: Send + 'static, O: Send + 'static> Background<I, O> {
    pub fn new(name: &str, mut work: impl FnMut(I) -> O + Send + 'static) -> std::io::Result<Self> {
        let (jobs, job_rx) = sync_channel::<I>(1);
        let (result_tx, results) = sync_channel::<O>(1);
        let thread = std::thread::Builder::new().name(name.into()).spawn(move || {
            if let Some(setup) = WORKER_SETUP.get() {
                setup();
            }
            while let Ok(job) = job_rx.recv() {
                if result_tx.send(work(job)).is_err() {
                    break;
                }
            }
        })?;
        Ok(Self { jobs, results, due: None, waits: 0, waited: Duration::ZERO, _thread: thread })
    }

    /// Whether a job is out.
    pub fn busy(&self) -> bool {
        self.due.is_some()
    }

    /// The step at which the pending job's result will be taken.
    pub fn due(&self) -> Option<u64> {
        self.due
    }

    /// Hands a job over; its result is taken at step `due`. Returns the job back when
    /// one is already out (or the worker is gone).
    pub fn submit(&mut self, job: I, due: u64) -> Result<(), I> {
        if self.due.is_some() {
            return Err(job);
        }
        self.jobs.send(job).map_err(|e| e.0)?;
        self.due = Some(due);
        Ok(())
    }

    /// At step `step`: the pending job's result if it is due now (waiting for it if the
    /// worker has not finished), else None. None also when the worker died (its panic
    /// is its own; the model goes on without the result).
    pub fn take_if_due(&mut self, step: u64) -> Option<O> {
        if self.due != Some(step) {
            return None;
        }
        self.due = None;
        match self.results.try_recv() {
            Ok(result) => Some(result),
            Err(std::sync::mpsc::TryRecvError::Empty) => {
                let started = Instant::now();
                let result = poll_until_ready(&self.results, started);
                self.waits += 1;
                self.waited += started.elapsed();
                result
            }
            Err(std::sync::mpsc::TryRecvError::Disconnected) => None,
        }
    }

    /// The pending job's result now, before its step (waiting for the worker if it has
    /// not finished; not counted as a step's wait): for a caller that needs what the job
    /// holds (a copy of a model whose state is out with its worker). None when no job is
    /// out or the worker died.
    pub fn take_early(&mut self) -> Option<O> {
        self.due.take()?;
        match self.results.try_recv() {
            Ok(result) => Some(result),
            Err(std::sync::mpsc::TryRecvError::Empty) => poll_until_ready(&self.results, Instant::now()),
            Err(std::sync::mpsc::TryRecvError::Disconnected) => None,
        }
    }
}

/// Polls `results` until a result arrives (None: the worker is gone), giving the CPU
/// away between polls: yielding for the first 0.2 ms (the worker may share this core),
/// then sleeping 50 µs at a time. Neither allocates.
fn poll_until_ready<O>(results: &Receiver<O>, started: Instant) -> Option<O> {
    loop {
        match results.try_recv() {
            Ok(result) => return Some(result),
            Err(std::sync::mpsc::TryRecvError::Disconnected) => return None,
            Err(std::sync::mpsc::TryRecvError::Empty) if started.elapsed() < Duration::from_micros(200) => std::thread::yield_now(),
            Err(std::sync::mpsc::TryRecvError::Empty) => std::thread::sleep(Duration::from_micros(50)),
        }
    }
}

/// The result due at `step` of a model whose pending job is either `precomputed` (a copy
/// of the model computed it when it was made: see the models' `Clone`) or out with
/// `worker`; a wait for the worker is added to `waits`.
pub fn take_due<I: Send + 'static, O: Send + 'static>(precomputed: &mut Option<O>, worker: Option<&mut Background<I, O>>, step: u64, waits: &mut u64) -> Option<O> {
    if let Some(result) = precomputed.take() {
        return Some(result);
    }
    let worker = worker.expect("a worker has the job");
    let before = worker.waits;
    let result = worker.take_if_due(step);
    *waits += worker.waits - before;
    result
}

impl<I: Send + 'static, O: Send + 'static> std::fmt::Debug for Background<I, O> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Background").field("due", &self.due).field("waits", &self.waits).finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_result_is_taken_exactly_at_its_step_however_long_it_takes() {
        let mut worker = Background::new("test-worker", |x: u64| {
            std::thread::sleep(Duration::from_millis(30));
            x * 2
        })
        .unwrap();
        worker.submit(21, 5).unwrap();
        assert_eq!(worker.submit(1, 6), Err(1), "one job at a time");
        for step in 0..5 {
            assert_eq!(worker.take_if_due(step), None);
        }
        // Step 5 comes sooner than the 30 ms the job takes: the step waits for it.
        assert_eq!(worker.take_if_due(5), Some(42));
        assert_eq!(worker.waits, 1);
        assert!(!worker.busy());
        worker.submit(1, 7).unwrap();
        std::thread::sleep(Duration::from_millis(60));
        assert_eq!(worker.take_if_due(7), Some(2));
        assert_eq!(worker.waits, 1, "a finished job is taken without a wait");
    }

    #[test]
    fn every_worker_thread_runs_the_process_setup_first() {
        use std::sync::atomic::{AtomicU64, Ordering};
        thread_local! {
            static SET_UP: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
        }
        static SETUPS: AtomicU64 = AtomicU64::new(0);
        fn setup() {
            SET_UP.with(|s| s.set(true));
            SETUPS.fetch_add(1, Ordering::Relaxed);
        }
        assert!(set_worker_setup(setup), "the first setup is taken");
        assert!(!set_worker_setup(|| {}), "a second one is ignored");
        // The job runs on the worker thread, after the setup ran there.
        let mut worker = Background::new("setup-test", |_: ()| SET_UP.with(|s| s.get())).unwrap();
        worker.submit((), 1).unwrap();
        assert_eq!(worker.take_if_due(1), Some(true));
        assert!(SETUPS.load(Ordering::Relaxed) >= 1);
        assert!(!SET_UP.with(|s| s.get()), "not on the thread that started the worker");
    }
}
