//! The processes of a local run: started in order, each once the one
//! before answers its health check; followed until the budget is spent or
//! a stop signal arrives; stopped in order.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use lcrl_learner::Connection;
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::GetStatusRequest;

use crate::binaries::sibling;
use crate::preset::Preset;
use crate::run_security::RunSecurity;
use crate::supervise::{stop_with_parent, wait_healthy, Managed};

/// The processes of a local run.
pub(super) struct Processes {
    graph_builder: Option<Managed>,
    learner: Managed,
    pub(super) learner_url: String,
    actors: Actors,
}

/// Restarts of dead actors a run allows in all, before it ends with an
/// error: an actor that keeps dying has a cause a restart does not fix.
pub const MAX_ACTOR_RESTARTS: u64 = 3;

/// The run's actor processes, watched: a dead one (any exit, a signal, an
/// iceoryx2 node error that ends it) is noticed at the next look, reaped,
/// and started again after a backoff of 1, 2, 4 s, up to
/// [`MAX_ACTOR_RESTARTS`] restarts in all.
pub(super) struct Actors {
    running: Vec<Option<Managed>>,
    commands: Vec<Vec<std::ffi::OsString>>,
    due: Vec<Option<Instant>>,
    logs: std::path::PathBuf,
    pub(super) restarts: u64,
}

impl Actors {
    fn start(k: usize, args: &[std::ffi::OsString], logs: &Path) -> anyhow::Result<Managed> {
        let mut cmd = Command::new(sibling("lcrl-actor")?);
        cmd.args(args);
        stop_with_parent(&mut cmd);
        Ok(Managed::spawn(&format!("actor-{k}"), cmd, logs, false)?.0)
    }

    /// One look: reaps dead actors and starts those whose backoff is over.
    /// Err says why the run cannot go on (restarts used up).
    pub(super) fn look(&mut self) -> Result<(), String> {
        for k in 0..self.running.len() {
            if let Some(status) = self.running[k].as_mut().and_then(Managed::exited) {
                self.running[k] = None;
                // An actor stops with 0 once the learner says the budget is
                // spent (before GetStatus says finished): not a death.
                if status.success() {
                    continue;
                }
                let log = self.logs.join(format!("actor-{k}.log"));
                if self.restarts >= MAX_ACTOR_RESTARTS {
                    return Err(format!("actor-{k} died ({status}) after {} restarts of the run's actors; see {}", self.restarts, log.display()));
                }
                let backoff = Duration::from_secs(1 << self.restarts.min(6));
                self.restarts += 1;
                eprintln!("\nlcrl run: actor-{k} died ({status}); restarting it in {} s ({} of {MAX_ACTOR_RESTARTS} restarts; see {})", backoff.as_secs(), self.restarts, log.display());
                self.due[k] = Some(Instant::now() + backoff);
            }
            if self.due[k].is_some_and(|t| Instant::now() >= t) {
                self.due[k] = None;
                // Its log is kept beside the new one's.
                let log = self.logs.join(format!("actor-{k}.log"));
                let _ = std::fs::rename(&log, self.logs.join(format!("actor-{k}.{}.log", self.restarts)));
                self.running[k] = Some(Self::start(k, &self.commands[k], &self.logs).map_err(|e| format!("restarting actor-{k}: {e:#}"))?);
            }
        }
        Ok(())
    }

    fn stop(&mut self) {
        for actor in self.running.iter_mut().flatten() {
            actor.stop(Duration::from_secs(10));
        }
    }
}

impl Processes {
    /// Actors first (they would only reconnect), then the learner (it
    /// checkpoints on SIGTERM), then the graph builder.
    pub(super) fn stop(mut self) {
        self.actors.stop();
        self.learner.stop(Duration::from_secs(30));
        if let Some(mut g) = self.graph_builder {
            g.stop(Duration::from_secs(5));
        }
    }
}

