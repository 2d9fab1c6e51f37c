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

use std::path::PathBuf;
use std::time::Instant;

use lcrl_sim::{make_env, Env};

use crate::policy::action::ActionMap;
use crate::algo::agent::observe;
use crate::run::files::{read_rows, EpisodeRow, MetricsLog};
use crate::run::summary::{evaluate_hand_over, write_summary, EvaluationPlan, GraphRecord, RunSummary};
use crate::policy::checkpoint::{write_checkpoint, CheckpointMeta};
use crate::run::start::{prepare, GraphSource, Prepared, RunStart};
use crate::config::{Algo, Connection, TrainConfig};
use crate::run::selection::{selected_dir, Selection};
use crate::{io, LearnerError};

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

/// Per-episode progress for the caller's display.
pub struct Progress<'a> {
    pub row: &'a EpisodeRow,
    pub episodes: usize,
    pub moving_average: f64,
    pub env_steps_per_sec: f64,
}

/// The result of a run: its summary and every metrics row.
pub struct TrainOutcome {
    pub summary: RunSummary,
    pub rows: Vec<EpisodeRow>,
}


/// One step of `lcrl train`'s loop from the agent's sampled u: the
/// environment's action is made by the action map (the one place it is
/// made; actors do the same), and the next state is normalized. The agent
/// stores u itself, not the action the map made of it.
pub fn step_env(env: &mut dyn Env, actions: &ActionMap, u: &[f32]) -> Result<(lcrl_sim::Step, Vec<f32>), LearnerError> {
    let step = env.step(&actions.to_env(u))?;
    let next_obs = observe(env, &step.state);
    Ok((step, next_obs))
}

/// Trains for `config.run.episodes` episodes (in total, counting resumed
/// ones), writing the run directory as it goes. The loop reads as the
/// distributed one ([`crate::service::runtime::TrainingLoop`]) does: start,
/// then per episode play, record, checkpoint if due, validate if due; then
/// finish.
pub fn train(req: &TrainRequest, on_episode: &mut dyn FnMut(&Progress)) -> Result<TrainOutcome, LearnerError> {
    let mut run = SingleProcessLoop::start(req)?;
    for episode in run.rows.len()..run.last_episode {
        let played = run.play(episode)?;
        run.record(played, on_episode)?;
        run.checkpoint_if_due(episode + 1)?;
        run.validate_if_due(episode + 1)?;
    }
    run.finish()
}

/// `lcrl train`'s run in progress: the environment, the agent and the run
/// directory's files, held by this process (`_lock`).
struct SingleProcessLoop<'r> {
    req: &'r TrainRequest,
    started: Instant,
    env: Box<dyn Env>,
    agent: Box<dyn crate::algo::agent::Agent>,
    actions: ActionMap,
    cfg: TrainConfig,
    /// The metadata every checkpoint of this run starts from.
    start: CheckpointMeta,
    mask: Vec<Vec<u8>>,
    graph_record: Option<GraphRecord>,
    rows: Vec<EpisodeRow>,
    metrics: MetricsLog,
    tensorboard: crate::run::tensorboard::EventWriter,
    selection: Option<Selection>,
    /// Update time so far, and the wall time of earlier lives (resumes).
    optimization: f64,
    prior_elapsed: f64,
    last_episode: usize,
    _lock: Option<crate::run::lock::RunLock>,
}

/// One episode as played: its row, and what the progress line needs.
struct Played {
    row: EpisodeRow,
    started: Instant,
    steps: u64,
}

impl<'r> SingleProcessLoop<'r> {
    /// Prepares (or resumes) the run, writes graph.json and config.toml,
    /// opens the metrics and the events, and validates the starting policy
    /// where selection asks.
    fn start(req: &'r TrainRequest) -> Result<Self, LearnerError> {
        let started = Instant::now();
        let env = make_env(&req.env)?;
        let prepared = prepare(
            RunStart {
                env: &req.env,
                algo: req.algo,
                connection: req.connection,
                run_dir: &req.run_dir,
                config: req.config.clone(),
                graph: req.graph.as_deref().map_or(GraphSource::Measure, GraphSource::File),
                resume: req.resume,
                // lcrl train computes as this invocation says, resumed or not.
                device: Some(req.config.run.device.clone()),
                threads: Some(req.config.run.threads),
            },
            env.as_ref(),
        )?;
        let Prepared { config: cfg, checkpoint, meta: start, graph, agent, actions, lock, .. } = prepared;
        if let Some(report) = &graph {
            report.write_json(&req.run_dir.join("graph.json"))?;
        }
        let rows = match &checkpoint {
            Some(_) => read_rows(&req.run_dir.join("metrics.csv"), start.episode)?,
            None => Vec::new(),
        };
        // A given graph (a study's draw, a graph file) is named in config.toml
        // and summary.json, so a run says which graph it trained on.
        let graph_record = req.graph.as_ref().map(|file| GraphRecord { file: file.display().to_string(), origin: graph.as_ref().and_then(|g| g.origin.clone()) });
        write_config(req, &cfg, graph_record.as_ref())?;
        let metrics = MetricsLog::create(&req.run_dir.join("metrics.csv"), &rows)?;
        let tensorboard = crate::run::tensorboard::EventWriter::create(&req.run_dir).map_err(io(&req.run_dir))?;
        let last_episode = req.stop_after.map_or(cfg.run.episodes, |stop| stop.min(cfg.run.episodes));
        let selection = Selection::new(&cfg.run, &req.run_dir, checkpoint.is_some())?;
        let mut run = SingleProcessLoop {
            req,
            started,
            env,
            agent,
            actions,
            mask: start.shape.mask.clone(),
            optimization: start.optimization_seconds,
            prior_elapsed: start.elapsed_seconds,
            start,
            cfg,
            graph_record,
            rows,
            metrics,
            tensorboard,
            selection,
            last_episode,
            _lock: lock,
        };
        run.validate_if_due(run.rows.len())?;
        Ok(run)
    }

