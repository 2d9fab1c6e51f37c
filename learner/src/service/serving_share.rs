//! Policy queries within a stated share of the time: training has
//! priority over serving. Four Act and four ActBatch(4,096) clients once
//! cut DDPG's updates by 82–98% (issue 71). Act and ActBatch compute one
//! at a time ([`POLICY_CONCURRENCY`]); after a computation
//! of d seconds the next may start only d·(1 − s)/s later, so over any
//! stretch of queries they compute at most a share s of the time. Calls
//! wait their turn holding no thread, and beyond a bounded queue are
//! refused with RESOURCE_EXHAUSTED. And each computation runs on a thread
//! of its own at a lower OS priority ([`below_training`], [`super::priority`]): the share
//! alone left DDPG's updates at 0.76–0.88 of a quiet run on 2 cores, since
//! it bounds the queries' time but not whose turn the kernel gives first.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use tonic::Status;

/// Act and ActBatch calls computed at once (the served policy is one, and
/// each computation holds a thread off the event loop). More wait their
/// turn on the event loop, holding no thread.
pub const POLICY_CONCURRENCY: usize = 1;

/// Calls that may wait for their turn; the next is refused.
pub const MAX_QUEUED_QUERIES: usize = 64;

/// Runs `compute` on a thread of its own below training
/// ([`super::priority::lower_this_thread`]) and returns
/// its result (inline where no thread can be started). One computation
/// runs at a time ([`POLICY_CONCURRENCY`]), so at most one such thread
/// lives; starting it costs tens of microseconds a query.
pub fn below_training<T: Send>(compute: impl FnOnce() -> T + Send) -> T {
    // Taken by whichever thread runs it: the new one, or this one when
    // none could be started.
    let compute = Mutex::new(Some(compute));
    let take = || compute.lock().unwrap_or_else(|p| p.into_inner()).take();
    let span = tracing::Span::current();
    std::thread::scope(|scope| {
        let started = std::thread::Builder::new().name("lcrl-serving".into()).spawn_scoped(scope, || {
            let _in_call = span.enter();
            super::priority::lower_this_thread("policy computations");
            // A query is one small forward pass: one libtorch thread, not
            // OpenMP's default team of one per core (a new thread's count).
            crate::device::torch::set_threads_here(1);
            take().map(|f| f())
        });
        match started {
            Ok(thread) => match thread.join() {
                Ok(value) => value.expect("the started thread takes the computation"),
                Err(panic) => std::panic::resume_unwind(panic),
            },
            // Not started (no threads left): computed here, at the caller's priority.
            Err(_) => (take().expect("not taken: the thread did not start"))(),
        }
    })
}

/// The share of one core's time policy queries may take, and whose turn
/// it is.
#[derive(Debug)]
pub struct ServingShare {
    share: f64,
    slot: tokio::sync::Semaphore,
    /// The earliest start of the next computation.
    next_start: Mutex<Instant>,
    waiting: AtomicUsize,
}

/// A turn to compute: hand it back with [`ServingShare::done`].
#[derive(Debug)]
pub struct Turn<'a> {
    _slot: tokio::sync::SemaphorePermit<'a>,
    started: Instant,
}

impl ServingShare {
    /// `share` in (0, 1]: 1 serves without pauses.
    pub fn new(share: f64) -> Self {
        ServingShare { share: share.clamp(0.01, 1.0), slot: tokio::sync::Semaphore::new(POLICY_CONCURRENCY), next_start: Mutex::new(Instant::now()), waiting: AtomicUsize::new(0) }
    }