/// Starts the graph builder (for a local actor without a given graph), the
/// learner, and the actors, each once the one before answers its health
/// check.
// args: the run's paths, transport, security and id, each a different part of the local run that starts the three processes
#[allow(clippy::too_many_arguments)]
pub(super) async fn start_processes(
    preset: &Preset,
    train_path: &Path,
    run_dir: &Path,
    logs: &Path,
    transport: &str,
    security: &RunSecurity,
    client_security: &lcrl_runtime::security::ClientSecurity,
    run_id: &str,
) -> anyhow::Result<Processes> {
    let job = &preset.job;
    let mut graph_builder = None;
    let mut graph_url = None;
    // A given graph (job.graph) is written as the run's graph.json and
    // handed to the learner as a file: no graph builder to start.
    let given_graph = match &preset.env_server {
        None => preset.given_graph(lcrl_sim::make_env(&job.env)?.spec())?,
        Some(_) => None,
    };
    if let Some(report) = &given_graph {
        report.write_json(&run_dir.join("graph.json"))?;
        eprintln!("{}, no graph builder", report.origin_line());
    }
    if job.connection == Connection::Local && given_graph.is_none() {
        let mut cmd = Command::new(sibling("lcrl-graph-builder")?);
        cmd.args(preset.graph_builder_args("127.0.0.1:0", run_dir)).args(security.server_args(false)?);
        stop_with_parent(&mut cmd);
        let (process, address) = Managed::spawn("graph-builder", cmd, logs, true)?;
        let url = security.url(&format!("http://{}", address.context("the graph builder did not start; see logs/graph-builder.log")?));
        eprintln!("graph builder at {url}: building the connection graph");
        wait_healthy(&url, "lcrl.v1.Graph", "the graph builder", Duration::from_secs(600), client_security).await?;
        graph_url = Some(url);
        graph_builder = Some(process);
    }
    let mut learner_cmd = Command::new(sibling("lcrl-learner")?);
    match &given_graph {
        Some(_) => learner_cmd.args(preset.learner_args_with_graph_file("127.0.0.1:0", run_id, train_path, &run_dir.join("learner"), &run_dir.join("graph.json"))),
        None => learner_cmd.args(preset.learner_args("127.0.0.1:0", run_id, train_path, &run_dir.join("learner"), graph_url.as_deref())?),
    };
    learner_cmd.args(security.server_args(graph_url.is_some())?);
    // Whatever ends this process (kill -9 included), the learner gets
    // SIGTERM and writes its final checkpoint.
    stop_with_parent(&mut learner_cmd);
    let (learner, address) = Managed::spawn("learner", learner_cmd, logs, true)?;
    let url = security.url(&format!("http://{}", address.context("the learner did not start; see logs/learner.log")?));
    wait_healthy(&url, "lcrl.v1.Learner", "the learner", Duration::from_secs(120), client_security).await?;
    eprintln!("learner at {url}; starting {} actor(s) over {transport}", job.actors);
    eprintln!("{}", query_hint(&url, &security.client_args()?, lcrl_sim::make_env(&job.env).map(|e| e.spec().state_dim()).unwrap_or(0)));
    let mut actors = Actors { running: Vec::new(), commands: Vec::new(), due: vec![None; job.actors], logs: logs.to_path_buf(), restarts: 0 };
    for k in 0..job.actors {
        let mut args = preset.actor_args(&url, run_id, transport, Some(&format!("actor-{k}")), k as u64);
        args.extend(security.client_args()?);
        actors.running.push(Some(Actors::start(k, &args, logs)?));
        actors.commands.push(args);
    }

    Ok(Processes { graph_builder, learner, learner_url: url, actors })
}

impl Processes {
    pub(super) fn actors(&mut self) -> &mut Actors {
        &mut self.actors
    }
}

