//! The single-process training loop: the environment runs inside the
//! learner's process. It owns the run directory:
//!
//! ```text
//! DIR/config.toml            resolved configuration (+ env, algo, connection)
//! DIR/graph.json             connection graph (connection = local)
//! DIR/metrics.csv            one row per episode
//! DIR/events.out.tfevents.*  the same as TensorBoard scalars
//! DIR/summary.json           final figures
//! DIR/checkpoints/epNNNNNN/  weights, optimizer state, replay, counters
//! ```

use std::path::{Path, PathBuf};
use std::time::Instant;

use lcrl_graph_builder::{build_graph, Cs3Config, GraphOptions, GraphReport, Rule};
use lcrl_sim::evaluate::evaluate;
use lcrl_sim::{make_env, Env};
use serde::{Deserialize, Serialize};

use crate::agent::Agent;
use crate::config::{Algo, Connection, TrainConfig};
use crate::ddpg::Ddpg;
use crate::lqr::{lqr_return, masked_lqr_return};
use crate::ppo::Ppo;
use crate::LearnerError;

/// What to train, and where.
#[derive(Debug, Clone)]
pub struct TrainRequest {
    pub env: String,
    pub algo: Algo,
    pub connection: Connection,
    /// A graph.json to use instead of building one (connection = local).
    pub graph: Option<PathBuf>,
    pub config: TrainConfig,
    /// Where the settings came from (a file, or the environment's
    /// defaults), recorded in the run's config.toml.
    pub settings_source: String,
    pub run_dir: PathBuf,
    pub resume: bool,
    /// Stop (with a checkpoint) after this many episodes, as an interruption
    /// would, keeping every schedule of the full run. None: run to the end.
    pub stop_after: Option<usize>,
}

/// One row of metrics.csv.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRow {
    pub episode: usize,
    #[serde(rename = "return")]
    pub episode_return: f64,
    pub length: usize,
    pub success: Option<bool>,
    pub peak_force_n: Option<f64>,
    pub peak_moment_nm: Option<f64>,
    pub wall_s: f64,
    pub optimization_s: f64,
    /// The return split into its reward terms (peg tasks; docs/peg.md).
    /// Spelled out rather than a flattened `ReturnColumns`: the csv crate
    /// cannot write flattened structs.
    #[serde(default)]
    pub return_depth: Option<f64>,
    #[serde(default)]
    pub return_force: Option<f64>,
    #[serde(default)]
    pub return_moment: Option<f64>,
    #[serde(default)]
    pub return_bonus: Option<f64>,
    #[serde(default)]
    pub return_failure: Option<f64>,
}

/// The columns of metrics.csv, in EpisodeRow's order.
pub const METRICS_COLUMNS: [&str; 13] = [
    "episode",
    "return",
    "length",
    "success",
    "peak_force_n",
    "peak_moment_nm",
    "wall_s",
    "optimization_s",
    "return_depth",
    "return_force",
    "return_moment",
    "return_bonus",
    "return_failure",
];

impl EpisodeRow {
    /// Fills the return-term columns from the episode's metrics.
    pub fn with_terms(self, terms: Option<lcrl_sim::ReturnTerms>) -> Self {
        let c = lcrl_sim::ReturnColumns::from(terms);
        EpisodeRow {
            return_depth: c.return_depth,
            return_force: c.return_force,
            return_moment: c.return_moment,
            return_bonus: c.return_bonus,
            return_failure: c.return_failure,
            ..self
        }
    }
}

/// What summary.json holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainSummary {
    pub env: String,
    pub algo: Algo,
    pub connection: Connection,
    pub seed: u64,
    pub episodes: usize,
    /// Mean return of the last 10 training episodes (with exploration).
    pub final_return: f64,
    /// Mean return of the deterministic policy over `eval_episodes` episodes.
    pub eval_return: f64,
    /// The evaluation's success rate and mean peak force (peg tasks).
    #[serde(default)]
    pub eval_success_rate: Option<f64>,
    #[serde(default)]
    pub eval_peak_force_n: Option<f64>,
    /// The evaluation return split into its reward terms (peg tasks).
    #[serde(flatten)]
    pub eval_terms: lcrl_sim::ReturnColumns,
    /// The neutral constant action a = 0 on the same evaluation episodes
    /// (on peg tasks the constant compliance controller): a reference line.
    #[serde(default)]
    pub zero_action_return: Option<f64>,
    /// The LQR controller's mean return on the same evaluation episodes
    /// (linear environments only).
    pub lqr_return: Option<f64>,
    /// The best controller with the actor's connection pattern (a = −K s
    /// with K zero where the mask is): the ceiling of a local actor, which
    /// may be below `lqr_return` when G hides states the optimum uses.
    pub masked_lqr_return: Option<f64>,
    pub graph_seconds: f64,
    pub optimization_seconds: f64,
    pub total_seconds: f64,
    pub env_steps: u64,
    pub updates: u64,
    pub actor_params: usize,
    pub critic_params: usize,
}

