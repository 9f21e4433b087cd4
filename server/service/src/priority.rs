//! Which threads the kernel runs first when the cores are short.
//!
//! A real-time session's physics thread must start its step within a few tens of
//! microseconds of a device's command, and the command and its answer must cross the
//! gRPC runtime as fast: those run at the default priority, the physics thread with short
//! time slices. Everything else a server does can wait a millisecond without anyone
//! noticing, and is told so: the HTTP side (viewers' WebSockets, the REST API, the
//! viewer's files) runs on a runtime of its own whose threads are niced; lockstep scripts
//! and replays, which run as fast as they can, and the models' worker threads (a
//! multirate deformation step, a preconditioner rebuilt after a cut: results due tens of
//! steps later) run in the idle class, which any other thread preempts the moment it
//! wakes. Linux schedules threads, not processes, so each of these applies to the calling
//! thread only; lowering one's own priority needs no privilege, so they work in a
//! container as they do on a desk.

/// Niceness of the HTTP runtime's threads: a viewer's frame is encoded after the
/// haptic work that is ready, not instead of it. (Nice 10 weighs a tenth of nice 0:
/// under full load viewers still get a share, which a frame every 1/60 s needs.)
const HTTP_NICE: libc::c_int = 10;

/// Niceness of the threads that run as fast as they can (lockstep scripts, replays), kept
/// where the kernel refuses `SCHED_IDLE` (a sandbox that filters sched_setscheduler).
const BACKGROUND_NICE: libc::c_int = 19;

/// Asks Linux to wake this thread when its timers expire rather than up to 50 µs later
/// (the default timer slack): deadlines of a 1 kHz loop need it.
pub fn precise_timers() {
    #[cfg(target_os = "linux")]
    // SAFETY: PR_SET_TIMERSLACK takes an integer and affects only the calling thread.
    unsafe {
        libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0);
    }
}

/// The time slice the physics thread asks for, ns (the kernel's floor is 0.1 ms).
const PHYSICS_SLICE_NS: u64 = 100_000;

/// Asks Linux's EEVDF scheduler (6.12 and later) for short time slices for this thread:
/// waking for its step, a thread with a shorter slice than the one running preempts it
/// at once, where otherwise it may wait out the other's slice (3 ms by default: a
/// deformation worker or an encoder that just woke takes a whole one). Needs no
/// privilege; false where the kernel refused (older kernels run as before).
pub fn short_slices() -> bool {
    #[cfg(target_os = "linux")]
    // SAFETY: getpriority and gettid query the calling thread; sched_setattr with pid 0
    // changes only the calling thread and reads `attr`, which outlives the call and whose
    // `size` says how much of it the kernel may read.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        let attr = libc::sched_attr {
            size: std::mem::size_of::<libc::sched_attr>() as u32,
            sched_policy: libc::SCHED_OTHER as u32,
            sched_flags: 0,
            // The niceness it has (raising it back to 0 would need privilege).
            sched_nice: libc::getpriority(libc::PRIO_PROCESS, tid),
            sched_priority: 0,
            sched_runtime: PHYSICS_SLICE_NS,
            sched_deadline: 0,
            sched_period: 0,
        };
        libc::syscall(libc::SYS_sched_setattr, 0, &attr as *const libc::sched_attr, 0) == 0
    }
    #[cfg(not(target_os = "linux"))]
    false
}

/// Lowers this thread below the haptic path: for the HTTP runtime's threads.
pub fn below_haptics() {
    set_own_niceness(HTTP_NICE);
}

/// Puts this thread in the `SCHED_IDLE` class: a real-time session's physics thread
/// waking for its deadline preempts it at once and it runs on the CPU time real-time
/// sessions leave, so a bot's script beside them costs them little. It still runs when
/// real-time sessions saturate the cores, only slowly.
pub fn yield_to_real_time() {
    #[cfg(target_os = "linux")]
    // SAFETY: pid 0 is the calling thread, so sched_setscheduler changes only it and
    // `param` outlives the call.
    unsafe {
        let param = libc::sched_param { sched_priority: 0 };
        if libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) != 0 {
            set_own_niceness(BACKGROUND_NICE);
        }
    }
}

fn set_own_niceness(nice: libc::c_int) {
    #[cfg(target_os = "linux")]
    // SAFETY: gettid has no arguments, and setpriority on our own thread id changes only
    // this thread.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, nice);
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::{HTTP_NICE, PHYSICS_SLICE_NS, below_haptics, short_slices, yield_to_real_time};

    /// This thread's scheduling policy and niceness.
    fn own_scheduling() -> (libc::c_int, libc::c_int) {
        // SAFETY: pid 0 and PRIO_PROCESS with tid query the calling thread only.
        unsafe {
            let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
            (libc::sched_getscheduler(0), libc::getpriority(libc::PRIO_PROCESS, tid))
        }
    }

    /// Runs `f` on a new thread and returns what it returns, checking that the calling
    /// thread's scheduling is left as it was (each helper changes its own thread only).
    fn on_a_new_thread<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
        let before = own_scheduling();
        let out = std::thread::spawn(f).join().unwrap();
        assert_eq!(own_scheduling(), before, "only the calling thread changes");
        out
    }

    #[test]
    fn a_background_thread_leaves_the_cores_to_real_time_ones() {
        let (policy, nice) = on_a_new_thread(|| {
            yield_to_real_time();
            own_scheduling()
        });
        assert!(policy == libc::SCHED_IDLE || nice == 19, "policy {policy}, niceness {nice}");
    }

    #[test]
    fn an_http_thread_runs_below_the_haptic_path_and_alone() {
        let (policy, nice) = on_a_new_thread(|| {
            below_haptics();
            own_scheduling()
        });
        assert_eq!(policy, libc::SCHED_OTHER, "still scheduled with everyone else");
        assert!(nice >= HTTP_NICE, "niceness {nice}");
    }

    #[test]
    fn a_physics_thread_asks_for_short_slices_and_keeps_its_class() {
        let before = own_scheduling();
        let (granted, attr, scheduling) = on_a_new_thread(|| {
            let granted = short_slices();
            // SAFETY: an all-zero sched_attr is valid; sched_getattr with pid 0 writes at
            // most `size` bytes of it for the calling thread.
            let attr = unsafe {
                let mut attr: libc::sched_attr = std::mem::zeroed();
                let size = std::mem::size_of::<libc::sched_attr>() as libc::c_uint;
                assert_eq!(libc::syscall(libc::SYS_sched_getattr, 0, &mut attr as *mut libc::sched_attr, size, 0), 0);
                attr
            };
            (granted, attr, own_scheduling())
        });
        assert_eq!(scheduling, before, "same class and niceness as the thread that started it");
        if granted {
            assert_eq!(attr.sched_runtime, PHYSICS_SLICE_NS, "the slice asked for");
        }
    }
}
