//! The learner's threads below training: a thread that must not take the
//! training thread's core where cores are short (policy queries,
//! validation episodes) raises its own nice value. Where cores are short
//! the kernel gives a thread at nice 0 about 9 times the time of one at
//! nice 10 (CFS weights 1024 and 110), so such a thread takes mostly what
//! training leaves; where cores are free it runs as fast as before.

/// How much nicer than the training thread the threads below it run.
pub const BELOW_TRAINING_NICE: i32 = 10;

/// Raises the calling thread's nice value alone by [`BELOW_TRAINING_NICE`],
/// up to 19 (Linux: a thread id given to setpriority names that thread; a
/// new thread starts at its creator's value). Raising one's own nice needs
/// no privilege; never lowering it keeps the thread below training even
/// where the learner was started niced; a failure leaves the thread as it
/// was, and says so at debug level.
pub fn lower_this_thread(what: &str) {
    #[cfg(target_os = "linux")]
    {
        let own = this_thread_nice();
        let lowered = (own + BELOW_TRAINING_NICE).min(19);
        // SAFETY: setpriority takes no pointers.
        if lowered > own && unsafe { libc::setpriority(libc::PRIO_PROCESS, this_thread_id() as libc::id_t, lowered) } != 0 {
            tracing::debug!("{what} runs at the learner's own priority: setpriority failed");
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = what;
}

/// The calling thread's nice value (Linux; 0 elsewhere).
pub fn this_thread_nice() -> i32 {
    #[cfg(target_os = "linux")]
    // SAFETY: getpriority takes no pointers.
    unsafe {
        libc::getpriority(libc::PRIO_PROCESS, this_thread_id() as libc::id_t)
    }
    #[cfg(not(target_os = "linux"))]
    0
}

/// The calling thread's kernel id (Linux: its /proc/self/task entry; 0
/// elsewhere).
pub fn this_thread_id() -> i64 {
    #[cfg(target_os = "linux")]
    // SAFETY: gettid takes no arguments.
    unsafe {
        libc::syscall(libc::SYS_gettid)
    }
    #[cfg(not(target_os = "linux"))]
    0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A lowered thread is BELOW_TRAINING_NICE nicer than the thread that
    /// started it (at most 19), and its starter keeps its own value.
    #[test]
    #[cfg(target_os = "linux")]
    fn a_lowered_thread_runs_nicer_than_its_starter_alone() {
        let starter = this_thread_nice();
        if starter >= 19 {
            eprintln!("skipped: the tests run at nice 19, no thread can run below them");
            return;
        }
        let lowered = std::thread::spawn(|| {
            lower_this_thread("the test thread");
            this_thread_nice()
        })
        .join()
        .unwrap();
        assert_eq!(lowered, (starter + BELOW_TRAINING_NICE).min(19));
        assert_eq!(this_thread_nice(), starter);
    }
}
