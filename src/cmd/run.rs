//! `lcrl run`: a whole distributed run on this machine from one preset —
//! graph builder, learner and actors as child processes.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use indicatif::{ProgressBar, ProgressStyle};
use lcrl_learner::Connection;
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::GetStatusRequest;

use lcrl::binaries::sibling;
use lcrl::preset::{LearnerCompute, Preset};
use lcrl::run_security::RunSecurity;
use lcrl::supervise::{die_with_parent, stop_with_parent, wait_healthy, Managed};

/// Run graph builder, learner and actors on this machine until the episode
/// budget is reached (or Ctrl-C), collecting everything in the run directory.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// Preset: a training config (TOML) with a [job] section; see configs/.
    #[arg(long)]
    pub config: PathBuf,
    /// Actor processes (overrides job.actors).
    #[arg(long)]
    pub actors: Option<usize>,
    /// Episode budget (overrides job.episodes).
    #[arg(long)]
    pub episodes: Option<u64>,
    /// Episodes of the final policy's evaluation (overrides the preset's
    /// run.eval_episodes; 1 to 100000).
    #[arg(long, value_parser = lcrl_proto::process::count_in::<1, 100_000>)]
    pub eval_episodes: Option<usize>,
    /// First seed of the evaluation starts (overrides run.eval_seed); 0 is
    /// `lcrl tune`'s, the starts of the best constant and a = 0.
    #[arg(long)]
    pub eval_seed: Option<u64>,
    /// Transport between actors and learner (all on this machine).
    #[arg(long, value_enum, default_value_t = TransportArg::Shm)]
    pub transport: TransportArg,
    /// Where everything goes (default: runs/<preset name>).
    #[arg(long)]
    pub run_dir: Option<PathBuf>,
    /// Only check the preset (and its environment) and exit.
    #[arg(long)]
    pub check: bool,
    #[command(flatten)]
    pub compute: LearnerCompute,
    #[command(flatten)]
    pub security: RunSecurity,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum TransportArg {
    /// gRPC on loopback.
    Grpc,
    /// iceoryx2 shared memory.
    Shm,
}

pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    let mut preset = Preset::load(&args.config)?;
    if let Some(actors) = args.actors {
        preset.job.actors = actors;
    }
    if let Some(episodes) = args.episodes {
        preset.job.episodes = episodes;
    }
    if let Some(episodes) = args.eval_episodes {
        preset.train.run.eval_episodes = episodes;
    }
    if let Some(seed) = args.eval_seed {
        preset.train.run.eval_seed = Some(seed);
    }
    preset.set_compute(&args.compute)?;
    preset.check()?;
    // A missing or malformed headroom reference fails before training, not after.
    preset.headroom()?;
    // A learner that cannot have its device fails here, before anything starts.
    lcrl_learner::device::torch::resolve_device(&preset.train.run.device)?;
    preset.pin_learner_threads();
    if args.check {
        let job = &preset.job;
        println!("{}: {} with {:?}/{:?}, {} episodes, {} actor(s) — ok", args.config.display(), job.env, job.algo, job.connection, job.episodes, job.actors);
        return Ok(());
    }
    let name = args.config.file_stem().and_then(|s| s.to_str()).unwrap_or("run");
    let run_dir = args.run_dir.clone().unwrap_or_else(|| PathBuf::from("runs").join(name));
    let logs = run_dir.join("logs");
    fs::create_dir_all(&logs).with_context(|| format!("creating {}", logs.display()))?;
    lcrl::output::write_atomic(&run_dir.join("config.toml"), &preset.text)?;
    let security = with_own_token(&args.security, &run_dir)?;
    // A served environment lives until the run's end: the final evaluation
    // steps it too. Dropped last, it is stopped after everything else.
    let _env_server = match preset.env_server.clone() {
        Some(server) => Some(start_env_server(&mut preset, &server, &args.config, &logs, &security)?),
        None => None,
    };
    let train_path = run_dir.join("train.toml");
    preset.write_train_config(&train_path)?;
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    // block_on polls `orchestrate` on this, the main thread, which starts
    // every child: their parent-death signal (supervise::stop_with_parent)
    // fires when the thread that forked them ends, so it must not be a
    // runtime worker or any other short-lived thread.
    let transport = match args.transport {
        TransportArg::Grpc => "grpc",
        TransportArg::Shm => "shm",
    };
    let summary = runtime.block_on(orchestrate(&preset, &train_path, &run_dir, &logs, transport, &security))?;
    println!("{summary}");
    Ok(())
}

