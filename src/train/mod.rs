//! `lcrl train`: LCRL or the GCRL baseline, trained in one process.
//!
//! The wiring of `lcrl train`, as named steps: [`run`] starts a served
//! environment where the config names one, then trains here: the settings
//! (config over the environment's, then the command line's overrides), the
//! connection checked against what one run can do, a given graph written
//! as a file, training with a progress bar, and the figures and reward
//! curve of report.rs. The binary only parses arguments.

mod report;
#[cfg(test)]
mod tests;

use std::path::PathBuf;

use anyhow::Context;
use lcrl_learner::run::trainer::{train, TrainRequest};
use lcrl_learner::{Algo, TrainConfig};

use crate::connection::ConnectionSpec;
use report::{plot_rewards, print_summary};

/// Train an actor with DDPG or PPO; the environment runs in this process.
#[derive(Debug, Clone, clap::Args)]
pub struct TrainArgs {
    /// Environment: a registered name, a path to a .toml file, or
    /// grpc://HOST:PORT for a served one (`python -m lcrl_env serve`; with
    /// `[env_server]` in --config, where the server it starts listens,
    /// e.g. grpc://127.0.0.1:0).
    #[arg(long)]
    pub env: String,
    #[arg(long, value_enum)]
    pub algo: Algo,
    /// local: LCRL (each action sees its connected states, eq. 8), its
    /// graph built with CS3 at T_rule = 1 (the above-average rule;
    /// local@0.1 is the publication's); local@T: at another T; graph:PATH:
    /// with a given graph.json (e.g. references/peg-eq21/graph.json);
    /// random@K: with K edges drawn at random (--graph-seed picks the draw);
    /// global: the GCRL baseline; full-subnets: the ablation. (Studies
    /// also take global+match=CONNECTION: here --connection global
    /// --match-params GRAPH.) Default: local at the config's
    /// run.graph_threshold (T_rule = 1 unless the config says otherwise).
    #[arg(long, value_name = "CONNECTION")]
    pub connection: Option<ConnectionSpec>,
    /// Use this graph.json instead of building the graph first (local
    /// kinds only; the same as --connection graph:PATH).
    #[arg(long, value_name = "graph.json")]
    pub graph: Option<PathBuf>,
    /// With --connection global: size the global actor's hidden layers
    /// (network.global_hidden's depth, one width) so it has as many
    /// parameters as the local actor on this graph.json would, the
    /// matched-size control of docs/lcrl-value.md.
    #[arg(long, value_name = "graph.json")]
    pub match_params: Option<PathBuf>,
    /// The draw of a random@K graph (the same draw for every --seed, so the
    /// seeds of a study cell share one graph).
    #[arg(long, default_value_t = 0)]
    pub graph_seed: u64,
    /// Episodes in total (overrides run.episodes of the config). The peg
    /// presets learn in 200 (DDPG, about 3–4 minutes on 2 cores) and 900
    /// (PPO, about 1–2 minutes); a run much shorter may hand over its
    /// starting policy, and says so.
    #[arg(long)]
    pub episodes: Option<usize>,
    /// Seed of networks, exploration and episodes (overrides run.seed).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Episodes of the deterministic policy evaluated after training
    /// (overrides run.eval_episodes; 1 to 100000).
    #[arg(long, value_parser = lcrl_runtime::process::count_in::<1, 100_000>)]
    pub eval_episodes: Option<usize>,
    /// First seed of the evaluation starts (overrides run.eval_seed; by
    /// default the run's own held-out range). `lcrl tune`'s are 0 on: with
    /// --eval-seed 0 the run is evaluated on the starts the best constant
    /// and a = 0 are, start for start.
    #[arg(long)]
    pub eval_seed: Option<u64>,
    /// libtorch intra-op threads (overrides run.threads; 0: the cores, at
    /// most 4).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Where the networks compute (overrides run.device).
    #[arg(long, value_parser = ["cpu", "cuda"])]
    pub device: Option<String>,
    /// Act around this base controller (residual RL): a best_constant.json
    /// of `lcrl tune`; sets base.action = "best-constant" from that file.
    #[arg(long, value_name = "best_constant.json")]
    pub base_action: Option<PathBuf>,
    /// Training configuration (TOML); keys it leaves out keep the
    /// environment's settings (configs/peg.toml on peg presets, with
    /// configs/peg-experiment.toml over it on peg-experiment and
    /// configs/peg-rand.toml on the -rand presets;
    /// configs/lti-fast.toml on lti-paper; Table I elsewhere).
    #[arg(long, value_name = "train.toml")]
    pub config: Option<PathBuf>,
    /// Run directory: config, graph, metrics.csv, summary.json, reward
    /// curve, checkpoints.
    #[arg(long, default_value = "runs/train")]
    pub run_dir: PathBuf,
    /// Continue the run in --run-dir from its newest checkpoint.
    #[arg(long)]
    pub resume: bool,
}

