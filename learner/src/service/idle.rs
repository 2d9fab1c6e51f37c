//! Sleeping until something happens, on the learner's own (non-async)
//! threads: the training loop waiting for its next batch, the shared-memory
//! policy broadcast waiting for the next version. An idle learner so wakes
//! for its checkpoints and a few housekeeping looks a second, not hundreds
//! of times a second (issue 71: polling at 250 µs to 2 ms took 7% of a
//! core with nothing to do).

use std::future::Future;
use std::pin::pin;
use std::task::{Context, Poll, Waker};
use std::time::{Duration, Instant};

thread_local! {
    /// This thread's timer. tokio's channels have no blocking receive with
    /// a deadline, so a small current-thread runtime (timers only, no I/O)
    /// waits on the channel's future and a timer at once, asleep in
    /// between.
    static WAITER: Option<tokio::runtime::Runtime> = tokio::runtime::Builder::new_current_thread().enable_time().build().ok();
}

/// Runs `until` to its end or for `timeout`, whichever comes first; None
/// when the time ran out. Inside an async context (a test driving the loop
/// from one) a second runtime cannot block, and where none could be built
/// there is none: both poll instead.
pub fn wait_for<F: Future>(timeout: Duration, until: F) -> Option<F::Output> {
    let outside_async = tokio::runtime::Handle::try_current().is_err();
    WAITER.with(|waiter| match waiter {
        Some(rt) if outside_async => rt.block_on(async { tokio::time::timeout(timeout, until).await.ok() }),
        _ => poll_until(timeout, until),
    })
}

/// The fallback: polls every millisecond until `timeout`.
fn poll_until<F: Future>(timeout: Duration, until: F) -> Option<F::Output> {
    let deadline = Instant::now() + timeout;
    let mut until = pin!(until);
    let mut cx = Context::from_waker(Waker::noop());
    loop {
        if let Poll::Ready(out) = until.as_mut().poll(&mut cx) {
            return Some(out);
        }
        if Instant::now() >= deadline {
            return None;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A value sent from another thread ends the wait at once, long before
    /// its timeout; with nothing sent the wait ends at the timeout, asleep.
    #[test]
    fn a_wait_ends_when_its_future_does_or_at_the_timeout() {
        let (tx, mut rx) = tokio::sync::mpsc::channel::<u32>(1);
        let sender = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(50));
            tx.blocking_send(7).unwrap();
            tx
        });
        let started = Instant::now();
        assert_eq!(wait_for(Duration::from_secs(30), rx.recv()), Some(Some(7)));
        assert!(started.elapsed() < Duration::from_secs(20), "woke only at the timeout");
        let _tx = sender.join().unwrap();
        let started = Instant::now();
        assert_eq!(wait_for(Duration::from_millis(100), rx.recv()), None);
        assert!(started.elapsed() >= Duration::from_millis(100));
        assert_eq!(poll_until(Duration::from_millis(10), std::future::pending::<()>()), None);
        assert_eq!(poll_until(Duration::from_millis(10), async { 3 }), Some(3));
    }
}