/// The run's security: as given, or, with no token given (--token-file or
/// $LCRL_TOKEN_FILE), a new token in RUN/token (owner-only) that every
/// server of the run requires, as compose does: without one, any local
/// user could act as a peer of the run (issue 71).
fn with_own_token(given: &RunSecurity, run_dir: &Path) -> anyhow::Result<RunSecurity> {
    let mut security = given.clone();
    if security.token_file.is_none() && std::env::var_os(lcrl_proto::security::TOKEN_FILE_ENV).is_none() {
        let path = run_dir.join("token");
        crate::cmd::certs::write_token(&path)?;
        eprintln!("this run's servers require the token in {} (clients: --token-file {})", path.display(), path.display());
        security.token_file = Some(path);
    }
    Ok(security)
}

/// Starts `python -m lcrl_env serve` for the preset's `[env_server]` and
/// points `job.env` at the address it listens on.
/// Under --tls-dir / --token-file it is secured like the run's other
/// servers, and this process and its children (which inherit the
/// environment) are its clients.
fn start_env_server(preset: &mut Preset, server: &lcrl::preset::EnvServer, config: &Path, logs: &Path, security: &RunSecurity) -> anyhow::Result<Managed> {
    let listen = lcrl_sim::remote::address(&preset.job.env).unwrap_or(&preset.job.env).to_string();
    // Every actor environment, plus the evaluation's, has an instance ready.
    let instances = preset.job.actors * preset.job.envs_per_actor + 1;
    let mut cmd = server.command(&listen, instances, config.parent().unwrap_or(Path::new(".")))?;
    cmd.args(security.server_args(false)?);
    security.export_env_client()?;
    die_with_parent(&mut cmd);
    let (process, address) = Managed::spawn("env-server", cmd, logs, true)?;
    let Some(address) = address else {
        let log = logs.join("env-server.log");
        let reason = fs::read_to_string(&log).ok().and_then(|t| t.lines().rev().find(|l| l.contains("error")).map(str::to_string));
        bail!("the environment server did not start: {}", reason.unwrap_or_else(|| format!("see {}", log.display())));
    };
    let scheme = if security.tls_dir.is_some() { lcrl_sim::remote::TLS_SCHEME } else { lcrl_sim::remote::SCHEME };
    preset.job.env = format!("{scheme}{address}");
    eprintln!("environment server at {}: {}", preset.job.env, server.gym.as_deref().or(server.entry_point.as_deref()).unwrap_or(""));
    preset.check()?;
    Ok(process)
}

async fn orchestrate(preset: &Preset, train_path: &Path, run_dir: &Path, logs: &Path, transport: &str, security: &RunSecurity) -> anyhow::Result<String> {
    // Certificates and the token are checked before anything starts.
    let client_security = security.client()?;
    let started = Instant::now();
    let run_id = format!("{}-{}", std::process::id(), started.elapsed().as_nanos() % 1_000_000);
    let processes = start_processes(preset, train_path, run_dir, logs, transport, security, &client_security, &run_id).await?;
    let mut client = LearnerClient::new(client_security.connect(&processes.learner_url).await?);
    // Ctrl-C and SIGTERM stop the run in order from here on (before, they
    // end this process and every child follows by its parent-death signal).
    // Listening once, not per loop turn, so no signal falls between turns.
    let mut stop_signals = StopSignals::new()?;
    let (interrupted, last_status) = watch_progress(&mut client, &mut stop_signals, preset.job.episodes, logs).await?;
    // Stopping (up to 30 s for the learner's checkpoint) and the final
    // evaluation run on; a further Ctrl-C or SIGTERM ends this process at
    // once, and the children follow by their parent-death signal.
    tokio::spawn(async move {
        stop_signals.recv().await;
        eprintln!("lcrl run: interrupted again; stopping now");
        std::process::exit(130);
    });
    if interrupted {
        eprintln!("interrupted: stopping the actors, then the learner (it writes a final checkpoint)");
    }
    let final_status = client.get_status(GetStatusRequest {}).await.map(|s| s.into_inner()).ok().or(last_status);
    processes.stop();
    report(preset, run_dir, &final_status.unwrap_or_default(), started.elapsed().as_secs_f64(), transport, &run_id, interrupted)
}

/// The processes of a local run.
struct Processes {
    graph_builder: Option<Managed>,
    learner: Managed,
    learner_url: String,
    actors: Vec<Managed>,
}