/// Written next to the tensors of every checkpoint.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointMeta {
    /// Episodes completed when the checkpoint was written.
    pub episode: usize,
    pub env: String,
    pub algo: Algo,
    pub connection: Connection,
    pub state_dim: usize,
    pub action_dim: usize,
    /// The actor's connection mask (n × m).
    pub mask: Vec<Vec<u8>>,
    pub config: TrainConfig,
    pub graph_seconds: f64,
    pub optimization_seconds: f64,
    /// Wall time of the run so far (graph, set-up, training), seconds.
    pub elapsed_seconds: f64,
    /// Distributed runs: the policy version at the checkpoint.
    #[serde(default)]
    pub policy_version: u64,
    /// Distributed runs: the highest batch sequence stored per actor, so a
    /// restarted learner still rejects replayed batches.
    #[serde(default)]
    pub actor_sequences: std::collections::HashMap<String, u64>,
    /// Distributed DDPG runs: the replay-ratio limiter's settings and
    /// counters, so a restarted learner keeps the ratio.
    #[serde(default)]
    pub rate_limiter: Option<crate::rate_limiter::RateLimiter>,
}

impl CheckpointMeta {
    /// The actor's architecture, as a published policy describes it.
    pub fn architecture(&self) -> crate::snapshot::Architecture {
        crate::snapshot::Architecture {
            env: self.env.clone(),
            algo: self.algo,
            connection: self.connection,
            state_dim: self.state_dim,
            action_dim: self.action_dim,
            mask: self.mask.clone(),
            network: self.config.network.clone(),
            base: self.config.controller.base_action(self.action_dim),
        }
    }
}

/// Per-episode progress for the caller's display.
pub struct Progress<'a> {
    pub row: &'a EpisodeRow,
    pub episodes: usize,
    pub moving_average: f64,
    pub env_steps_per_sec: f64,
}

/// The result of a run: its summary and every metrics row.
pub struct TrainOutcome {
    pub summary: TrainSummary,
    pub rows: Vec<EpisodeRow>,
}

/// The seed of training episode `episode`: distinct per episode, and
/// disjoint from the evaluation seeds.
fn episode_seed(seed: u64, episode: usize) -> u64 {
    seed.wrapping_mul(1_000_003).wrapping_add(episode as u64)
}

pub fn eval_seed(seed: u64, k: usize) -> u64 {
    (seed ^ 0xE7A1_0000_0000).wrapping_mul(7_919).wrapping_add(k as u64)
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> LearnerError + '_ {
    move |source| LearnerError::Io { path: path.to_path_buf(), source }
}

/// A raw state as the agent's input: normalized, f32.
pub fn observe(env: &dyn Env, state: &[f64]) -> Vec<f32> {
    env.normalize_state(state).iter().map(|&v| v as f32).collect()
}

/// The libtorch device of `run.device` (validated: "cpu" or "cuda").
pub fn device(cfg: &TrainConfig) -> Result<tch::Device, LearnerError> {
    match cfg.run.device.as_str() {
        "cuda" if tch::Cuda::is_available() => Ok(tch::Device::Cuda(0)),
        "cuda" => Err(LearnerError::Config("run.device = \"cuda\" but no CUDA device is available; use \"cpu\"".into())),
        _ => Ok(tch::Device::Cpu),
    }
}

/// Builds the agent for the request on `run.device`.
pub fn make_agent(algo: Algo, connection: Connection, cfg: &TrainConfig, mask: &[Vec<u8>], m: usize, n: usize) -> Result<Box<dyn Agent>, LearnerError> {
    let device = device(cfg)?;
    Ok(match algo {
        Algo::Ddpg => Box::new(Ddpg::new(&cfg.ddpg, &cfg.network, connection, mask, m, n, cfg.run.seed, device)),
        Algo::Ppo => Box::new(Ppo::new(&cfg.ppo, &cfg.network, connection, mask, m, n, cfg.run.seed, device)),
    })
}

