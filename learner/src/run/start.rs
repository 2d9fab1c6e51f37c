//! How a run starts, the same for `lcrl train` and the distributed learner
//! ([`prepare`]): the checkpoint to resume (checked against what the caller
//! asks for) or the new run's settings, the actor's mask, the base
//! controller written down as numbers, the compute threads, the agent and
//! its action map.

use std::path::{Path, PathBuf};

use lcrl_graph_builder::{build_graph, GraphOptions, GraphReport};
use lcrl_sim::Env;

use crate::policy::action::ActionMap;
use crate::algo::agent::Agent;
use crate::policy::checkpoint::{intact_checkpoints, latest_checkpoint, read_meta, recover_folders, CheckpointMeta};
use crate::config::{Algo, BaseController, Connection, TrainConfig};
use crate::LearnerError;

/// Where a new run's mask comes from (connection local; other connections
/// see every state).
#[derive(Debug, Clone)]
pub enum GraphSource<'a> {
    /// CS3 here, with the run's seed, samples and threshold.
    Measure,
    /// A graph.json (`--graph`).
    File(&'a Path),
    /// A mask already checked against the environment (the graph builder's).
    Mask(Vec<Vec<u8>>),
}

/// What a run asks for at its start.
#[derive(Debug, Clone)]
pub struct RunStart<'a> {
    pub env: &'a str,
    pub algo: Algo,
    pub connection: Connection,
    pub run_dir: &'a Path,
    /// A new run's settings, resolved by the one fallback rule
    /// ([`TrainConfig::load_for_env`], [`TrainConfig::for_env`]). A resumed
    /// run keeps its checkpoint's, but for the episode budget, which may
    /// grow, and the device and threads below.
    pub config: TrainConfig,
    pub graph: GraphSource<'a>,
    /// Continue the newest checkpoint of `run_dir`. Without it, a run
    /// directory that holds one is an error.
    pub resume: bool,
    /// Where and on how many threads to compute, when asked for
    /// (`--device`, `--threads`): a resumed run may change them.
    pub device: Option<String>,
    pub threads: Option<usize>,
}

/// A run ready for its first episode.
pub struct Prepared {
    /// The settings the run trains with (base controller as numbers).
    pub config: TrainConfig,
    /// The checkpoint resumed, if any.
    pub checkpoint: Option<PathBuf>,
    /// Its metadata, or a new run's (episode 0, with the graph's time).
    pub meta: CheckpointMeta,
    /// The graph built or read here for a new run (to keep as graph.json).
    pub graph: Option<GraphReport>,
    pub agent: Box<dyn Agent>,
    /// How the agent's actions become the environment's.
    pub actions: ActionMap,
    /// libtorch intra-op threads in use.
    pub threads: usize,
    /// The run directory, held by this process alone (crate::run::lock).
    pub lock: Option<crate::run::lock::RunLock>,
}

/// Starts or resumes a run in `start.run_dir` on `env`: the one start-up
/// sequence of `lcrl train` and `lcrl-learner`.
pub fn prepare(start: RunStart, env: &dyn Env) -> Result<Prepared, LearnerError> {
    std::fs::create_dir_all(start.run_dir).map_err(crate::io(start.run_dir))?;
    // Before anything in it is read or tidied: a second writer fails here.
    let lock = crate::run::lock::RunLock::acquire(start.run_dir)?;
    let mut prepared = prepare_held(start, env)?;
    prepared.lock = Some(lock);
    Ok(prepared)
}

/// [`prepare`] once the run directory is held.
fn prepare_held(start: RunStart, env: &dyn Env) -> Result<Prepared, LearnerError> {
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    // A writer killed mid-checkpoint left a staging folder (space to give
    // back) or the previous checkpoint moved aside (to put back). Should
    // that fail, the listing still takes a folder moved aside for the
    // checkpoint, so the run can go on.
    if let Err(e) = recover_folders(&start.run_dir.join("checkpoints")) {
        tracing::warn!("cannot tidy the checkpoints a killed writer left: {e}");
    }
    if !start.resume && latest_checkpoint(start.run_dir).is_some() {
        return Err(LearnerError::Mismatch(format!(
            "{} already holds a run; pass --resume to continue it or choose another --run-dir",
            start.run_dir.display()
        )));
    }
    if start.resume {
        if let Some(prepared) = resume(&start, env)? {
            return Ok(prepared);
        }
    }
    let measured_here = matches!(start.graph, GraphSource::Measure);
    let (mask, graph) = match start.graph {
        GraphSource::Mask(ref mask) if start.connection == Connection::Local => (mask.clone(), None),
        GraphSource::File(path) => resolve_mask(start.connection, Some(path), env, &start.config)?,
        _ => resolve_mask(start.connection, None, env, &start.config)?,
    };
    // Time spent building G here (none when it was given).
    let graph_seconds = graph.as_ref().filter(|_| measured_here).map_or(0.0, |r| r.elapsed_s);
    let meta = CheckpointMeta { graph_seconds, ..CheckpointMeta::start(start.env, start.algo, start.connection, m, n, mask, start.config.clone()) };
    let config = start.config.clone();
    build_agent(&start, env, config, None, meta, graph)
}

