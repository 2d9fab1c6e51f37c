//! Process supervision for the commands that start other lcrl processes
//! (`lcrl run`, `lcrl scale`, `lcrl bench`, `lcrl experiment`): children
//! that are stopped when dropped and die with their parent, and waiting for
//! a server to report healthy.

use std::fs;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use lcrl_runtime::security::ClientSecurity;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::{health_client::HealthClient, HealthCheckRequest};

/// Whether `service` at `url` reports SERVING (health checks need no
/// token; TLS where `security` says).
pub async fn is_serving(url: &str, service: &str, security: &ClientSecurity) -> anyhow::Result<bool> {
    let channel = security.connect(url).await?;
    let status = HealthClient::new(channel).check(HealthCheckRequest { service: service.into() }).await?.into_inner().status;
    Ok(status == ServingStatus::Serving as i32)
}

/// A child process, stopped (SIGTERM, then SIGKILL after a grace period)
/// when dropped, so no run leaves orphans behind.
pub struct Managed {
    name: String,
    child: Child,
}

impl Managed {
    /// Starts `command` with stderr to logs/NAME.log. A server prints
    /// "listening on ADDR" as its first line; with `server` that address is
    /// read and returned.
    pub fn spawn(name: &str, command: Command, logs: &Path, server: bool) -> anyhow::Result<(Managed, Option<String>)> {
        Self::spawn_announcing(name, command, logs, server.then_some("listening on "))
    }

    /// Starts `command` as [`Managed::spawn`] does; where `prefix` is
    /// given, the process's first line of stdout is read and what follows
    /// the prefix returned ("metrics on " for an actor's metrics address).
    pub fn spawn_announcing(name: &str, mut command: Command, logs: &Path, prefix: Option<&str>) -> anyhow::Result<(Managed, Option<String>)> {
        let log = fs::File::create(logs.join(format!("{name}.log")))?;
        let stdout = if prefix.is_some() { Stdio::piped() } else { Stdio::null() };
        let child = command.stdout(stdout).stderr(log).spawn().with_context(|| format!("starting {name}"))?;
        let mut managed = Managed { name: name.to_string(), child };
        let mut address = None;
        if let (Some(stdout), Some(prefix)) = (managed.child.stdout.take(), prefix) {
            let mut line = String::new();
            if BufReader::new(stdout).read_line(&mut line).is_ok() {
                address = line.trim().strip_prefix(prefix).map(|a| a.trim().to_string());
            }
        }
        Ok((managed, address))
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// How the process ended, once it has (reaped: no zombie stays).
    pub fn exited(&mut self) -> Option<std::process::ExitStatus> {
        self.child.try_wait().ok().flatten()
    }

    pub fn stop(&mut self, grace: Duration) {
        if matches!(self.child.try_wait(), Ok(Some(_))) {
            return;
        }
        let _ = Command::new("kill").args(["-TERM", &self.child.id().to_string()]).status();
        let deadline = Instant::now() + grace;
        while Instant::now() < deadline {
            if matches!(self.child.try_wait(), Ok(Some(_))) {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        tracing::warn!("{} did not stop within {} s; killing it", self.name, grace.as_secs());
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Managed {
    fn drop(&mut self) {
        self.stop(Duration::from_secs(10));
    }
}

/// Makes a child die with this process (Linux: PR_SET_PDEATHSIG with
/// SIGKILL): a killed `lcrl run` or study leaves no server or run behind.
/// See [`signal_on_parent_death`] for the thread that must start it.
pub fn die_with_parent(command: &mut Command) {
    signal_on_parent_death(command, ParentDeath::Kill);
}

/// Makes a child stop with this process (Linux: PR_SET_PDEATHSIG with
/// SIGTERM), as it stops on Ctrl-C: a learner writes its final checkpoint.
/// `lcrl run` starts its graph builder, learner and actors so. See
/// [`signal_on_parent_death`] for the thread that must start it.
pub fn stop_with_parent(command: &mut Command) {
    signal_on_parent_death(command, ParentDeath::Terminate);
}

/// The signal a child gets when its parent dies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParentDeath {
    /// SIGTERM: the child stops as on Ctrl-C (servers and actors of lcrl
    /// handle it; the learner checkpoints first).
    Terminate,
    /// SIGKILL: nothing survives, nothing is saved.
    Kill,
}

/// The parent-death signal (Linux: PR_SET_PDEATHSIG), set in the child
/// between fork and exec, so the child gets `signal` whatever ends this
/// process: an error, Ctrl-C, kill -9.
///
/// The kernel sends it when the *thread* that forked the child exits, not
/// the process: start such children from the main thread or a thread that
/// lives as long as the process (not from a `spawn_blocking`, rayon or
/// other short-lived worker thread), or they are signalled when that thread
/// ends. The setting survives exec (but for set-user-ID binaries), so it
/// also holds for a child that execs again, as `lcrl launch` does.
#[cfg(target_os = "linux")]
pub fn signal_on_parent_death(command: &mut Command, signal: ParentDeath) {
    use std::os::unix::process::CommandExt;
    let parent = std::process::id() as libc::pid_t;
    let signal = match signal {
        ParentDeath::Terminate => libc::SIGTERM,
        ParentDeath::Kill => libc::SIGKILL,
    };
    // SAFETY: the closure runs in the forked child before exec and calls
    // only async-signal-safe functions (prctl, getppid, _exit).
    unsafe {
        command.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, signal as libc::c_ulong) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The parent may have died before prctl took effect.
            if libc::getppid() != parent {
                libc::_exit(1);
            }
            Ok(())
        });
    }
}

#[cfg(not(target_os = "linux"))]
pub fn signal_on_parent_death(_command: &mut Command, _signal: ParentDeath) {}

pub async fn wait_healthy(url: &str, service: &str, what: &str, timeout: Duration, security: &ClientSecurity) -> anyhow::Result<()> {
    let deadline = Instant::now() + timeout;
    loop {
        if let Ok(true) = is_serving(url, service, security).await {
            return Ok(());
        }
        if Instant::now() > deadline {
            bail!("{what} did not become healthy within {} s; see its log", timeout.as_secs());
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}