impl Processes {
    /// Actors first (they would only reconnect), then the learner (it
    /// checkpoints on SIGTERM), then the graph builder.
    fn stop(mut self) {
        for actor in self.actors.iter_mut() {
            actor.stop(Duration::from_secs(10));
        }
        self.learner.stop(Duration::from_secs(30));
        if let Some(mut g) = self.graph_builder {
            g.stop(Duration::from_secs(5));
        }
    }
}

/// Starts the graph builder (for a local actor without a given graph), the
/// learner, and the actors, each once the one before answers its health
/// check.
#[allow(clippy::too_many_arguments)]
async fn start_processes(
    preset: &Preset,
    train_path: &Path,
    run_dir: &Path,
    logs: &Path,
    transport: &str,
    security: &RunSecurity,
    client_security: &lcrl_proto::security::ClientSecurity,
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
    let mut actors = Vec::new();
    for k in 0..job.actors {
        let mut cmd = Command::new(sibling("lcrl-actor")?);
        cmd.args(preset.actor_args(&url, run_id, transport, Some(&format!("actor-{k}")), k as u64)).args(security.client_args()?);
        stop_with_parent(&mut cmd);
        actors.push(Managed::spawn(&format!("actor-{k}"), cmd, logs, false)?.0);
    }

    Ok(Processes { graph_builder, learner, learner_url: url, actors })
}