/// Resumes from the newest intact checkpoint whose agent loads; one whose
/// files are whole but whose contents cannot be loaded (a damaged replay
/// buffer consistent with its manifest) is skipped for the one before it,
/// with the reason logged (issue 71). None when there is no checkpoint.
fn resume(start: &RunStart, env: &dyn Env) -> Result<Option<Prepared>, LearnerError> {
    let mut unloadable: Vec<(PathBuf, LearnerError)> = Vec::new();
    for dir in intact_checkpoints(start.run_dir) {
        let meta = checked_meta(&dir, start.env, start.algo, start.connection)?;
        let mut config = meta.config.clone();
        config.run.episodes = start.config.run.episodes.max(meta.episode);
        match build_agent(start, env, config, Some(dir.clone()), meta, None) {
            Ok(prepared) => {
                // Set aside, so that no later resume takes them for the
                // newest (metrics.csv is cut back to this one).
                for (skipped, why) in &unloadable {
                    set_aside(skipped, why);
                }
                return Ok(Some(prepared));
            }
            Err(e @ (LearnerError::Io { .. } | LearnerError::Checkpoint(_))) => {
                tracing::warn!(checkpoint = %dir.display(), "cannot load this checkpoint ({e}); trying the one before it");
                unloadable.push((dir, e));
            }
            Err(e) => return Err(e),
        }
    }
    // None loads: the newest one's reason (never a fresh start over them).
    match unloadable.into_iter().next() {
        Some((_, why)) => Err(why),
        None => Ok(None),
    }
}

/// Renames an unloadable checkpoint folder to `.NAME.unloadable` beside
/// it: kept for a post-mortem, never listed again.
fn set_aside(dir: &Path, why: &LearnerError) {
    let Some(name) = dir.file_name().map(|n| n.to_string_lossy().into_owned()) else { return };
    let aside = dir.with_file_name(format!(".{name}.unloadable"));
    match std::fs::rename(dir, &aside) {
        Ok(()) => tracing::warn!(checkpoint = %dir.display(), "set aside as {} ({why})", aside.display()),
        Err(e) => tracing::warn!(checkpoint = %dir.display(), "cannot set it aside: {e}"),
    }
}

/// The rest of the start-up: the device, threads and base controller, and
/// the agent (loaded from `checkpoint` when resuming).
fn build_agent(start: &RunStart, env: &dyn Env, mut config: TrainConfig, checkpoint: Option<PathBuf>, mut meta: CheckpointMeta, graph: Option<GraphReport>) -> Result<Prepared, LearnerError> {
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    if let Some(device) = start.device.clone() {
        config.run.device = device;
    }
    if let Some(threads) = start.threads {
        config.run.threads = threads;
    }
    config.validate()?;
    // The base controller as numbers, so config.toml and every checkpoint
    // record exactly what the agent acts around.
    let base = fix_base_controller(&mut config, env)?;
    let actions = ActionMap::new(env.spec(), base.as_deref())?.with_residual_scale(config.residual_scale(start.algo));
    meta.config = config.clone();
    let threads = crate::device::torch::apply_threads(config.run.threads, 0);
    let mut agent = crate::algo::algorithms::make_agent(start.algo, start.connection, &config, &meta.shape.mask, m, n)?;
    if let Some(dir) = &checkpoint {
        agent.load(dir)?;
    }
    Ok(Prepared { config, checkpoint, meta, graph, agent, actions, threads, lock: None })
}