    /// The checkpoint metadata after `episode` episodes.
    fn meta(&self, episode: usize) -> CheckpointMeta {
        let elapsed = self.prior_elapsed + self.started.elapsed().as_secs_f64();
        CheckpointMeta { episode, optimization_seconds: self.optimization, elapsed_seconds: elapsed, ..self.start.clone() }
    }

    /// Plays episode `episode` (0-based) with exploration, the agent
    /// learning as it goes (Algorithm 2's inner loop).
    fn play(&mut self, episode: usize) -> Result<Played, LearnerError> {
        let episode_started = Instant::now();
        let _span = tracing::info_span!("episode", episode = episode + 1).entered();
        let (env, agent) = (self.env.as_mut(), self.agent.as_mut());
        agent.set_progress(episode as f64 / self.cfg.run.episodes as f64);
        let steps_before = agent.counters().env_steps;
        let mut state = env.reset(lcrl_sim::seeds::training(self.cfg.run.seed, episode))?;
        let (mut total, mut length, mut opt_seconds) = (0.0, 0, 0.0);
        // A start beyond the environment's bounds (issue 82: a served
        // environment's 1e30 start state ended a run) is never acted on:
        // the episode ends before its first step, as a diverged one.
        let unsound_start = lcrl_sim::state_out_of_bounds(env, &state);
        if let Some(why) = &unsound_start {
            tracing::warn!("the environment's start state is unsound ({why}): the episode ends before its first step (diverged_env)");
            agent.end_stream();
        }
        while unsound_start.is_none() {
            let obs = observe(env, &state);
            let u = agent.explore(&obs, episode);
            let (step, next_obs) = step_env(env, &self.actions, &u)?;
            if let Some(why) = lcrl_sim::diverged(env, &step) {
                // The episode ends at its last sound state; training goes on.
                tracing::warn!(steps = length, "the environment diverged ({why}): the episode ends here (diverged_env)");
                agent.end_stream();
                break;
            }
            opt_seconds += agent.observe(crate::algo::agent::Transition {
                obs: &obs,
                action: &u,
                reward: step.reward as f32,
                next_obs: &next_obs,
                terminated: step.terminated,
                truncated: step.truncated,
                log_prob: None,
                cut: false,
                stream: 0,
            });
            total += step.reward;
            length += 1;
            state = step.state;
            if step.terminated || step.truncated {
                break;
            }
        }
        self.optimization += opt_seconds;
        let metrics_now = env.episode_metrics();
        let row = EpisodeRow {
            episode: episode + 1,
            episode_return: total,
            length,
            success: metrics_now.success,
            peak_force_n: metrics_now.peak_force_n,
            peak_moment_nm: metrics_now.peak_moment_nm,
            wall_s: Some(episode_started.elapsed().as_secs_f64()),
            optimization_s: Some(opt_seconds),
            terms: Default::default(),
        }
        .with_terms(metrics_now.return_terms);
        Ok(Played { row, started: episode_started, steps: agent.counters().env_steps - steps_before })
    }

    /// The episode's row in metrics.csv and TensorBoard, and the caller's
    /// progress line.
    fn record(&mut self, played: Played, on_episode: &mut dyn FnMut(&Progress)) -> Result<(), LearnerError> {
        let row = played.row;
        self.metrics.push(&row)?;
        let mut scalars = vec![("episode/return", row.episode_return), ("episode/length", row.length as f64), ("time/optimization_s", row.optimization_s.unwrap_or(0.0))];
        scalars.extend(row.peak_force_n.map(|f| ("episode/peak_force_n", f)));
        scalars.extend(row.success.map(|s| ("episode/success", f64::from(u8::from(s)))));
        let tensorboard = &mut self.tensorboard;
        tensorboard.scalars(row.episode as i64, &scalars).and_then(|()| tensorboard.flush()).map_err(io(tensorboard.path()))?;
        self.rows.push(row);
        let recent = &self.rows[self.rows.len().saturating_sub(10)..];
        on_episode(&Progress {
            row: &recent[recent.len() - 1],
            episodes: self.cfg.run.episodes,
            moving_average: recent.iter().map(|r| r.episode_return).sum::<f64>() / recent.len() as f64,
            env_steps_per_sec: played.steps as f64 / played.started.elapsed().as_secs_f64().max(1e-9),
        });
        Ok(())
    }