/// Shows the learner's progress until it reports the budget spent (false)
/// or a stop signal arrives (true); with the last status read.
async fn watch_progress(
    client: &mut LearnerClient<tonic::service::interceptor::InterceptedService<tonic::transport::Channel, lcrl_proto::security::Bearer>>,
    stop_signals: &mut StopSignals,
    episodes: u64,
    logs: &Path,
) -> anyhow::Result<(bool, Option<lcrl_proto::v1::LearnerStatus>)> {
    let bar = ProgressBar::new(episodes);
    if let Ok(style) = ProgressStyle::with_template("episode {pos}/{len} [{bar:25}] {msg} ({elapsed}, eta {eta})") {
        bar.set_style(style.progress_chars("=> "));
    }
    let (mut last_steps, mut last_updates, mut last_time) = (0u64, 0u64, Instant::now());
    let mut last_status = None;
    let interrupted = loop {
        tokio::select! {
            _ = stop_signals.recv() => break true,
            _ = tokio::time::sleep(Duration::from_millis(500)) => {}
        }
        let status = match client.get_status(GetStatusRequest {}).await {
            Ok(s) => s.into_inner(),
            // Ctrl-C at a terminal reaches the whole process group: the
            // learner may stop before this process sees its own SIGINT.
            Err(e) => {
                tokio::select! {
                    _ = stop_signals.recv() => break true,
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
            break false;
        }
    };
    bar.finish_and_clear();
    Ok((interrupted, last_status))
}

/// Writes the run's summary and reward curve, and says what the run did
/// beside its reference.
fn report(preset: &Preset, run_dir: &Path, s: &lcrl_proto::v1::LearnerStatus, wall: f64, transport: &str, run_id: &str, interrupted: bool) -> anyhow::Result<String> {
    let job = &preset.job;
    let summary = lcrl::run_summary::write_run_summary(preset, run_dir, s, wall, job.actors, transport)?;
    let evaluation = &summary.evaluation;
    let service = summary.service.as_ref().context("the run's summary has no service figures")?;
    let curve = run_dir.join("reward_curve.png");
    plot_curve(&run_dir.join("learner/metrics.csv"), &curve, &job.env, evaluation)?;
    let reference = match (evaluation.lqr_return, evaluation.masked_lqr_return, job.connection) {
        (_, Some(masked), Connection::Local) => format!("reference: masked LQR (the best controller with G) {masked:.3}"),
        (Some(lqr), _, _) => format!("reference: LQR {lqr:.3}"),
        _ => reference_table(job, evaluation),
    };
    let which = match (&summary.selection, evaluation.last_eval_return) {
        (Some(chosen), Some(last)) => format!("the selected policy (after {} episodes, {}; the last policy scores {last:.3})", chosen.episode, chosen.how_chosen()),
        _ => "the final policy".to_string(),
    };
    Ok(format!(
        "{}run {run_id}: {} episodes, {} env steps, {} updates ({}), policy lag mean {:.1}, policy v{}, recent average return {:.3}, {:.1} s\n\
         eval return {:.3} over {} episodes of {which}; {reference}\n\
         results in {}: summary.json, config.toml, graph.json/graph.png, learner/metrics.csv (and TensorBoard events), learner/checkpoints/, reward_curve.png, logs/",
        if interrupted { "interrupted: " } else { "" },
        s.episodes,
        s.env_steps,
        s.updates,
        match (job.algo, service.replay_ratio_target > 0.0) {
            (lcrl_learner::Algo::Ppo, _) => "PPO, on-policy".to_string(),
            (_, true) => format!("replay ratio {:.1} sampled per inserted, target {:.0}", service.replay_ratio, service.replay_ratio_target),
            (_, false) => format!("replay ratio {:.1} sampled per inserted, unlimited", service.replay_ratio),
        },
        service.policy_lag.mean,
        s.policy_version,
        s.recent_return,
        wall,
        evaluation.eval_return,
        evaluation.eval_episodes.unwrap_or(preset.train.run.eval_episodes),
        run_dir.display()
    ))
}

/// Ctrl-C (SIGINT) and SIGTERM, listened to from creation on.
struct StopSignals {
    interrupt: tokio::signal::unix::Signal,
    terminate: tokio::signal::unix::Signal,
}

impl StopSignals {
    fn new() -> anyhow::Result<Self> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(StopSignals {
            interrupt: signal(SignalKind::interrupt()).context("listening for Ctrl-C")?,
            terminate: signal(SignalKind::terminate()).context("listening for SIGTERM")?,
        })
    }

    async fn recv(&mut self) {
        tokio::select! {
            _ = self.interrupt.recv() => {}
            _ = self.terminate.recv() => {}
        }
    }
}

/// The trained policy beside every reference controller, on the same
/// evaluation starts (peg tasks: a = 0, the best constant, the headroom).
fn reference_table(job: &lcrl::preset::Job, evaluation: &lcrl_learner::run::summary::Evaluation) -> String {
    let pct = |r: Option<f64>| r.map_or("n/a".into(), |r| format!("{:.0}%", 100.0 * r));
    let force = |f: Option<f64>| f.map_or("n/a".into(), |f| format!("{f:.1} N"));
    let trained = format!("trained: {:?} {:?}", job.algo, job.connection).to_lowercase();
    let mut rows = vec![(trained, evaluation.eval_return, evaluation.eval_success_rate, evaluation.eval_peak_force_n)];
    rows.extend(evaluation.references.iter().map(|r| (r.controller.clone(), r.mean_return, r.success_rate, r.mean_peak_force_n)));
    let mut table = format!("beside the reference controllers on the same {} starts:\n  {:<34} {:>10} {:>8} {:>11}", evaluation.eval_episodes.unwrap_or(0), "controller", "return", "success", "peak force");
    for (name, ret, success, peak) in rows {
        table.push_str(&format!("\n  {name:<34} {ret:>10.3} {:>8} {:>11}", pct(success), force(peak)));
    }
    if let Some(bar) = evaluation.references.iter().find(|r| r.controller == lcrl::run_summary::BEST_CONSTANT) {
        let verdict = if evaluation.eval_return > bar.mean_return { "beats" } else { "does not beat" };
        table.push_str(&format!("\n  the trained policy {verdict} the best constant by {:+.3}", evaluation.eval_return - bar.mean_return));
    }
    table
}

fn plot_curve(metrics: &Path, out: &Path, env: &str, evaluation: &lcrl_learner::run::summary::Evaluation) -> anyhow::Result<()> {
    let Ok(mut reader) = csv::Reader::from_path(metrics) else { return Ok(()) };
    let returns: Vec<f64> = reader.records().filter_map(|r| r.ok()?.get(1)?.parse().ok()).collect();
    if returns.is_empty() {
        return Ok(());
    }
    let x: Vec<f64> = (1..=returns.len()).map(|e| e as f64).collect();
    let average: Vec<f64> = (0..returns.len())
        .map(|k| {
            let w = &returns[k.saturating_sub(19)..=k];
            w.iter().sum::<f64>() / w.len() as f64
        })
        .collect();
    let mut references = crate::cmd::compare::reference_lines(evaluation.lqr_return, evaluation.masked_lqr_return, evaluation.zero_action_return);
    references.extend(evaluation.references.iter().filter(|r| r.controller != lcrl::run_summary::ZERO_ACTION).map(|r| (r.controller.clone(), r.mean_return)));
    let panel = lcrl::plots::Panel::rewards("episode return", vec![("return".into(), returns), ("moving average (20)".into(), average)], references);
    lcrl::plots::line_panels(out, &format!("{env} — distributed run"), &x, "episode (as reported by actors)", &[panel])
}