/// Shows the learner's progress until it reports the budget spent (false)
/// or a stop signal arrives (true); with the last status read.
pub(super) async fn watch_progress(
    client: &mut LearnerClient<tonic::service::interceptor::InterceptedService<tonic::transport::Channel, lcrl_runtime::security::Bearer>>,
    stop_signals: &mut StopSignals,
    actors: &mut Actors,
    episodes: u64,
    logs: &Path,
) -> anyhow::Result<(Watched, Option<lcrl_proto::v1::LearnerStatus>)> {
    let bar = lcrl_graph_builder::progress::bar(episodes, "episode {pos}/{len} [{bar:25}] {msg} ({elapsed}, eta {eta})");
    let (mut last_steps, mut last_updates, mut last_time) = (0u64, 0u64, Instant::now());
    let mut last_status = None;
    let watched = loop {
        tokio::select! {
            _ = stop_signals.recv() => break Watched::Interrupted,
            _ = tokio::time::sleep(Duration::from_millis(500)) => {}
        }
        if let Err(why) = actors.look() {
            break Watched::ActorsFailed(why);
        }
        let status = match client.get_status(GetStatusRequest {}).await {
            Ok(s) => s.into_inner(),
            // Another local process asked too often (GetStatus is rate
            // bounded per peer address, and loopback is one): ask again
            // at the next tick.
            Err(e) if e.code() == tonic::Code::ResourceExhausted => continue,
            // Ctrl-C at a terminal reaches the whole process group: the
            // learner may stop before this process sees its own SIGINT.
            Err(e) => {
                tokio::select! {
                    _ = stop_signals.recv() => break Watched::Interrupted,
                    _ = tokio::time::sleep(Duration::from_secs(1)) => {}
                }
                bail!("lost the learner ({e}); see {}/learner.log", logs.display())
            }
        };
        last_status = Some(status.clone());
        let dt = last_time.elapsed().as_secs_f64().max(1e-9);
        bar.set_position(status.episodes.min(episodes));
        bar.set_message(format!(
            "avg return {:.2}, {:.0} steps/s, {:.0} updates/s, policy v{}",
            status.recent_return,
            (status.env_steps - last_steps.min(status.env_steps)) as f64 / dt,
            (status.updates - last_updates.min(status.updates)) as f64 / dt,
            status.policy_version
        ));
        (last_steps, last_updates, last_time) = (status.env_steps, status.updates, Instant::now());
        // The learner owns the budget: it stops training, writes its final
        // checkpoint and summary, then reports `finished`.
        if status.finished {
            break Watched::Finished;
        }
    };
    bar.finish_and_clear();
    Ok((watched, last_status))
}

/// How watching a run ended.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Watched {
    /// The learner spent its budget.
    Finished,
    /// Ctrl-C or SIGTERM.
    Interrupted,
    /// Actors kept dying: why.
    ActorsFailed(String),
}

/// Ctrl-C (SIGINT) and SIGTERM, listened to from creation on.
pub(super) struct StopSignals {
    interrupt: tokio::signal::unix::Signal,
    terminate: tokio::signal::unix::Signal,
}

impl StopSignals {
    pub(super) fn new() -> anyhow::Result<Self> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(StopSignals {
            interrupt: signal(SignalKind::interrupt()).context("listening for Ctrl-C")?,
            terminate: signal(SignalKind::terminate()).context("listening for SIGTERM")?,
        })
    }

    pub(super) async fn recv(&mut self) {
        tokio::select! {
            _ = self.interrupt.recv() => {}
            _ = self.terminate.recv() => {}
        }
    }
}


/// Ready-to-paste queries of this run's learner, with its TLS files and
/// token (`lcrl run` always makes a token): the Python client with a state
/// of the environment's size, and `lcrl status`.
fn query_hint(url: &str, security_args: &[std::ffi::OsString], state_dim: usize) -> String {
    let target = url.trim_start_matches("http://").trim_start_matches("https://");
    let flags: Vec<String> = security_args.iter().map(|a| a.to_string_lossy().into_owned()).collect();
    let flags = flags.join(" ");
    let state = vec!["0"; state_dim.max(1)].join(" ");
    format!(
        "query it (another shell, while it trains):\n  .venv/bin/python clients/python/lcrl_client.py --target {target} {flags} --state {state}\n  target/debug/lcrl status {url} {flags}"
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_query_hint_carries_the_token_and_a_full_state() {
        let args: Vec<std::ffi::OsString> = vec!["--token-file".into(), "runs/x/token".into()];
        let hint = query_hint("http://127.0.0.1:5000", &args, 3);
        assert!(hint.contains("lcrl_client.py --target 127.0.0.1:5000 --token-file runs/x/token --state 0 0 0"), "{hint}");
        assert!(hint.contains("lcrl status http://127.0.0.1:5000 --token-file runs/x/token"), "{hint}");
    }
}