/// Sets network.global_hidden so the global actor has as many parameters
/// as the local actor on the graph in `path` (`--match-params`).
fn match_global_to_local(config: &mut TrainConfig, env: &str, path: &std::path::Path) -> anyhow::Result<()> {
    let spec = lcrl_sim::make_env(env)?.spec().clone();
    // As measured (an action may have no edge: dz at T = 1), like the
    // graphs `lcrl graph` writes for the local cells it matches.
    let graph = lcrl_graph_builder::given::load_measured_for(path, &spec).with_context(|| format!("--match-params {}", path.display()))?;
    let shape = (spec.state_names.len(), spec.action_names.len());
    let target = lcrl_learner::algo::nets::local_actor_params(&config.network, &graph.g);
    config.network.global_hidden = lcrl_learner::algo::nets::matched_global_hidden(&config.network, shape, target);
    let matched = lcrl_learner::algo::nets::global_actor_params(&config.network, shape);
    eprintln!(
        "global actor matched to the local actor of {}: hidden {:?}, {matched} parameters against {target} ({:+.1}%)",
        path.display(),
        config.network.global_hidden,
        100.0 * (matched as f64 / target as f64 - 1.0)
    );
    Ok(())
}

pub fn run(args: &TrainArgs) -> anyhow::Result<()> {
    // A run directory another process holds is refused before anything in
    // it is written (the environment server's token among them); the
    // trainer takes the lock for itself when it starts.
    if args.run_dir.is_dir() {
        drop(lcrl_learner::run::lock::RunLock::acquire(&args.run_dir)?);
    }
    match serve_configured_env(args)? {
        // The server lives until training and the final evaluation end.
        Some((served_args, _server, _config)) => train_here(&served_args),
        None => train_here(args),
    }
}