/// The newest intact checkpoint in `run_dir` with its metadata, if there
/// is one (damaged ones are skipped and logged: [`latest_checkpoint`]).
/// A checkpoint of another environment, algorithm or connection is an
/// error: resuming it as this run would mix two runs.
pub fn checkpoint_to_resume(run_dir: &Path, env: &str, algo: Algo, connection: Connection) -> Result<Option<(PathBuf, CheckpointMeta)>, LearnerError> {
    let Some(dir) = latest_checkpoint(run_dir) else { return Ok(None) };
    let meta = checked_meta(&dir, env, algo, connection)?;
    Ok(Some((dir, meta)))
}

/// A checkpoint's metadata, checked to be a run of this environment,
/// algorithm and connection. Two served environments (grpc://) count as
/// the same: a server started for the run (`[env_server]`) listens on
/// another port each time.
fn checked_meta(dir: &Path, env: &str, algo: Algo, connection: Connection) -> Result<CheckpointMeta, LearnerError> {
    let meta = read_meta(dir)?;
    let same_env = meta.shape.env == env || (lcrl_sim::remote::is_served(&meta.shape.env) && lcrl_sim::remote::is_served(env));
    if !same_env || meta.shape.algo != algo || meta.shape.connection != connection {
        return Err(LearnerError::Mismatch(format!(
            "{} holds a run of {} with {:?}/{:?}; continue it with the same --env, --algo and --connection, or choose another --run-dir",
            dir.display(),
            meta.shape.env,
            meta.shape.algo,
            meta.shape.connection
        )));
    }
    Ok(meta)
}

/// Replaces `config`'s base controller by the numbers it stands for
/// ("best-constant" becomes the constant itself), so config.toml and every
/// checkpoint record exactly what the agent acts around. Returns them.
pub fn fix_base_controller(config: &mut TrainConfig, env: &dyn Env) -> Result<Option<Vec<f64>>, LearnerError> {
    let base = crate::policy::action::resolve_base(&config.base, env.spec())?;
    config.base.action = base.clone().map_or(BaseController::None, BaseController::Action);
    config.base.best_constant_file = None;
    Ok(base)
}

/// The actor's mask (n × m): ones for a global actor; for a local one, G
/// from `graph` (a graph.json) or built here with CS3 (Algorithm 1, with
/// the run's seed, `run.graph_samples` and eq. 7 at `run.graph_threshold`),
/// returned with its report.
pub fn resolve_mask(connection: Connection, graph: Option<&Path>, env: &dyn Env, config: &TrainConfig) -> Result<(Vec<Vec<u8>>, Option<GraphReport>), LearnerError> {
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    if connection != Connection::Local {
        return Ok((vec![vec![1; m]; n], None));
    }
    let report = match graph {
        // The one loader of graph files (lcrl_graph_builder::given): shape,
        // 0/1, this environment's names in its order. A measured graph may
        // leave an action without an edge (its subnetwork learns a constant).
        Some(path) => lcrl_graph_builder::given::load_measured_for(path, env.spec())?,
        None => {
            let options = GraphOptions {
                rule: lcrl_graph_builder::Rule::Threshold(config.run.graph_threshold),
                ..GraphOptions::paper(config.run.graph_samples, config.run.seed, lcrl_graph_builder::DEFAULT_BOOTSTRAP)
            };
            build_graph(env, &options, &|| {})?
        }
    };
    Ok((report.g.clone(), Some(report)))
}

// A run's start on the single-process loop: a resume continues exactly,
// past a checkpoint that cannot load, and a run directory or graph that
// does not fit is refused.
#[cfg(test)]
mod tests {
    use lcrl_sim::make_env;

    use crate::config::test_config::{tiny, tiny_with_episodes};
    use crate::config::{Algo, Connection};
    use crate::run::test_run::{run, run_until, timeless};
    use crate::run::trainer::{train, TrainRequest};

