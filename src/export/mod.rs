//! `lcrl export`: a trained policy as one file that a robot controller
//! loads with a standard runtime (libtorch's TorchScript, or ONNX
//! Runtime), with no lcrl process, no network hop and no Rust toolchain.
//! The file holds the whole path from the raw state the environment
//! reports to the action the controller applies (model.rs); policy.json
//! beside it says what it computes, on what, and where it came from
//! (manifest.rs). Every file is checked, before the command reports
//! success, against the policy as the learner serves it on probe states.
//! docs/export.md.

pub mod file;
pub mod manifest;
pub mod model;
pub mod onnx;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use lcrl_learner::config::Connection;
use lcrl_learner::policy::checkpoint::{latest_checkpoint, read_meta, selected_dir};
use lcrl_learner::policy::trained::Policy;
use lcrl_sim::Env;

pub use file::{max_difference, run_module, write_torchscript, Prepared, TOLERANCE};
use manifest::{ActionComponent, ActionInputs, FileEntry, GraphInfo, Manifest, Source, StateComponent, TensorInfo};
use model::Pipeline;

/// The file formats `lcrl export` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// TorchScript (libtorch: `torch.jit.load`, `torch::jit::load`).
    Torchscript,
    /// ONNX (ONNX Runtime), converted from the TorchScript module by
    /// PyTorch's exporter in the project's Python.
    Onnx,
}

impl Format {
    pub fn key(self) -> &'static str {
        match self {
            Format::Torchscript => "torchscript",
            Format::Onnx => "onnx",
        }
    }
}

/// What to export and where.
#[derive(Debug, Clone)]
pub struct Request {
    /// A run directory (or a policy folder itself).
    pub run: PathBuf,
    /// Another policy than the run's: `epNNNNNN` (under RUN/checkpoints),
    /// `newest`, or a folder holding a checkpoint.json.
    pub checkpoint: Option<String>,
    /// The environment, where the policy's own name no longer builds it.
    pub env: Option<String>,
    pub out: PathBuf,
    pub format: Format,
}

/// What the command wrote.
#[derive(Debug, Clone)]
pub struct Outcome {
    pub file: PathBuf,
    pub manifest_path: PathBuf,
    pub manifest: Manifest,
    pub entry: FileEntry,
}

/// Exports one file and policy.json beside it.
pub fn export(request: &Request) -> anyhow::Result<Outcome> {
    let manifest_path = manifest_path(&request.out)?;
    // Every product here is one row or a few hundred: on more threads
    // libtorch only synchronizes (15× slower on 2 busy cores). The file
    // carries no thread setting; its caller chooses its own.
    tch::set_num_threads(1);
    let prepared = prepare(request)?;
    let entry = match request.format {
        Format::Torchscript => write_torchscript(&prepared, &request.out)?,
        Format::Onnx => onnx::write(&prepared, &request.out)?,
    };
    let manifest = write_manifest(&manifest_path, &prepared.manifest, request.format, &entry)?;
    Ok(Outcome { file: request.out.clone(), manifest_path, manifest, entry })
}

/// policy.json's path: the output's name with `.json`, beside it.
pub fn manifest_path(out: &Path) -> anyhow::Result<PathBuf> {
    if out.extension().is_some_and(|e| e == "json") || out.file_name().is_none() {
        bail!("--out {} must name the policy file (policy.pt, policy.onnx); policy.json is written beside it", out.display());
    }
    Ok(out.with_extension("json"))
}

