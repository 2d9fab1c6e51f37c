//! A prepared policy written to a file and checked: what the TorchScript
//! and the ONNX writers share. The file's actions on the probe states
//! must be the served policy's within [`TOLERANCE`].

use std::path::Path;

use anyhow::{bail, Context};
use tch::{Kind, Tensor};

use super::manifest::{FileEntry, Manifest};
use super::model::Pipeline;

/// The largest difference between a written file's actions and the served
/// policy's that the command accepts (action units). The arithmetic is the
/// same but for ELU, which a served CPU policy computes with lcrl's kernel
/// and the file with libtorch's op (values within 1.2e-7,
/// learner/src/algo/elu.rs), so real differences are that and rounding of
/// a different batch size.
pub const TOLERANCE: f64 = 1e-5;

/// A policy ready to be written: the pipeline to trace, policy.json
/// without its files, and probe states (rows of f32) with the served
/// policy's actions on them (`Policy::act`, what `Policy.Act` answers).
pub struct Prepared {
    pub pipeline: Pipeline,
    pub manifest: Manifest,
    pub state_dim: usize,
    pub action_dim: usize,
    pub probes: Vec<f32>,
    pub served: Vec<f32>,
}

/// The largest |a − b| over two action lists: infinite where their
/// lengths differ or a value is not finite (a NaN is never "close").
pub fn max_difference(a: &[f32], b: &[f32]) -> f64 {
    if a.len() != b.len() {
        return f64::INFINITY;
    }
    a.iter()
        .zip(b)
        .map(|(x, y)| if x.is_finite() && y.is_finite() { (f64::from(*x) - f64::from(*y)).abs() } else { f64::INFINITY })
        .fold(0.0, f64::max)
}

/// Traces the pipeline and writes it beside `path`, loads the written
/// file back, and moves it to `path` once it acts as the served policy.
pub fn write_torchscript(prepared: &Prepared, path: &Path) -> anyhow::Result<FileEntry> {
    let m = prepared.state_dim;
    // The trace's example: a few probe rows (no size is recorded in it).
    let rows = (prepared.probes.len() / m).min(4);
    let example = Tensor::from_slice(&prepared.probes[..rows * m]).view([rows as i64, m as i64]);
    let module = prepared.pipeline.trace(&example)?;
    let partial = partial_of(path)?;
    module.save(&partial).with_context(|| format!("writing {}", partial.display()))?;
    let actions = tch::CModule::load(&partial)
        .with_context(|| format!("loading the written {} back", partial.display()))
        .and_then(|written| run_module(&written, &prepared.probes, m));
    match actions {
        Ok(actions) => install(&partial, path, prepared, &actions),
        Err(e) => {
            let _ = std::fs::remove_file(&partial);
            Err(e)
        }
    }
}

/// A TorchScript module's actions on rows of f32 states.
pub fn run_module(module: &tch::CModule, states: &[f32], m: usize) -> anyhow::Result<Vec<f32>> {
    let input = Tensor::from_slice(states).view([-1, m as i64]);
    let out = tch::no_grad(|| module.forward_ts(&[input])).context("running the exported module")?;
    Ok(Vec::<f32>::try_from(out.to_kind(Kind::Float).flatten(0, -1))?)
}

/// Moves the written `partial` to `path` once its actions on the probe
/// states are within [`TOLERANCE`] of the served policy's, and returns
/// its entry in policy.json; removes it otherwise (a file already at
/// `path` stays as it was).
pub fn install(partial: &Path, path: &Path, prepared: &Prepared, actions: &[f32]) -> anyhow::Result<FileEntry> {
    let states = prepared.served.len() / prepared.action_dim.max(1);
    let difference = max_difference(actions, &prepared.served);
    if difference > TOLERANCE {
        let _ = std::fs::remove_file(partial);
        bail!(
            "the file for {} acts differently from the served policy (largest difference {difference:e} on {states} probe states, tolerance {TOLERANCE:e}); it is not the policy and was not written: please report this",
            path.display()
        );
    }
    std::fs::rename(partial, path).with_context(|| format!("moving {} to {}", partial.display(), path.display()))?;
    Ok(FileEntry {
        file: path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
        bytes: std::fs::metadata(path).map(|m| m.len()).unwrap_or(0),
        checked_states: states,
        max_abs_difference: difference,
    })
}

/// Where a file is written before it is checked: beside `path`, hidden.
pub fn partial_of(path: &Path) -> anyhow::Result<std::path::PathBuf> {
    let dir = lcrl_runtime::files::folder_of(path);
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    Ok(dir.join(format!(".{}.{}.partial", path.file_name().map(|n| n.to_string_lossy()).unwrap_or_default(), std::process::id())))
}
