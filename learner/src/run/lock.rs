//! One writer per run directory: an exclusive lock (flock) on RUN/.lock,
//! held while a learner or `lcrl train` writes the run and released by the
//! kernel however the process ends. A second writer fails at once, naming
//! the holder, instead of interleaving checkpoints and metrics with it.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, Write};
use std::path::Path;

use crate::LearnerError;

/// The lock file inside a run directory.
pub const LOCK_FILE: &str = ".lock";

/// A held run directory (released when dropped or when the process ends).
#[derive(Debug)]
pub struct RunLock {
    _file: File,
}

impl RunLock {
    /// Takes the run directory `dir` (which must exist) for this process,
    /// recording who holds it (pid and command line) for whoever finds it
    /// taken.
    pub fn acquire(dir: &Path) -> Result<RunLock, LearnerError> {
        let path = dir.join(LOCK_FILE);
        let mut file = OpenOptions::new().read(true).write(true).create(true).truncate(false).open(&path).map_err(crate::io(&path))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = file.read_to_string(&mut holder);
                let holder = holder.trim();
                return Err(LearnerError::Mismatch(format!(
                    "{} is in use by another run ({}); stop it first or choose another --run-dir",
                    dir.display(),
                    if holder.is_empty() { "a process that has not said which" } else { holder }
                )));
            }
            // A volume without locks (some network file systems): the run
            // goes on unguarded, said once.
            Err(std::fs::TryLockError::Error(e)) if matches!(e.raw_os_error(), Some(libc::ENOLCK | libc::EOPNOTSUPP)) => {
                tracing::warn!(path = %path.display(), "this file system takes no locks ({e}): nothing stops a second writer of this run directory");
                return Ok(RunLock { _file: file });
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(LearnerError::Io { path, source: e }),
        }
        let cmdline = std::fs::read(format!("/proc/{}/cmdline", std::process::id()))
            .map(|c| String::from_utf8_lossy(&c).replace('\0', " ").trim().to_string())
            .unwrap_or_default();
        let record = format!("pid {}: {cmdline}\n", std::process::id());
        file.set_len(0).and_then(|()| file.rewind()).and_then(|()| file.write_all(record.as_bytes())).map_err(crate::io(&path))?;
        Ok(RunLock { _file: file })
    }

}

#[cfg(test)]
mod tests {
    use super::*;

    /// A second holder is refused with the first one's pid; once the first
    /// lets go, the directory can be taken again.
    #[test]
    fn a_run_directory_has_one_holder_at_a_time() {
        let dir = tempfile::tempdir().unwrap();
        let first = RunLock::acquire(dir.path()).unwrap();
        let err = RunLock::acquire(dir.path()).unwrap_err().to_string();
        assert!(err.contains("is in use by another run") && err.contains(&format!("pid {}", std::process::id())), "{err}");
        drop(first);
        RunLock::acquire(dir.path()).expect("free again");
    }
}