/// The mask of the actor: G for local (loaded or built), ones otherwise.
fn resolve_mask(req: &TrainRequest, env: &dyn Env) -> Result<(Vec<Vec<u8>>, f64, Option<GraphReport>), LearnerError> {
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    if req.connection != Connection::Local {
        return Ok((vec![vec![1; m]; n], 0.0, None));
    }
    let report = match &req.graph {
        Some(path) => GraphReport::load(path)?,
        None => {
            let options = GraphOptions {
                cs3: Cs3Config { samples: req.config.run.graph_samples, seed: req.config.run.seed, threads: 0, start: None },
                rule: Rule::Threshold(0.1),
                bootstrap: 200,
            };
            build_graph(env, &options, &|| {})?
        }
    };
    if report.actions() != n || report.states() != m {
        return Err(LearnerError::Mismatch(format!(
            "the graph is {}×{} (actions × states) but environment {} has {n} actions and {m} states; build the graph for this environment",
            report.actions(),
            report.states(),
            env.spec().name
        )));
    }
    let seconds = if req.graph.is_some() { 0.0 } else { report.elapsed_s };
    Ok((report.g.clone(), seconds, Some(report)))
}

/// The newest complete checkpoint under `run_dir`, if any.
pub fn latest_checkpoint(run_dir: &Path) -> Option<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(run_dir.join("checkpoints"))
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("checkpoint.json").is_file())
        .collect();
    dirs.sort();
    dirs.pop()
}

pub fn read_meta(dir: &Path) -> Result<CheckpointMeta, LearnerError> {
    let path = dir.join("checkpoint.json");
    let text = std::fs::read_to_string(&path).map_err(io(&path))?;
    serde_json::from_str(&text).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

/// Writes a checkpoint atomically: into a temporary folder, then renamed.
pub fn write_checkpoint(run_dir: &Path, agent: &dyn Agent, meta: &CheckpointMeta) -> Result<PathBuf, LearnerError> {
    let root = run_dir.join("checkpoints");
    std::fs::create_dir_all(&root).map_err(io(&root))?;
    let name = format!("ep{:06}", meta.episode);
    let staging = root.join(format!(".{name}.partial"));
    let _ = std::fs::remove_dir_all(&staging);
    std::fs::create_dir_all(&staging).map_err(io(&staging))?;
    agent.save(&staging, meta.config.run.save_replay)?;
    let text = serde_json::to_string_pretty(meta).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    std::fs::write(staging.join("checkpoint.json"), text).map_err(io(&staging))?;
    let target = root.join(name);
    let _ = std::fs::remove_dir_all(&target);
    std::fs::rename(&staging, &target).map_err(io(&target))?;
    prune_checkpoints(&root, KEEP_CHECKPOINTS);
    Ok(target)
}

/// Checkpoints kept per run: each can hold a replay buffer of hundreds of
/// megabytes, so only the newest few stay.
pub const KEEP_CHECKPOINTS: usize = 3;

/// Deletes all but the newest `keep` complete checkpoints.
fn prune_checkpoints(root: &Path, keep: usize) {
    let Ok(entries) = std::fs::read_dir(root) else { return };
    let mut complete: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("checkpoint.json").is_file())
        .collect();
    complete.sort();
    let excess = complete.len().saturating_sub(keep);
    for old in &complete[..excess] {
        if let Err(e) = std::fs::remove_dir_all(old) {
            tracing::warn!("cannot remove old checkpoint {}: {e}", old.display());
        }
    }
}

fn read_rows(path: &Path, keep: usize) -> Result<Vec<EpisodeRow>, LearnerError> {
    let mut reader = csv::Reader::from_path(path).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))?;
    let rows: Result<Vec<EpisodeRow>, _> = reader.deserialize().take(keep).collect();
    rows.map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

fn write_rows(path: &Path, rows: &[EpisodeRow]) -> Result<csv::Writer<std::fs::File>, LearnerError> {
    let file = std::fs::File::create(path).map_err(io(path))?;
    // The header is written by hand, now, so an interrupted run still leaves
    // a well-formed file (serde's automatic header waits for a first row).
    let mut writer = csv::WriterBuilder::new().has_headers(false).from_writer(file);
    writer
        .write_record(METRICS_COLUMNS)
        .map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    for row in rows {
        writer.serialize(row).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    }
    writer.flush().map_err(io(path))?;
    Ok(writer)
}

