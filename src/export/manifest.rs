//! policy.json: what an exported policy file computes, on what, and where
//! it came from. A controller reads the names, units and bounds from it;
//! a person reads which run and checkpoint the file is.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use lcrl_learner::config::{Algo, Connection, NetworkConfig};
use lcrl_sim::Env;
use serde::{Deserialize, Serialize};

/// Bumped when a field changes meaning.
pub const FORMAT_VERSION: u32 = 1;

/// The whole file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub format_version: u32,
    pub lcrl_version: String,
    /// What the module computes, in one line.
    pub computes: String,
    /// The input and output tensors, for TorchScript and ONNX alike.
    pub input: TensorInfo,
    pub output: TensorInfo,
    pub env: String,
    pub state: Vec<StateComponent>,
    pub action: Vec<ActionComponent>,
    pub graph: GraphInfo,
    pub algo: Algo,
    pub network: NetworkConfig,
    /// `[base] residual_scale` (or DDPG's own): the share of each
    /// half-width of the box the policy may move the action from its base.
    pub residual_scale: f64,
    pub source: Source,
    /// The files written of this policy, by format ("torchscript",
    /// "onnx"), each with its check against the served policy.
    pub files: BTreeMap<String, FileEntry>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TensorInfo {
    /// The ONNX name (TorchScript takes it positionally).
    pub name: String,
    pub shape: Vec<serde_json::Value>,
    pub dtype: String,
    pub meaning: String,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StateComponent {
    pub name: String,
    /// None where the environment does not say (a served environment).
    pub unit: Option<String>,
    /// The policy sees state / scale.
    pub scale: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ActionComponent {
    pub name: String,
    pub unit: Option<String>,
    pub low: f64,
    pub high: f64,
    /// The action at u = 0: the base controller, or the box's centre.
    pub centre: f64,
    /// How far u = ±1 moves the action from `centre` (before the box clips).
    pub reach: f64,
    /// The base controller's component, when the policy acts around one.
    pub base: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct GraphInfo {
    pub connection: Connection,
    /// G as n rows of m 0/1 (all ones for global and full-subnets).
    pub mask: Vec<Vec<u8>>,
    /// Per action, the states its subnetwork sees (local connection).
    pub inputs: Vec<ActionInputs>,
    pub edges: usize,
    /// Where the run's graph came from (its graph.json `origin`), if it says.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub origin: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub threshold: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ActionInputs {
    pub action: String,
    pub states: Vec<String>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Source {
    /// The run directory, when the policy came from one.
    pub run: Option<PathBuf>,
    /// The policy folder read (RUN/selected, RUN/checkpoints/epNNNNNN, …).
    pub checkpoint: PathBuf,
    /// Why this folder: "selected", "newest checkpoint" or "given".
    pub chosen: String,
    /// Training episodes behind the policy.
    pub episode: usize,
    /// The policy version a distributed learner published it as (0 for
    /// `lcrl train`'s runs).
    pub policy_version: u64,
    /// The actor's gradient steps behind the policy, from the folder's
    /// agent.json (absent in folders without one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub updates: Option<u64>,
    /// For a selected policy: how selection chose it (its selection.json).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub selection: Option<serde_json::Value>,
}

/// One written file and how it was checked: the largest difference
/// between its actions and the policy's as the learner serves it
/// (`Policy::act`, what `Policy.Act` answers) on the probe states the
/// command drew, in action units.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FileEntry {
    /// The file's name, beside policy.json.
    pub file: String,
    pub bytes: u64,
    pub checked_states: usize,
    pub max_abs_difference: f64,
}

/// The units of the state and action components, where lcrl knows them:
/// the peg tasks' (docs/method.md §6, sim/src/peg/mod.rs) and the linear
/// systems' (dimensionless); None for a served environment.
pub fn units(env: &dyn Env) -> (Vec<Option<String>>, Vec<Option<String>>) {
    let spec = env.spec();
    let (m, n) = (spec.state_dim(), spec.action_dim());
    let all = |k: usize, unit: Option<&str>| vec![unit.map(str::to_string); k];
    if env.as_any().is::<lcrl_sim::peg::PegEnv>() {
        let state = ["mm", "mm", "mm", "deg", "deg", "deg", "N", "N", "N", "N·m", "N·m", "N·m"];
        if state.len() == m {
            return (state.iter().map(|u| Some(u.to_string())).collect(), all(n, Some("1 (revision factor of the compliance, eq. 20)")));
        }
    }
    if env.as_any().is::<lcrl_sim::lti::LtiEnv>() {
        return (all(m, Some("1")), all(n, Some("1")));
    }
    (all(m, None), all(n, None))
}

/// `graph.json` of the run, where it says where the graph came from.
pub fn graph_origin(run: Option<&Path>) -> (Option<String>, Option<f64>) {
    let Some(text) = run.and_then(|dir| std::fs::read_to_string(dir.join("graph.json")).ok()) else {
        return (None, None);
    };
    let Ok(value) = serde_json::from_str::<serde_json::Value>(&text) else {
        return (None, None);
    };
    (value.get("origin").and_then(|o| o.as_str()).map(str::to_string), value.get("threshold").and_then(serde_json::Value::as_f64))
}
