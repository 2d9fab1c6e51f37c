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
/// ones), writing the run directory as it goes.
// long: the whole single-process loop (start, episodes, validation, checkpoints, end) in one place; issue 83 item 1 splits it into steps as TrainingLoop
pub fn train(req: &TrainRequest, on_episode: &mut dyn FnMut(&Progress)) -> Result<TrainOutcome, LearnerError> {
    let started = Instant::now();
    let mut env = make_env(&req.env)?;
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
    // `_lock` holds the run directory until training ends.
    let Prepared { config: cfg, checkpoint, meta: start, graph, mut agent, actions, lock: _lock, .. } = prepared;
    if let Some(report) = &graph {
        report.write_json(&req.run_dir.join("graph.json"))?;
    }
    let mask = start.shape.mask.clone();
    let (graph_seconds, mut prior_opt, prior_elapsed) = (start.graph_seconds, start.optimization_seconds, start.elapsed_seconds);
    let mut rows = match &checkpoint {
        Some(_) => read_rows(&req.run_dir.join("metrics.csv"), start.episode)?,
        None => Vec::new(),
    };
    // A given graph (a study's draw, a graph file) is named in config.toml
    // and summary.json, so a run says which graph it trained on.
    let graph_record = req.graph.as_ref().map(|file| GraphRecord {
        file: file.display().to_string(),
        origin: graph.as_ref().and_then(|g| g.origin.clone()),
    });
    let resolved = toml::to_string_pretty(&cfg).map_err(|e| LearnerError::Config(e.to_string()))?;
    let mut header = format!(
        "# resolved configuration\n# env = {:?}, algo = {:?}, connection = {:?}\n# settings from: {}\n",
        req.env, req.algo, req.connection, req.settings_source
    );
    if req.connection == Connection::Local && req.graph.is_none() {
        let t = cfg.run.graph_threshold;
        header += &format!("# graph: measured, eq. 7 at T = {t}: {}\n", lcrl_graph_builder::choose_t::threshold_reason(t));
    }
    if let Some(record) = &graph_record {
        header += &format!("# graph file: {}\n# graph origin: {}\n", record.file, record.origin.as_deref().unwrap_or("measured"));
    }
    let config_path = req.run_dir.join("config.toml");
    crate::run::files::write_atomically(&config_path, (header + &resolved).as_bytes())?;

    let metrics_path = req.run_dir.join("metrics.csv");
    let mut metrics = MetricsLog::create(&metrics_path, &rows)?;
    let mut tensorboard = crate::run::tensorboard::EventWriter::create(&req.run_dir).map_err(io(&req.run_dir))?;
    let mut optimization = prior_opt;
    let meta_for = |episode: usize, optimization: f64, elapsed: f64| CheckpointMeta { episode, optimization_seconds: optimization, elapsed_seconds: elapsed, ..start.clone() };

    let last_episode = req.stop_after.map_or(cfg.run.episodes, |stop| stop.min(cfg.run.episodes));
    let mut selection = Selection::new(&cfg.run, &req.run_dir, checkpoint.is_some())?;
    if let Some(selection) = selection.as_mut().filter(|s| s.due(rows.len(), last_episode)) {
        let elapsed = prior_elapsed + started.elapsed().as_secs_f64();
        selection.validate(env.as_ref(), agent.as_ref(), &req.run_dir, &meta_for(rows.len(), optimization, elapsed))?;
    }
    for episode in rows.len()..last_episode {
        let episode_started = Instant::now();
        let _span = tracing::info_span!("episode", episode = episode + 1).entered();
        agent.set_progress(episode as f64 / cfg.run.episodes as f64);
        let steps_before = agent.counters().env_steps;
        let mut state = env.reset(lcrl_sim::seeds::training(cfg.run.seed, episode))?;
        let (mut total, mut length, mut opt_seconds) = (0.0, 0, 0.0);
        loop {
            let obs = observe(env.as_ref(), &state);
            let u = agent.explore(&obs, episode);
            let (step, next_obs) = step_env(env.as_mut(), &actions, &u)?;
            if let Some(why) = lcrl_sim::diverged(env.as_ref(), &step) {
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
        optimization += opt_seconds;
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
        metrics.push(&row)?;
        let mut scalars = vec![("episode/return", row.episode_return), ("episode/length", row.length as f64), ("time/optimization_s", opt_seconds)];
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
            match write_checkpoint(&req.run_dir, agent.as_ref(), &meta_for(done, optimization, elapsed)) {
                // Diverged weights are never written; the run still ends
                // with its summary (issue 71).
                Err(crate::LearnerError::Diverged(why)) => tracing::error!(episode = done, "{why}"),
                other => {
                    other?;
                }
            }
        }
        if let Some(selection) = selection.as_mut().filter(|s| s.due(done, last_episode)) {
            let elapsed = prior_elapsed + started.elapsed().as_secs_f64();
            selection.validate(env.as_ref(), agent.as_ref(), &req.run_dir, &meta_for(done, optimization, elapsed))?;
        }
    }
    prior_opt = optimization;

    // The run's policy (the selected one, confirmed on more starts where
    // the run asks, or the last) beside the references, on the same
    // starts (crate::run::summary, as the learner does).
    if let Some(selection) = selection.as_mut() {
        selection.confirm(env.as_ref(), &req.run_dir)?;
    }
    let chosen = selection.as_ref().and_then(Selection::record);
    let last = crate::policy::snapshot::snapshot(agent.as_ref(), &start.architecture(), 0)?;
    // The last validation chose the agent as it is: that is the last policy.
    let selected = match &chosen {
        Some(c) if c.episode != rows.len() => Some(crate::policy::snapshot::read_snapshot(&selected_dir(&req.run_dir))?),
        _ => None,
    };
    let plan = EvaluationPlan {
        episodes: cfg.run.eval_episodes,
        first_seed: cfg.run.first_eval_seed(),
        local_mask: (req.connection == Connection::Local).then_some(mask.as_slice()),
        headroom: None,
    };
    let evaluation = evaluate_hand_over(env.as_ref(), selected.as_ref(), &last, &plan)?;
    let recent = &rows[rows.len().saturating_sub(10)..];
    let (actor_params, critic_params) = agent.param_counts();
    let counters = agent.counters();
    let summary = RunSummary {
        env: req.env.clone(),
        algo: req.algo,
        connection: req.connection,
        seed: cfg.run.seed,
        episodes: rows.len(),
        final_return: recent.iter().map(|r| r.episode_return).sum::<f64>() / recent.len().max(1) as f64,
        evaluation,
        selection: chosen,
        graph_seconds,
        graph: graph_record.clone(),
        optimization_seconds: prior_opt,
        total_seconds: prior_elapsed + started.elapsed().as_secs_f64(),
        env_steps: counters.env_steps,
        updates: counters.updates,
        critic_updates: counters.critic_updates,
        skipped_updates: counters.skipped_updates,
        diverged_env: counters.diverged_env,
        samples_drawn: agent.samples_drawn(),
        actor_params,
        critic_params,
        service: None,
    };
    write_summary(&req.run_dir, &summary)?;
    Ok(TrainOutcome { summary, rows })
}