/// `[env_server]` in the training config: `lcrl train` starts the Python
/// environment server itself, as `lcrl run` does, and stops it at the end.
/// Returns the arguments pointing at it (`--env` its address, `--config`
/// the rest of the file), the server, and that file.
fn serve_configured_env(args: &TrainArgs) -> anyhow::Result<Option<(TrainArgs, crate::supervise::Managed, tempfile::NamedTempFile)>> {
    let Some(path) = &args.config else { return Ok(None) };
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut table: toml::Table = toml::from_str(&text).with_context(|| format!("{}", path.display()))?;
    let Some(section) = table.remove("env_server") else { return Ok(None) };
    let server: crate::preset::EnvServer = section.try_into().with_context(|| format!("{}: [env_server]", path.display()))?;
    server.check(&args.env)?;
    let listen = lcrl_sim::remote::address(&args.env).unwrap_or(&args.env).to_string();
    let logs = args.run_dir.join("logs");
    std::fs::create_dir_all(&logs).with_context(|| format!("creating {}", logs.display()))?;
    // The run's environment, plus the evaluation's and a validation's.
    let mut cmd = server.command(&listen, 3, path.parent().unwrap_or(std::path::Path::new(".")))?;
    // Its own token, as `lcrl run` gives its servers (unless one is set):
    // this process, its only client, reads it from $LCRL_TOKEN_FILE.
    if std::env::var_os(lcrl_runtime::security::TOKEN_FILE_ENV).is_none() {
        let token = args.run_dir.join("token");
        crate::run_security::write_token(&token)?;
        std::env::set_var(lcrl_runtime::security::TOKEN_FILE_ENV, &token);
    }
    crate::supervise::die_with_parent(&mut cmd);
    let (process, address) = crate::supervise::Managed::spawn("env-server", cmd, &logs, true)?;
    let address = address.with_context(|| format!("the environment server did not start; see {}", logs.join("env-server.log").display()))?;
    let rest = tempfile::NamedTempFile::new().context("a temporary file for the training settings")?;
    std::fs::write(rest.path(), toml::to_string(&table)?)?;
    let mut served = args.clone();
    served.env = format!("{}{address}", lcrl_sim::remote::SCHEME);
    served.config = Some(rest.path().to_path_buf());
    eprintln!("environment server at {}: {}", served.env, server.gym.as_deref().or(server.entry_point.as_deref()).unwrap_or(""));
    Ok(Some((served, process, rest)))
}

fn train_here(args: &TrainArgs) -> anyhow::Result<()> {
    if let Some(ConnectionSpec::MatchedGlobal { to }) = &args.connection {
        anyhow::bail!(
            "--connection global+match={}: for one run, give the graph of the actor it matches: `--connection global --match-params graph.json` \
             (the graph of {} from `lcrl graph`)",
            to.label(),
            to.label()
        );
    }
    let (mut config, source) = settings(args)?;
    let connection = connection_for(args, &mut config)?;
    let (given_file, graph) = given_graph(args, &connection)?;
    eprintln!("training settings: {source}");
    if let Some(checkpoint) = args.resume.then(|| lcrl_learner::policy::checkpoint::latest_checkpoint(&args.run_dir)).flatten() {
        eprintln!("resuming from checkpoint {}", checkpoint.display());
    }
    let request = TrainRequest {
        env: args.env.clone(),
        algo: args.algo,
        connection: connection.connection(),
        graph,
        config: config.clone(),
        settings_source: source,
        run_dir: args.run_dir.clone(),
        resume: args.resume,
        stop_after: None,
    };
    let outcome = train_with_progress(&request)?;
    drop(given_file);
    plot_rewards(&outcome.rows, &outcome.summary, args, &connection)?;
    print_summary(&outcome.summary, &config, args)
}

/// The run's settings: the config file over the environment's (or the
/// environment's alone), then the command line's overrides; and where they
/// came from.
fn settings(args: &TrainArgs) -> anyhow::Result<(TrainConfig, String)> {
    let (mut config, source) = match &args.config {
        Some(path) => (TrainConfig::load_for_env(path, &args.env)?, format!("{} (missing keys: the environment's settings)", path.display())),
        None => {
            let (config, source) = TrainConfig::for_env(&args.env);
            (config, source.to_string())
        }
    };
    if let Some(episodes) = args.episodes {
        config.run.episodes = episodes;
    }
    if let Some(seed) = args.seed {
        config.run.seed = seed;
    }
    if let Some(threads) = args.threads {
        config.run.threads = threads;
    }
    if let Some(episodes) = args.eval_episodes {
        config.run.eval_episodes = episodes;
    }
    if let Some(seed) = args.eval_seed {
        config.run.eval_seed = Some(seed);
    }
    if let Some(device) = &args.device {
        config.run.device = device.clone();
    }
    if let Some(path) = &args.base_action {
        // Read now, so a bad file fails before any work.
        lcrl_learner::policy::action::read_best_constant(path)?;
        config.base.action = lcrl_learner::config::BaseController::BestConstant;
        config.base.best_constant_file = Some(path.clone());
    }
    Ok((config, source))
}