    /// Waits for a turn (refused when [`MAX_QUEUED_QUERIES`] wait already).
    pub async fn turn(&self) -> Result<Turn<'_>, Status> {
        // Counted while waiting, and uncounted however the wait ends: a
        // caller that gives up (a deadline, a reset stream) drops this
        // future mid-wait, and a count left behind would refuse everyone.
        let waiting = Waiting::enter(&self.waiting);
        if waiting.ahead >= MAX_QUEUED_QUERIES {
            return Err(Status::resource_exhausted(format!(
                "{MAX_QUEUED_QUERIES} policy queries are waiting; training has priority (--serving-share {}): retry later",
                self.share
            )));
        }
        let slot = self.slot.acquire().await.map_err(|_| Status::unavailable("the learner is shutting down"))?;
        drop(waiting);
        let start = *self.next_start.lock().unwrap_or_else(|p| p.into_inner());
        tokio::time::sleep_until(start.into()).await;
        Ok(Turn { _slot: slot, started: Instant::now() })
    }

    /// Ends a turn: the next starts after the pause its length asks.
    pub fn done(&self, turn: Turn<'_>) {
        let took = turn.started.elapsed();
        let pause = took.mul_f64((1.0 - self.share) / self.share);
        *self.next_start.lock().unwrap_or_else(|p| p.into_inner()) = Instant::now() + pause.min(Duration::from_secs(10));
    }

    pub fn share(&self) -> f64 {
        self.share
    }
}

/// One caller counted among those waiting, until dropped.
struct Waiting<'a> {
    count: &'a AtomicUsize,
    /// Callers waiting before this one.
    ahead: usize,
}

impl<'a> Waiting<'a> {
    fn enter(count: &'a AtomicUsize) -> Self {
        Waiting { ahead: count.fetch_add(1, Ordering::AcqRel), count }
    }
}

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.count.fetch_sub(1, Ordering::AcqRel);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Computations of 20 ms at a share of 0.25 take at least 4 × their
    /// time end to end; at a share of 1, about their time.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn queries_take_at_most_their_share_of_the_time() {
        for (share, least, most) in [(0.25, 4.0, 6.0), (1.0, 1.0, 1.8)] {
            let limiter = ServingShare::new(share);
            let started = Instant::now();
            for _ in 0..10 {
                let turn = limiter.turn().await.unwrap();
                std::thread::sleep(Duration::from_millis(20));
                limiter.done(turn);
            }
            // The last pause is owed by the next query: count it too.
            let _ = limiter.turn().await.unwrap();
            let ratio = started.elapsed().as_secs_f64() / 0.2;
            assert!(ratio >= least * 0.95 && ratio <= most, "share {share}: {ratio:.2} × the computing time");
        }
    }

    /// A computation runs below training's priority and hands its result
    /// back; the caller's own priority is untouched.
    #[cfg(target_os = "linux")]
    #[test]
    fn computations_run_at_the_serving_nice_value() {
        let nice_here = crate::service::priority::this_thread_nice;
        let caller = nice_here();
        let (inside, value) = below_training(|| (nice_here(), 6 * 7));
        assert_eq!(value, 42);
        assert_eq!(inside, (caller + crate::service::priority::BELOW_TRAINING_NICE).min(19).max(caller), "the computing thread's nice value");
        assert_eq!(nice_here(), caller, "the caller's nice value is unchanged");
    }

    /// Beyond the queue, calls are refused at once with RESOURCE_EXHAUSTED.
    #[tokio::test]
    async fn a_full_queue_refuses() {
        let limiter = std::sync::Arc::new(ServingShare::new(1.0));
        let held = limiter.turn().await.unwrap();
        let mut waiting = Vec::new();
        for _ in 0..MAX_QUEUED_QUERIES {
            let limiter = limiter.clone();
            waiting.push(tokio::spawn(async move { limiter.turn().await.map(|_| ()) }));
        }
        while limiter.waiting.load(Ordering::Acquire) < MAX_QUEUED_QUERIES {
            tokio::task::yield_now().await;
        }
        let refused = limiter.turn().await.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
        // Callers that give up while waiting leave no count behind.
        for w in &waiting {
            w.abort();
        }
        for w in waiting {
            let _ = w.await;
        }
        assert_eq!(limiter.waiting.load(Ordering::Acquire), 0);
        limiter.done(held);
        limiter.turn().await.unwrap();
    }
}