    /// A checkpoint every `run.checkpoint_every` episodes and at the last.
    fn checkpoint_if_due(&mut self, done: usize) -> Result<(), LearnerError> {
        if done % self.cfg.run.checkpoint_every != 0 && done != self.last_episode {
            return Ok(());
        }
        match write_checkpoint(&self.req.run_dir, self.agent.as_ref(), &self.meta(done)) {
            // Diverged weights are never written; the run still ends
            // with its summary (issue 71).
            Err(crate::LearnerError::Diverged(why)) => {
                tracing::error!(episode = done, "{why}");
                Ok(())
            }
            other => other.map(|_| ()),
        }
    }

    /// Validation of the policy after `done` episodes, where selection asks.
    fn validate_if_due(&mut self, done: usize) -> Result<(), LearnerError> {
        let meta = self.meta(done);
        if let Some(selection) = self.selection.as_mut().filter(|s| s.due(done, self.last_episode)) {
            selection.validate(self.env.as_ref(), self.agent.as_ref(), &self.req.run_dir, &meta)?;
        }
        Ok(())
    }

    /// The run's policy (the selected one, confirmed on more starts where
    /// the run asks, or the last) beside the references, on the same
    /// starts (crate::run::summary, as the learner does); summary.json.
    fn finish(mut self) -> Result<TrainOutcome, LearnerError> {
        let req = self.req;
        if let Some(selection) = self.selection.as_mut() {
            selection.confirm(self.env.as_ref(), &req.run_dir)?;
        }
        let chosen = self.selection.as_ref().and_then(Selection::record);
        let last = crate::policy::snapshot::snapshot(self.agent.as_ref(), &self.start.architecture(), 0)?;
        // The last validation chose the agent as it is: that is the last policy.
        let selected = match &chosen {
            Some(c) if c.episode != self.rows.len() => Some(crate::policy::snapshot::read_snapshot(&selected_dir(&req.run_dir))?),
            _ => None,
        };
        let plan = EvaluationPlan {
            episodes: self.cfg.run.eval_episodes,
            first_seed: self.cfg.run.first_eval_seed(),
            local_mask: (req.connection == Connection::Local).then_some(self.mask.as_slice()),
            headroom: None,
        };
        let evaluation = evaluate_hand_over(self.env.as_ref(), selected.as_ref(), &last, &plan)?;
        let recent = &self.rows[self.rows.len().saturating_sub(10)..];
        let (actor_params, critic_params) = self.agent.param_counts();
        let counters = self.agent.counters();
        let summary = RunSummary {
            env: req.env.clone(),
            algo: req.algo,
            connection: req.connection,
            seed: self.cfg.run.seed,
            episodes: self.rows.len(),
            final_return: recent.iter().map(|r| r.episode_return).sum::<f64>() / recent.len().max(1) as f64,
            evaluation,
            selection: chosen,
            graph_seconds: self.start.graph_seconds,
            graph: self.graph_record.clone(),
            optimization_seconds: self.optimization,
            total_seconds: self.prior_elapsed + self.started.elapsed().as_secs_f64(),
            env_steps: counters.env_steps,
            updates: counters.updates,
            critic_updates: counters.critic_updates,
            skipped_updates: counters.skipped_updates,
            diverged_env: counters.diverged_env,
            samples_drawn: self.agent.samples_drawn(),
            actor_params,
            critic_params,
            service: None,
        };
        write_summary(&req.run_dir, &summary)?;
        Ok(TrainOutcome { summary, rows: self.rows })
    }
}

/// config.toml: every resolved setting, where the settings came from, and
/// which graph the run trains on and why (a measured graph's T).
fn write_config(req: &TrainRequest, cfg: &TrainConfig, graph_record: Option<&GraphRecord>) -> Result<(), LearnerError> {
    let resolved = toml::to_string_pretty(cfg).map_err(|e| LearnerError::Config(e.to_string()))?;
    let mut header = format!(
        "# resolved configuration\n# env = {:?}, algo = {:?}, connection = {:?}\n# settings from: {}\n",
        req.env, req.algo, req.connection, req.settings_source
    );
    if req.connection == Connection::Local && req.graph.is_none() {
        let t = cfg.run.graph_threshold;
        header += &format!("# graph: measured, eq. 7 at T = {t}: {}\n", lcrl_graph_builder::choose_t::threshold_reason(t));
    }
    if let Some(record) = graph_record {
        header += &format!("# graph file: {}\n# graph origin: {}\n", record.file, record.origin.as_deref().unwrap_or("measured"));
    }
    crate::run::files::write_atomically(&req.run_dir.join("config.toml"), (header + &resolved).as_bytes())
}