/// The policy folder `request` means, the run it belongs to, and why.
fn locate(run: &Path, checkpoint: Option<&str>) -> anyhow::Result<(PathBuf, Option<PathBuf>, String)> {
    let is_policy = |dir: &Path| dir.join("checkpoint.json").is_file();
    let run_of = |folder: &Path| -> Option<PathBuf> {
        let parent = folder.parent()?;
        match parent.file_name()?.to_str()? {
            "checkpoints" | "candidates" => parent.parent().map(Path::to_path_buf),
            _ if folder.file_name().is_some_and(|n| n == "selected") => Some(parent.to_path_buf()),
            _ => None,
        }
    };
    if !run.is_dir() {
        bail!("{} is not a folder: name a run directory (runs/peg-group1) or a policy folder (RUN/checkpoints/epNNNNNN)", run.display());
    }
    // `lcrl run` keeps its learner's records, policies included, in
    // RUN/learner/.
    let learner = run.join("learner");
    let has_policies = |dir: &Path| is_policy(dir) || is_policy(&selected_dir(dir)) || dir.join("checkpoints").is_dir();
    if !has_policies(run) && has_policies(&learner) {
        return locate(&learner, checkpoint);
    }
    match checkpoint {
        None if is_policy(run) => Ok((run.to_path_buf(), run_of(run), "given".into())),
        None if is_policy(&selected_dir(run)) => Ok((selected_dir(run), Some(run.to_path_buf()), "selected".into())),
        None => match latest_checkpoint(run) {
            Some(dir) => Ok((dir, Some(run.to_path_buf()), "newest checkpoint (the run has no selected policy)".into())),
            None => bail!(
                "{} holds no policy: neither RUN/selected/ nor RUN/checkpoints/epNNNNNN/ with a checkpoint.json; name the run directory of `lcrl train` or `lcrl run`",
                run.display()
            ),
        },
        Some("newest") => match latest_checkpoint(run) {
            Some(dir) => Ok((dir, Some(run.to_path_buf()), "newest checkpoint".into())),
            None => bail!("{} has no intact checkpoint under checkpoints/", run.display()),
        },
        Some(name) => {
            let candidates = [PathBuf::from(name), run.join("checkpoints").join(name), run.join(name)];
            match candidates.iter().find(|dir| is_policy(dir)) {
                Some(dir) => Ok((dir.clone(), run_of(dir).or_else(|| Some(run.to_path_buf())), "given".into())),
                None => {
                    let names: Vec<String> = std::fs::read_dir(run.join("checkpoints"))
                        .map(|entries| entries.flatten().filter(|e| is_policy(&e.path())).map(|e| e.file_name().to_string_lossy().into_owned()).collect())
                        .unwrap_or_default();
                    bail!(
                        "--checkpoint {name}: no checkpoint.json there, under {}/checkpoints/ or in {}; name one of [{}], `newest`, or a policy folder",
                        run.display(),
                        run.display(),
                        names.join(", ")
                    )
                }
            }
        }
    }
}

/// Loads the policy, builds its environment and pipeline, and draws the
/// probe states.
pub fn prepare(request: &Request) -> anyhow::Result<Prepared> {
    let (folder, run, chosen) = locate(&request.run, request.checkpoint.as_deref())?;
    let meta_path = folder.join("checkpoint.json");
    let meta_text = std::fs::read_to_string(&meta_path).with_context(|| format!("reading {}", meta_path.display()))?;
    let weights_path = folder.join("actor.safetensors");
    let weights = std::fs::read(&weights_path).with_context(|| format!("reading {}", weights_path.display()))?;
    // The reference: the policy as `lcrl sim` and the learner load it,
    // checked (architecture, every weight's name, shape and finiteness).
    let policy = Policy::from_checkpoint(&meta_text, &weights).with_context(|| format!("loading the policy in {}", folder.display()))?;
    let meta = read_meta(&folder)?;
    let architecture = policy.architecture.clone();
    let env_name = crate::recorded_env::environment_to_build(&architecture.shape.env, request.env.as_deref(), &folder)?;
    let env = lcrl_sim::make_env(&env_name).with_context(|| {
        format!("building {env_name}, the environment the policy acts on (pass --env to name it another way: a TOML file's new path, a served environment's address)")
    })?;
    policy.check_env(env.as_ref())?;
    let pipeline = Pipeline::new(&architecture, &weights, env.as_ref())?;
    let (m, n) = (architecture.shape.state_dim, architecture.shape.action_dim);
    let probes = probe_states(env.as_ref(), &policy, &pipeline.scale)?;
    let served: Vec<f32> = probes.chunks(m).flat_map(|row| policy.act(env.as_ref(), &row.iter().map(|&v| f64::from(v)).collect::<Vec<_>>())).map(|a| a as f32).collect();
    let selection = (chosen == "selected")
        .then(|| std::fs::read_to_string(folder.join("selection.json")).ok().and_then(|t| serde_json::from_str(&t).ok()))
        .flatten();
    let updates = actor_updates(&folder);
    let source = Source {
        run: run.map(|r| std::fs::canonicalize(&r).unwrap_or(r)),
        checkpoint: std::fs::canonicalize(&folder).unwrap_or(folder),
        chosen,
        episode: meta.episode,
        policy_version: meta.policy_version,
        updates,
        selection,
    };
    let manifest = describe(env.as_ref(), &architecture, &pipeline, source);
    Ok(Prepared { pipeline, manifest, state_dim: m, action_dim: n, probes, served })
}

/// The actor's gradient steps a checkpoint folder's agent.json records.
fn actor_updates(folder: &std::path::Path) -> Option<u64> {
    let text = std::fs::read_to_string(folder.join("agent.json")).ok()?;
    serde_json::from_str::<serde_json::Value>(&text).ok()?["counters"]["updates"].as_u64()
}