/// Trains for `config.run.episodes` episodes (in total, counting resumed
/// ones), writing the run directory as it goes.
pub fn train(req: &TrainRequest, on_episode: &mut dyn FnMut(&Progress)) -> Result<TrainOutcome, LearnerError> {
    let started = Instant::now();
    let mut env = make_env(&req.env)?;
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    std::fs::create_dir_all(&req.run_dir).map_err(io(&req.run_dir))?;
    let existing = latest_checkpoint(&req.run_dir);
    if existing.is_some() && !req.resume {
        return Err(LearnerError::Mismatch(format!(
            "{} already holds a run; pass --resume to continue it or choose another --run-dir",
            req.run_dir.display()
        )));
    }

    let mut cfg = req.config.clone();
    let (mask, graph_seconds, mut prior_opt, prior_elapsed, mut rows, checkpoint) = match (req.resume, existing) {
        (true, Some(dir)) => {
            let meta = read_meta(&dir)?;
            if meta.env != req.env || meta.algo != req.algo || meta.connection != req.connection {
                return Err(LearnerError::Mismatch(format!(
                    "{} was trained on {} with {:?}/{:?}; resume it with the same --env, --algo and --connection",
                    dir.display(),
                    meta.env,
                    meta.algo,
                    meta.connection
                )));
            }
            let episodes = cfg.run.episodes;
            cfg = meta.config.clone();
            cfg.run.episodes = episodes.max(meta.episode);
            let rows = read_rows(&req.run_dir.join("metrics.csv"), meta.episode)?;
            (meta.mask.clone(), meta.graph_seconds, meta.optimization_seconds, meta.elapsed_seconds, rows, Some(dir))
        }
        _ => {
            let (mask, seconds, report) = resolve_mask(req, env.as_ref())?;
            if let Some(report) = report {
                report.write_json(&req.run_dir.join("graph.json"))?;
            }
            (mask, seconds, 0.0, 0.0, Vec::new(), None)
        }
    };
    cfg.validate()?;
    // The base controller as numbers, so config.toml and every checkpoint
    // record exactly what the agent acted around.
    let base = crate::action::resolve_base(&cfg.controller, env.spec())?;
    cfg.controller.base = base.clone().map_or(crate::config::BaseController::None, crate::config::BaseController::Action);
    cfg.controller.best_constant_file = None;
    let actions = crate::action::ActionMap::new(env.spec(), base.as_deref())?;
    tch::set_num_threads(cfg.run.threads as i32);
    let resolved = toml::to_string_pretty(&cfg).map_err(|e| LearnerError::Config(e.to_string()))?;
    let header = format!(
        "# resolved configuration\n# env = {:?}, algo = {:?}, connection = {:?}\n# settings from: {}\n",
        req.env, req.algo, req.connection, req.settings_source
    );
    let config_path = req.run_dir.join("config.toml");
    std::fs::write(&config_path, header + &resolved).map_err(io(&config_path))?;

    let mut agent = make_agent(req.algo, req.connection, &cfg, &mask, m, n)?;
    if let Some(dir) = &checkpoint {
        agent.load(dir)?;
    }
    let metrics_path = req.run_dir.join("metrics.csv");
    let mut metrics = write_rows(&metrics_path, &rows)?;
    let mut tensorboard = crate::tensorboard::EventWriter::create(&req.run_dir).map_err(io(&req.run_dir))?;
    let mut optimization = prior_opt;
    let meta_for = |episode: usize, optimization: f64, elapsed: f64| CheckpointMeta {
        episode,
        env: req.env.clone(),
        algo: req.algo,
        connection: req.connection,
        state_dim: m,
        action_dim: n,
        mask: mask.clone(),
        config: cfg.clone(),
        graph_seconds,
        optimization_seconds: optimization,
        elapsed_seconds: elapsed,
        policy_version: 0,
        actor_sequences: Default::default(),
        rate_limiter: None,
    };

    let last_episode = req.stop_after.map_or(cfg.run.episodes, |stop| stop.min(cfg.run.episodes));
    for episode in rows.len()..last_episode {
        let episode_started = Instant::now();
        agent.set_progress(episode as f64 / cfg.run.episodes as f64);
        let steps_before = agent.counters().env_steps;
        let mut state = env.reset(episode_seed(cfg.run.seed, episode))?;
        let (mut total, mut length, mut opt_seconds) = (0.0, 0, 0.0);
        loop {
            let obs = observe(env.as_ref(), &state);
            let u = agent.explore(&obs, episode);
            let step = env.step(&actions.to_env(&u))?;
            let next_obs = observe(env.as_ref(), &step.state);
            opt_seconds += agent.observe(crate::agent::Transition {
                obs: &obs,
                action: &u,
                reward: step.reward as f32,
                next_obs: &next_obs,
                terminated: step.terminated,
                truncated: step.truncated,
            });
            total += step.reward;
            length += 1;
            state = step.state;
            if step.terminated || step.truncated {
                break;
            }
        }
        optimization += opt_seconds;
        let metrics_now = env.episode_metrics();
        let row = EpisodeRow {
            episode: episode + 1,
            episode_return: total,
            length,
            success: metrics_now.success,
            peak_force_n: metrics_now.peak_force_n,
            peak_moment_nm: metrics_now.peak_moment_nm,
            wall_s: episode_started.elapsed().as_secs_f64(),
            optimization_s: opt_seconds,
            return_depth: None,
            return_force: None,
            return_moment: None,
            return_bonus: None,
            return_failure: None,
        }
        .with_terms(metrics_now.return_terms);
        metrics.serialize(&row).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
        metrics.flush().map_err(io(&metrics_path))?;
        let mut scalars = vec![("episode/return", row.episode_return), ("episode/length", row.length as f64), ("time/optimization_s", row.optimization_s)];
        scalars.extend(row.peak_force_n.map(|f| ("episode/peak_force_n", f)));
        scalars.extend(row.success.map(|s| ("episode/success", f64::from(u8::from(s)))));
        tensorboard.scalars(row.episode as i64, &scalars).and_then(|()| tensorboard.flush()).map_err(io(tensorboard.path()))?;
        rows.push(row);
        let recent = &rows[rows.len().saturating_sub(10)..];
        let steps = agent.counters().env_steps - steps_before;
        on_episode(&Progress {
            row: rows.last().unwrap_or(&rows[0]),
            episodes: cfg.run.episodes,
            moving_average: recent.iter().map(|r| r.episode_return).sum::<f64>() / recent.len() as f64,
            env_steps_per_sec: steps as f64 / episode_started.elapsed().as_secs_f64().max(1e-9),
        });
        let done = episode + 1;
        if done % cfg.run.checkpoint_every == 0 || done == last_episode {
            let elapsed = prior_elapsed + started.elapsed().as_secs_f64();
            write_checkpoint(&req.run_dir, agent.as_ref(), &meta_for(done, optimization, elapsed))?;
        }
    }
    prior_opt = optimization;

    // The deterministic policy, a = 0 and the LQR ceiling on the same episodes.
    let episodes = cfg.run.eval_episodes.max(1);
    let env_ref = env.fresh();
    let mut policy = |s: &[f64]| actions.to_env(&agent.act(&observe(env_ref.as_ref(), s)));
    let (eval, _) = evaluate(env.as_mut(), "policy", episodes, eval_seed(cfg.run.seed, 0), &mut policy, &mut |_| {})?;
    let (zero, _) = evaluate(env.as_mut(), "a = 0", episodes, eval_seed(cfg.run.seed, 0), &mut |_| vec![0.0; n], &mut |_| {})?;
    let lqr = env.as_lti().and_then(|lti| lqr_return(lti, episodes, eval_seed(cfg.run.seed, 0)));
    let masked_lqr = env.as_lti().and_then(|lti| masked_lqr_return(lti, &mask, episodes, eval_seed(cfg.run.seed, 0)));
    let recent = &rows[rows.len().saturating_sub(10)..];
    let (actor_params, critic_params) = agent.param_counts();
    let counters = agent.counters();
    let summary = TrainSummary {
        env: req.env.clone(),
        algo: req.algo,
        connection: req.connection,
        seed: cfg.run.seed,
        episodes: rows.len(),
        final_return: recent.iter().map(|r| r.episode_return).sum::<f64>() / recent.len().max(1) as f64,
        eval_return: eval.mean_return,
        eval_success_rate: eval.success_rate,
        eval_peak_force_n: eval.mean_peak_force_n,
        eval_terms: eval.terms,
        zero_action_return: Some(zero.mean_return),
        lqr_return: lqr,
        masked_lqr_return: masked_lqr,
        graph_seconds,
        optimization_seconds: prior_opt,
        total_seconds: prior_elapsed + started.elapsed().as_secs_f64(),
        env_steps: counters.env_steps,
        updates: counters.updates,
        actor_params,
        critic_params,
    };
    let path = req.run_dir.join("summary.json");
    let text = serde_json::to_string_pretty(&summary).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    // Written whole, then renamed: a summary.json marks a finished run
    // (`lcrl experiment` skips it), so it must never be half a file.
    let partial = req.run_dir.join(".summary.json.partial");
    std::fs::write(&partial, text + "\n").map_err(io(&partial))?;
    std::fs::rename(&partial, &path).map_err(io(&path))?;
    Ok(TrainOutcome { summary, rows })
}
