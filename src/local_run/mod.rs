//! `lcrl run`: a whole distributed run on this machine from one preset —
//! graph builder, learner and actors as child processes.

//!
//! The wiring of `lcrl run`, as named steps: [`run`] reads the preset and
//! its overrides, gives the run its own token, starts a served environment
//! where the preset has one, then [`orchestrate`] starts the processes
//! (processes.rs), follows the learner's progress until the budget is
//! spent or a stop signal arrives, stops them in order, and writes the
//! summary and reward curve (report.rs). The binary only parses arguments.

mod processes;
pub(crate) mod report;
#[cfg(test)]
mod tests;

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::GetStatusRequest;

use crate::preset::{LearnerCompute, Preset};
use crate::run_security::RunSecurity;
use crate::supervise::{die_with_parent, Managed};
use crate::run_summary::RunEnd;
use processes::{start_processes, watch_progress, StopSignals, Watched};
pub use processes::MAX_ACTOR_RESTARTS;
use report::report;

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
    /// PPO: policy versions a batch may lag the newest and still be trained
    /// on, its behaviour probabilities correcting the update (overrides
    /// job.max_staleness; 0: on-policy, as `lcrl train`).
    #[arg(long)]
    pub max_staleness: Option<u64>,
    /// Episodes of the final policy's evaluation (overrides the preset's
    /// run.eval_episodes; 1 to 100000).
    #[arg(long, value_parser = lcrl_runtime::process::count_in::<1, 100_000>)]
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
    if let Some(lag) = args.max_staleness {
        preset.job.max_staleness = Some(lag);
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
    // One `lcrl run` per run directory, held before anything in it is
    // written (config.toml, the token): a second one would replace a live
    // run's token. The learner holds RUN/learner itself.
    let _run_lock = lcrl_learner::run::lock::RunLock::acquire(&run_dir)?;
    let mut recorded = preset.text.clone();
    if preset.job.connection == lcrl_learner::Connection::Local && preset.job.graph.is_none() {
        // The graph's T and why, as `lcrl graph` prints it (docs/method.md, "Choosing T").
        let t = preset.job.graph_threshold;
        let why = format!("eq. 7 at T = {t}: {}", lcrl_graph_builder::choose_t::threshold_reason(t));
        println!("graph: {why}");
        recorded = format!("# graph: measured, {why}\n{recorded}");
    }
    crate::output::write_atomic(&run_dir.join("config.toml"), &recorded)?;
    let token_in_env = std::env::var_os(lcrl_runtime::security::TOKEN_FILE_ENV).is_some();
    let security = with_own_token(&args.security, token_in_env, &run_dir)?;
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
fn with_own_token(given: &RunSecurity, token_in_env: bool, run_dir: &Path) -> anyhow::Result<RunSecurity> {
    let mut security = given.clone();
    if security.token_file.is_none() && !token_in_env {
        let path = run_dir.join("token");
        crate::run_security::write_token(&path)?;
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
fn start_env_server(preset: &mut Preset, server: &crate::preset::EnvServer, config: &Path, logs: &Path, security: &RunSecurity) -> anyhow::Result<Managed> {
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
    let mut processes = start_processes(preset, train_path, run_dir, logs, transport, security, &client_security, &run_id).await?;
    let mut client = LearnerClient::new(client_security.connect(&processes.learner_url).await?);
    // Ctrl-C and SIGTERM stop the run in order from here on (before, they
    // end this process and every child follows by its parent-death signal).
    // Listening once, not per loop turn, so no signal falls between turns.
    let mut stop_signals = StopSignals::new()?;
    let (watched, last_status) = watch_progress(&mut client, &mut stop_signals, processes.actors(), preset.job.episodes, logs).await?;
    let interrupted = watched == Watched::Interrupted;
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
    let ended_early = match &watched {
        Watched::ActorsFailed(why) => {
            eprintln!("lcrl run: {why}\nstopping the learner (it writes a final checkpoint); summary.json records why the run ended");
            Some(why.clone())
        }
        _ => None,
    };
    let end = RunEnd { actors: preset.job.actors, transport: transport.to_string(), actor_restarts: processes.actors().restarts, ended_early };
    let final_status = client.get_status(GetStatusRequest {}).await.map(|s| s.into_inner()).ok().or(last_status);
    processes.stop();
    let text = report(preset, run_dir, &final_status.unwrap_or_default(), started.elapsed().as_secs_f64(), &end, &run_id, interrupted)?;
    match end.ended_early {
        Some(why) => {
            println!("{text}");
            bail!("the run ended before its budget: {why}")
        }
        None => Ok(text),
    }
}