    /// 4 episodes straight, or interrupted after 2 then --resume: the same rows,
    /// counters and final policy (one thread, same seed). DDPG also with twin
    /// critics and annealed learning rates, whose second critic, its optimizer
    /// and the schedules must come back from the checkpoint as well.
    #[test]
    fn resumed_run_continues_exactly() {
        let mut td3 = tiny();
        td3.ddpg.twin_critics = true;
        td3.ddpg.anneal_lr = true;
        for (algo, cfg) in [(Algo::Ddpg, tiny()), (Algo::Ddpg, td3), (Algo::Ppo, tiny())] {
            let straight_dir = tempfile::tempdir().unwrap();
            let straight = run(algo, Connection::Local, cfg.clone(), straight_dir.path(), false);
            let resumed_dir = tempfile::tempdir().unwrap();
            run_until(algo, Connection::Local, cfg.clone(), resumed_dir.path(), false, Some(2));
            if cfg.ddpg.twin_critics {
                assert!(crate::policy::checkpoint::latest_checkpoint(resumed_dir.path()).unwrap().join("critic2.safetensors").is_file());
            }
            let resumed = run(algo, Connection::Local, cfg, resumed_dir.path(), true);
            assert_eq!(timeless(&straight.rows), timeless(&resumed.rows), "{algo:?}");
            assert_eq!((straight.summary.env_steps, straight.summary.updates), (resumed.summary.env_steps, resumed.summary.updates));
            assert_eq!(straight.summary.evaluation.eval_return, resumed.summary.evaluation.eval_return, "{algo:?}: final policies differ");
        }
    }

    /// A replay buffer damaged so that its file still matches the manifest
    /// (a tensor renamed in place: same size, valid header) cannot be loaded:
    /// the resume falls back to the checkpoint before it, instead of stopping
    /// (issue 71).
    #[test]
    fn a_resume_falls_back_past_a_checkpoint_whose_replay_cannot_load() {
        let dir = tempfile::tempdir().unwrap();
        run_until(Algo::Ddpg, Connection::Global, tiny(), dir.path(), false, Some(4));
        let newest = crate::policy::checkpoint::latest_checkpoint(dir.path()).unwrap();
        assert!(newest.ends_with("ep000004"), "{}", newest.display());
        let replay = newest.join("replay.safetensors");
        let bytes = std::fs::read(&replay).unwrap();
        let at = bytes.windows(9).position(|w| w == b"\"next_obs").expect("the header names next_obs");
        let mut damaged = bytes.clone();
        damaged[at + 1..at + 9].copy_from_slice(b"next_obz");
        std::fs::write(&replay, &damaged).unwrap();
        crate::policy::checkpoint::check_intact(&newest).expect("still consistent with its manifest");
        let resumed = run_until(Algo::Ddpg, Connection::Global, tiny_with_episodes(6), dir.path(), true, None);
        // Episodes 3 and 4 trained again from ep000002, then 5 and 6; the
        // unloadable one was set aside, never to be taken for the newest.
        assert_eq!(resumed.rows.len(), 6);
        assert_eq!(resumed.summary.episodes, 6);
        assert!(dir.path().join("checkpoints/.ep000004.unloadable").is_dir());
    }

    #[test]
    fn refuses_to_overwrite_a_run_and_rejects_mismatched_graphs() {
        let dir = tempfile::tempdir().unwrap();
        run(Algo::Ddpg, Connection::Global, tiny(), dir.path(), false);
        let request = TrainRequest {
            env: "lti-paper".into(),
            algo: Algo::Ddpg,
            connection: Connection::Global,
            graph: None,
            config: tiny(),
            settings_source: "test".into(),
            run_dir: dir.path().into(),
            resume: false,
            stop_after: None,
        };
        let err = train(&request, &mut |_| {}).err().unwrap().to_string();
        assert!(err.contains("--resume"), "{err}");
        let resume_other = TrainRequest { algo: Algo::Ppo, resume: true, ..request.clone() };
        assert!(train(&resume_other, &mut |_| {}).err().unwrap().to_string().contains("same --env, --algo"));

        // A graph built for lti-paper (3×3) does not fit peg-group1 (6×12).
        let graph = dir.path().join("graph.json");
        let options = lcrl_graph_builder::GraphOptions {
            cs3: lcrl_graph_builder::Cs3Config { samples: 8, seed: 0, threads: 1, start: None },
            rule: lcrl_graph_builder::Rule::Threshold(0.1),
            bootstrap: 0,
        };
        let env = make_env("lti-paper").unwrap();
        lcrl_graph_builder::build_graph(env.as_ref(), &options, &|| {}).unwrap().write_json(&graph).unwrap();
        let peg = TrainRequest {
            env: "peg-group1".into(),
            connection: Connection::Local,
            graph: Some(graph),
            run_dir: dir.path().join("peg"),
            ..request
        };
        let err = train(&peg, &mut |_| {}).err().unwrap().to_string();
        assert!(err.contains("3×3") && err.contains("6 actions"), "{err}");
    }
}
