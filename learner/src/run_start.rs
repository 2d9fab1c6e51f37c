//! How a run starts, the same for `lcrl train` and the distributed learner:
//! the checkpoint to resume (checked against what the caller asks for), the
//! base controller written down as numbers, and the actor's mask.

use std::path::{Path, PathBuf};

use lcrl_graph_builder::{build_graph, GraphOptions, GraphReport};
use lcrl_sim::Env;

use crate::checkpoint::{latest_checkpoint, read_meta, CheckpointMeta};
use crate::config::{Algo, BaseController, Connection, TrainConfig};
use crate::LearnerError;

/// The newest checkpoint in `run_dir` with its metadata, if there is one.
/// A checkpoint of another environment, algorithm or connection is an
/// error: resuming it as this run would mix two runs.
pub fn checkpoint_to_resume(run_dir: &Path, env: &str, algo: Algo, connection: Connection) -> Result<Option<(PathBuf, CheckpointMeta)>, LearnerError> {
    let Some(dir) = latest_checkpoint(run_dir) else { return Ok(None) };
    let meta = read_meta(&dir)?;
    if meta.shape.env != env || meta.shape.algo != algo || meta.shape.connection != connection {
        return Err(LearnerError::Mismatch(format!(
            "{} holds a run of {} with {:?}/{:?}; continue it with the same --env, --algo and --connection, or choose another --run-dir",
            dir.display(),
            meta.shape.env,
            meta.shape.algo,
            meta.shape.connection
        )));
    }
    Ok(Some((dir, meta)))
}

/// Replaces `config`'s base controller by the numbers it stands for
/// ("best-constant" becomes the constant itself), so config.toml and every
/// checkpoint record exactly what the agent acts around. Returns them.
pub fn fix_base_controller(config: &mut TrainConfig, env: &dyn Env) -> Result<Option<Vec<f64>>, LearnerError> {
    let base = crate::action::resolve_base(&config.base, env.spec())?;
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
        // 0/1, this environment's names in its order, an edge per action.
        Some(path) => lcrl_graph_builder::given::load_for(path, env.spec())?,
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