/// policy.json's content, without its files.
fn describe(env: &dyn Env, architecture: &lcrl_learner::policy::architecture::Architecture, pipeline: &Pipeline, source: Source) -> Manifest {
    let spec = env.spec();
    let (state_units, action_units) = manifest::units(env);
    let shape = &architecture.shape;
    let mask = match shape.connection {
        Connection::Local => shape.mask.clone(),
        _ => vec![vec![1; shape.state_dim]; shape.action_dim],
    };
    let inputs = mask
        .iter()
        .zip(&spec.action_names)
        .map(|(row, action)| ActionInputs {
            action: action.clone(),
            states: row.iter().zip(&spec.state_names).filter(|(g, _)| **g == 1).map(|(_, s)| s.clone()).collect(),
        })
        .collect();
    let (origin, threshold) = manifest::graph_origin(source.run.as_deref());
    let batch = serde_json::Value::from("batch");
    Manifest {
        format: "lcrl-policy".into(),
        format_version: manifest::FORMAT_VERSION,
        lcrl_version: env!("CARGO_PKG_VERSION").into(),
        computes: "action = clip(centre + reach * clip(actor(state / scale), -1, 1), low, high): normalization and action map in float64, the actor in float32".into(),
        input: TensorInfo {
            name: "state".into(),
            shape: vec![batch.clone(), shape.state_dim.into()],
            dtype: "float32".into(),
            meaning: "raw states as the environment reports them, one row per state, in the order and units of `state`".into(),
        },
        output: TensorInfo {
            name: "action".into(),
            shape: vec![batch, shape.action_dim.into()],
            dtype: "float32".into(),
            meaning: "the actions to apply, within [low, high], in the order of `action`".into(),
        },
        env: spec.name.clone(),
        state: spec
            .state_names
            .iter()
            .zip(state_units)
            .zip(&pipeline.scale)
            .map(|((name, unit), &scale)| StateComponent { name: name.clone(), unit, scale })
            .collect(),
        action: (0..spec.action_dim())
            .map(|i| ActionComponent {
                name: spec.action_names[i].clone(),
                unit: action_units[i].clone(),
                low: pipeline.low[i],
                high: pipeline.high[i],
                centre: pipeline.centre[i],
                reach: pipeline.reach[i],
                base: architecture.base.as_ref().map(|b| b[i]),
            })
            .collect(),
        graph: GraphInfo { connection: shape.connection, edges: mask.iter().flatten().filter(|&&g| g == 1).count(), mask, inputs, origin, threshold },
        algo: shape.algo,
        network: architecture.network.clone(),
        residual_scale: architecture.residual_scale,
        source,
        files: BTreeMap::new(),
    }
}

/// States to check a file on, rounded to f32 as a caller's would be:
/// the states of a few episodes of the policy itself, and states drawn
/// far around them (up to three times each component's scale, where the
/// policy's actions saturate and the box clips).
fn probe_states(env: &dyn Env, policy: &Policy, scale: &[f64]) -> anyhow::Result<Vec<f32>> {
    let mut rows: Vec<Vec<f64>> = Vec::new();
    let mut episode = env.fresh();
    for seed in 0..4u64 {
        let mut state = episode.reset(seed).context("resetting the environment for probe states")?;
        for _ in 0..60 {
            rows.push(state.clone());
            let step = episode.step(&policy.act(env, &state)).context("stepping the environment for probe states")?;
            if step.terminated || step.truncated {
                break;
            }
            state = step.state;
        }
    }
    let mut x: u64 = 0x2545_F491_4F6C_DD1D;
    let mut uniform = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    for _ in 0..256 {
        rows.push(scale.iter().map(|s| (uniform() * 6.0 - 3.0) * s).collect());
    }
    Ok(rows.iter().flatten().map(|&v| v as f32).collect())
}

/// Writes policy.json with `entry` under `format`, keeping the entries of
/// other formats already there when they are files of the same policy.
fn write_manifest(path: &Path, manifest: &Manifest, format: Format, entry: &FileEntry) -> anyhow::Result<Manifest> {
    let mut manifest = manifest.clone();
    if let Some(existing) = std::fs::read_to_string(path).ok().and_then(|t| serde_json::from_str::<Manifest>(&t).ok()) {
        let same = existing.source.checkpoint == manifest.source.checkpoint
            && existing.source.episode == manifest.source.episode
            && existing.source.policy_version == manifest.source.policy_version;
        if same {
            manifest.files = existing.files.into_iter().filter(|(_, e)| path.with_file_name(&e.file).is_file()).collect();
        }
    }
    manifest.files.insert(format.key().into(), entry.clone());
    let text = serde_json::to_string_pretty(&manifest)?;
    lcrl_runtime::files::write_atomically(path, format!("{text}\n").as_bytes()).with_context(|| format!("writing {}", path.display()))?;
    Ok(manifest)
}

#[cfg(test)]
mod tests;
