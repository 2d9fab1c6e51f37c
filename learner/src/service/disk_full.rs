//! A full disk at the end of a run: the final checkpoint and summary.json
//! wait for space instead of being lost. A run whose disk filled at its
//! budget once exited 1 with no summary.json, half its work lost
//! (issue 71); now it keeps retrying for a stated time, says what it is
//! waiting for, and names exactly what it kept when it gives up.

use std::time::{Duration, Instant};

use crate::LearnerError;

/// How long the end of a run waits for space.
pub const WAIT_FOR_SPACE: Duration = Duration::from_secs(600);
/// How often it tries again meanwhile.
pub const RETRY_EVERY: Duration = Duration::from_secs(5);

/// Whether `error` is a full disk (ENOSPC, or a quota: EDQUOT).
pub fn is_disk_full(error: &LearnerError) -> bool {
    const ENOSPC: i32 = 28;
    const EDQUOT: i32 = 122;
    match error {
        LearnerError::Io { source, .. } => matches!(source.raw_os_error(), Some(ENOSPC | EDQUOT)),
        other => other.to_string().contains("No space left on device"),
    }
}

/// Runs `write` until it succeeds, fails otherwise than for a full disk,
/// `wait` has passed (trying every `every`), or `stopped` says the process
/// was told to stop (issue 82: SIGTERM went unheard for the whole wait);
/// logs once that it waits.
pub fn retry_while_full<T>(what: &str, (wait, every): (Duration, Duration), stopped: impl Fn() -> bool, mut write: impl FnMut() -> Result<T, LearnerError>) -> Result<T, LearnerError> {
    let started = Instant::now();
    let mut told = false;
    loop {
        match write() {
            Err(e) if is_disk_full(&e) && stopped() => {
                return Err(LearnerError::Checkpoint(format!("{what}: told to stop while the disk was full ({e}); not written")));
            }
            Err(e) if is_disk_full(&e) && started.elapsed() + every <= wait => {
                if !told {
                    tracing::error!("{what}: the disk is full ({e}); trying again every {} s for up to {} s: free some space", every.as_secs_f64(), wait.as_secs());
                    told = true;
                }
                // Asleep in short steps, so a stop is heard within 0.1 s.
                let until = Instant::now() + every;
                while Instant::now() < until && !stopped() {
                    std::thread::sleep(every.min(Duration::from_millis(100)));
                }
            }
            Err(e) if is_disk_full(&e) => {
                return Err(LearnerError::Checkpoint(format!("{what}: the disk stayed full for {} s ({e})", wait.as_secs())));
            }
            other => {
                if told && other.is_ok() {
                    tracing::info!("{what}: written once space returned");
                }
                return other;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn full() -> LearnerError {
        LearnerError::Io { path: "summary.json".into(), source: std::io::Error::from_raw_os_error(28) }
    }

    #[test]
    fn a_full_disk_is_waited_out_and_other_errors_are_not() {
        let ms = Duration::from_millis;
        let mut calls = 0;
        let written = retry_while_full("summary.json", (ms(500), ms(10)), || false, || {
            calls += 1;
            if calls < 3 { Err(full()) } else { Ok(calls) }
        });
        assert_eq!(written.unwrap(), 3, "written on the third try, once space returned");
        let mut calls = 0;
        let other = retry_while_full("summary.json", (ms(500), ms(10)), || false, || -> Result<(), _> {
            calls += 1;
            Err(LearnerError::Config("bad".into()))
        });
        assert!(other.is_err() && calls == 1, "another error is not retried");
        let started = Instant::now();
        let given_up = retry_while_full("the final checkpoint", (ms(60), ms(10)), || false, || -> Result<(), _> { Err(full()) }).unwrap_err();
        assert!(given_up.to_string().contains("the final checkpoint: the disk stayed full"), "{given_up}");
        assert!(started.elapsed() >= ms(50) && started.elapsed() < ms(500));
        // Told to stop while waiting (SIGTERM): it returns within a step,
        // not after the whole wait.
        let started = Instant::now();
        let stop_at = started + ms(150);
        let stopped = retry_while_full("the final checkpoint", (Duration::from_secs(600), Duration::from_secs(5)), || Instant::now() >= stop_at, || -> Result<(), _> { Err(full()) }).unwrap_err();
        assert!(stopped.to_string().contains("told to stop while the disk was full"), "{stopped}");
        assert!(started.elapsed() < Duration::from_secs(2), "heard the stop after {:?}", started.elapsed());
    }
}
