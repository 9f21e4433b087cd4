//! Which threads the kernel runs first when the cores are short.
//!
//! A real-time session's physics thread must start its step within a few tens of
//! microseconds of a device's command, and the command and its answer must cross the
//! gRPC runtime as fast: those run at the default priority. Everything else a server
//! does can wait a millisecond without anyone noticing, and is told so: the HTTP side
//! (viewers' WebSockets, the REST API, the viewer's files) runs on a runtime of its own
//! whose threads are niced, and lockstep scripts and replays, which run as fast as they
//! can, take only the CPU real-time sessions leave. Linux schedules threads, not
//! processes, so each of these applies to the calling thread only; lowering one's own
//! priority needs no privilege, so they work in a container as they do on a desk.

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
    use super::{HTTP_NICE, below_haptics, yield_to_real_time};

    /// This thread's scheduling policy and niceness.
    fn own_scheduling() -> (libc::c_int, libc::c_int) {
        // SAFETY: pid 0 and PRIO_PROCESS with tid query the calling thread only.
        unsafe {
            let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
            (libc::sched_getscheduler(0), libc::getpriority(libc::PRIO_PROCESS, tid))
        }
    }

    #[test]
    fn a_background_thread_leaves_the_cores_to_real_time_ones() {
        let before = own_scheduling();
        let (policy, nice) = std::thread::spawn(|| {
            yield_to_real_time();
            own_scheduling()
        })
        .join()
        .unwrap();
        assert!(policy == libc::SCHED_IDLE || nice == 19, "policy {policy}, niceness {nice}");
        assert_eq!(own_scheduling(), before, "only the calling thread changes");
    }

    #[test]
    fn an_http_thread_runs_below_the_haptic_path_and_alone() {
        let before = own_scheduling();
        let (policy, nice) = std::thread::spawn(|| {
            below_haptics();
            own_scheduling()
        })
        .join()
        .unwrap();
        assert_eq!(policy, libc::SCHED_OTHER, "still scheduled with everyone else");
        assert!(nice >= HTTP_NICE, "niceness {nice}");
        assert_eq!(own_scheduling(), before, "only the calling thread changes");
    }
}