/// The actor's connection (the local actor at the config's threshold
/// without --connection), checked against what one run can do.
fn connection_for(args: &TrainArgs, config: &mut TrainConfig) -> anyhow::Result<ConnectionSpec> {
    // Without --connection: the local actor at the config's threshold.
    let connection = args.connection.clone().unwrap_or(ConnectionSpec::Local { threshold: config.run.graph_threshold, rows: Vec::new(), per_seed: false });
    if let Some(t) = connection.threshold() {
        config.run.graph_threshold = t;
    }
    config.validate()?;
    if let Some(path) = &args.match_params {
        if connection != ConnectionSpec::Global {
            anyhow::bail!("--match-params sizes a global actor: use it with --connection global (it has --connection {})", connection.label());
        }
        match_global_to_local(config, &args.env, path)?;
    }
    if let ConnectionSpec::RandomRows { .. } = &connection {
        anyhow::bail!(
            "--connection {}: random rows are a study's control (lcrl experiment: draws by environment and draw index); for one run, \
             draw the graph with `lcrl graph --env ENV --random-rows GRAPH.json --seed N --out rows.json` and pass `--connection local --graph rows.json`",
            connection.label()
        );
    }
    if connection.has_modifiers() {
        anyhow::bail!(
            "--connection {}: +per-seed and row rules (+ACTION=T) are for studies (lcrl experiment); for one run, build the graph with \
             `lcrl graph --threshold T --row ACTION=T --seed N --out graph.json` and pass `--connection local --graph graph.json`",
            connection.label()
        );
    }
    if args.graph.is_some() && !matches!(connection, ConnectionSpec::Local { .. }) {
        anyhow::bail!("--graph only applies to --connection local or local@T (graph:PATH names the file itself)");
    }
    Ok(connection)
}

/// A given graph (graph:PATH, random@K) reaches the trainer as a file,
/// checked against the environment first; the run records it as its
/// graph.json, with `origin` saying where it came from. Returns the file
/// (kept until training ends) and the graph path to train with.
fn given_graph(args: &TrainArgs, connection: &ConnectionSpec) -> anyhow::Result<(Option<tempfile::NamedTempFile>, Option<std::path::PathBuf>)> {
    let given = match connection {
        ConnectionSpec::Graph { .. } | ConnectionSpec::Random { .. } => connection.given_graph(lcrl_sim::make_env(&args.env)?.spec(), args.graph_seed)?,
        _ => None,
    };
    let given_file = match &given {
        Some(report) => {
            let file = tempfile::NamedTempFile::new().context("a temporary file for the given graph")?;
            report.write_json(file.path())?;
            Some(file)
        }
        None => None,
    };
    let graph = given_file.as_ref().map(|f| f.path().to_path_buf()).or_else(|| args.graph.clone());
    if let Some(report) = &given {
        eprintln!("{}", report.origin_line());
    }
    Ok((given_file, graph))
}

/// Trains with a progress bar (episode, return, its 10-episode average,
/// steps per second).
fn train_with_progress(request: &TrainRequest) -> anyhow::Result<lcrl_learner::run::trainer::TrainOutcome> {
    let bar = lcrl_graph_builder::progress::bar(request.config.run.episodes as u64, "episode {pos}/{len} [{bar:25}] {msg} ({elapsed}, eta {eta})");
    let outcome = train(request, &mut |p| {
        bar.set_length(p.episodes as u64);
        bar.set_position(p.row.episode as u64);
        bar.set_message(format!(
            "return {:.2}, avg(10) {:.2}, {:.0} steps/s",
            p.row.episode_return, p.moving_average, p.env_steps_per_sec
        ));
    });
    bar.finish_and_clear();
    Ok(outcome?)
}

