//! The checkpoint store of a run directory: `checkpoints/epNNNNNN/`, each
//! the agent's tensors (weights, optimizer state, replay) beside
//! `checkpoint.json` (this [`CheckpointMeta`] and a manifest of the files),
//! written atomically and durably ([`write_folder`]), the newest
//! [`KEEP_CHECKPOINTS`] kept. A checkpoint whose weights are not all
//! finite is never written, and never counts as intact. Resume takes the newest intact one
//! ([`latest_checkpoint`]). `lcrl train` and the distributed
//! learner both write and resume from it.

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use lcrl_runtime::files::{folder_of, sync_dir, sync_file};
use serde::{Deserialize, Serialize};

use crate::algo::agent::Agent;
use crate::config::{Algo, Connection, TrainConfig};
use crate::policy::architecture::{ActorShape, Architecture};
use crate::{io, LearnerError};


/// Written next to the tensors of every checkpoint.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointMeta {
    /// Episodes completed when the checkpoint was written.
    pub episode: usize,
    #[serde(flatten)]
    pub shape: ActorShape,
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
    pub rate_limiter: Option<crate::algo::rate_limiter::RateLimiter>,
}

impl CheckpointMeta {
    /// The metadata of a run at its start (episode 0, nothing timed, no
    /// distributed state): what every writer fills in from.
    #[allow(clippy::too_many_arguments)]
    // args: the ActorShape it builds, field by field, and the config; its callers (service/ among them) hold the fields, not a shape
    pub fn start(env: &str, algo: Algo, connection: Connection, state_dim: usize, action_dim: usize, mask: Vec<Vec<u8>>, config: TrainConfig) -> Self {
        CheckpointMeta {
            episode: 0,
            shape: ActorShape { env: env.to_string(), algo, connection, state_dim, action_dim, mask },
            config,
            graph_seconds: 0.0,
            optimization_seconds: 0.0,
            elapsed_seconds: 0.0,
            policy_version: 0,
            actor_sequences: Default::default(),
            rate_limiter: None,
        }
    }

    /// The actor's architecture, as a published policy describes it.
    pub fn architecture(&self) -> Architecture {
        Architecture {
            shape: self.shape.clone(),
            network: self.config.network.clone(),
            base: self.config.base.base_action(self.shape.action_dim),
            residual_scale: self.config.residual_scale(self.shape.algo),
        }
    }
}

/// The folder of a run's selected policy (written by selection.rs): a
/// policy folder as a checkpoint is, under `run_dir`.
pub fn selected_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("selected")
}

/// The newest intact checkpoint under `run_dir`, if any: the highest
/// episode whose checkpoint.json parses and whose files are whole
/// ([`check_intact`]). A checkpoint damaged after it was written (a
/// truncated file, a disk error) must not stop a resume when an older one
/// is whole, so those are skipped, each logged with the reason.
pub fn latest_checkpoint(run_dir: &Path) -> Option<PathBuf> {
    intact_checkpoints(run_dir).next()
}

/// The intact checkpoints of `run_dir`, newest first (checked as they are
/// asked for; damaged ones skipped and logged).
pub fn intact_checkpoints(run_dir: &Path) -> impl Iterator<Item = PathBuf> {
    checkpoint_folders(&run_dir.join("checkpoints")).into_iter().rev().filter(|dir| match check_intact(dir) {
        Ok(()) => true,
        Err(e) => {
            tracing::warn!(checkpoint = %dir.display(), "skipping a checkpoint that is not intact: {e}");
            false
        }
    })
}

/// The checkpoints in `root` holding a checkpoint.json, oldest first by
/// the episode in their name (`ep1000000` after `ep999999`: the names
/// outgrow their zero padding). [`write_folder`]'s staging folders
/// (`.NAME.partial`) are never among them; a folder it moved aside
/// (`.NAME.old`) stands for NAME while NAME is missing: a writer killed
/// between its two renames leaves the previous checkpoint there.
fn checkpoint_folders(root: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(root) else { return Vec::new() };
    let names: Vec<String> = entries
        .filter_map(|e| e.ok())
        .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    let mut found: Vec<(usize, PathBuf)> = names
        .iter()
        .filter_map(|name| {
            let plain = match name.strip_prefix('.').and_then(|n| n.strip_suffix(".old")) {
                Some(plain) if names.iter().any(|n| n == plain) => return None,
                Some(plain) => plain,
                None => name.as_str(),
            };
            Some((checkpoint_episode(plain)?, root.join(name)))
        })
        .filter(|(_, dir)| dir.join("checkpoint.json").is_file())
        .collect();
    found.sort();
    found.into_iter().map(|(_, dir)| dir).collect()
}

/// The episode of a checkpoint folder's name `epNNNNNN`, if it is one.
fn checkpoint_episode(name: &str) -> Option<usize> {
    let digits = name.strip_prefix("ep")?;
    // Digits only: `parse` would also take a sign.
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

/// Whether the checkpoint folder `dir` can be resumed: checkpoint.json
/// parses; every file its manifest lists (the `files` [`write_folder`]
/// records: name and size) is there with its size; every safetensors file
/// has a whole header whose tensors end where the file ends; agent.json
/// parses; and actor.safetensors, which every agent and `lcrl eval` reads,
/// is there. Checkpoints written before the manifest get all but the
/// size check. The error says what is wrong.
pub fn check_intact(dir: &Path) -> Result<(), LearnerError> {
    let path = dir.join("checkpoint.json");
    let text = std::fs::read_to_string(&path).map_err(io(&path))?;
    let bad = |what: String| LearnerError::Checkpoint(format!("{}: {what}", path.display()));
    parse_meta(&text).map_err(|e| bad(e.to_string()))?;
    let manifest: Manifest = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    for (name, size) in manifest.files.unwrap_or_default() {
        // A manifest names files in this folder, never a path elsewhere.
        if name.contains('/') || name.contains('\\') || name == ".." || name == "." {
            return Err(bad(format!("the manifest names {name:?}, not a file of the checkpoint")));
        }
        let file = dir.join(&name);
        let len = std::fs::metadata(&file).map_err(io(&file))?.len();
        if len != size {
            return Err(bad(format!("{name} is {len} bytes, the checkpoint wrote {size}")));
        }
    }
    let actor = dir.join("actor.safetensors");
    if !actor.is_file() {
        return Err(LearnerError::Checkpoint(format!("{} is missing", actor.display())));
    }
    for entry in std::fs::read_dir(dir).map_err(io(dir))? {
        let file = entry.map_err(io(dir))?.path();
        let name = file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        if name.ends_with(".safetensors") {
            check_safetensors(&file)?;
            // Weights and optimizer state: a NaN or ∞ in them would make
            // every policy after a resume NaN (issue 71). The replay
            // buffer is data, checked at the door, and can be large.
            if name != "replay.safetensors" {
                check_finite(&file)?;
            }
        } else if name == "agent.json" {
            let reader = std::io::BufReader::new(std::fs::File::open(&file).map_err(io(&file))?);
            serde_json::from_reader::<_, serde::de::IgnoredAny>(reader).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", file.display())))?;
        }
    }
    Ok(())
}

/// The part of checkpoint.json that [`write_folder`] adds beside the
/// metadata: every other file of the folder with its size in bytes.
#[derive(Deserialize)]
struct Manifest {
    #[serde(default)]
    files: Option<BTreeMap<String, u64>>,
}

/// The safetensors format's own bound on a header (the crate refuses
/// larger ones), so a garbled length cannot make us read gigabytes.
const MAX_SAFETENSORS_HEADER: u64 = 100_000_000;

/// Whether the safetensors file `path` is whole, reading only its header
/// (a replay buffer can be hundreds of megabytes): an 8-byte length, a
/// JSON header, and the tensors' data ending exactly at the file's end.
fn check_safetensors(path: &Path) -> Result<(), LearnerError> {
    use std::io::Read as _;
    let bad = |what: &str| LearnerError::Checkpoint(format!("{}: {what}", path.display()));
    let mut file = std::fs::File::open(path).map_err(io(path))?;
    let len = file.metadata().map_err(io(path))?.len();
    let mut prefix = [0u8; 8];
    file.read_exact(&mut prefix).map_err(|_| bad("shorter than a safetensors header"))?;
    let n = u64::from_le_bytes(prefix);
    if n > MAX_SAFETENSORS_HEADER || n.saturating_add(8) > len {
        return Err(bad("the header runs past the end of the file"));
    }
    let mut header = vec![0u8; n as usize];
    file.read_exact(&mut header).map_err(io(path))?;
    let header: BTreeMap<String, serde_json::Value> = serde_json::from_slice(&header).map_err(|_| bad("the header is not a safetensors header"))?;
    let mut end = 0u64;
    for (name, info) in header.iter().filter(|(name, _)| name.as_str() != "__metadata__") {
        let offsets = info.get("data_offsets").and_then(|o| o.as_array()).filter(|o| o.len() == 2);
        let stop = offsets.and_then(|o| o[1].as_u64()).ok_or_else(|| bad(&format!("tensor {name} has no data offsets")))?;
        end = end.max(stop);
    }
    // Saturating: the offsets are the file's to say, and may be absurd.
    let described = 8u64.saturating_add(n).saturating_add(end);
    if described != len {
        return Err(bad(&format!("{len} bytes, but its header describes {described}")));
    }
    Ok(())
}

/// Whether every floating-point value of the safetensors file `path` is
/// finite ([`crate::policy::finite::all_finite`]).
fn check_finite(path: &Path) -> Result<(), LearnerError> {
    let bytes = std::fs::read(path).map_err(io(path))?;
    match crate::policy::finite::all_finite(&bytes) {
        Ok(true) => Ok(()),
        Ok(false) => Err(LearnerError::Checkpoint(format!("{} holds a non-finite weight (NaN or ∞)", path.display()))),
        Err(e) => Err(LearnerError::Checkpoint(format!("{}: {e}", path.display()))),
    }
}

/// Every weight file of a staged checkpoint is finite; else the
/// checkpoint is not written (the earlier ones stay the newest).
fn check_staged_finite(dir: &Path) -> Result<(), LearnerError> {
    for entry in std::fs::read_dir(dir).map_err(io(dir))? {
        let file = entry.map_err(io(dir))?.path();
        let name = file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        if name.ends_with(".safetensors") && name != "replay.safetensors" {
            check_finite(&file).map_err(|e| LearnerError::Diverged(format!("{e}; training has diverged, the last finite checkpoint stays the newest")))?;
        }
    }
    Ok(())
}

pub fn read_meta(dir: &Path) -> Result<CheckpointMeta, LearnerError> {
    let path = dir.join("checkpoint.json");
    let text = std::fs::read_to_string(&path).map_err(io(&path))?;
    parse_meta(&text).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

/// checkpoint.json's metadata. A checkpoint written before an option was
/// removed records it at its "off" value: read as it was
/// (crate::config::REMOVED_DDPG_KEYS_AT_OFF).
fn parse_meta(text: &str) -> Result<CheckpointMeta, serde_json::Error> {
    let mut json: serde_json::Value = serde_json::from_str(text)?;
    if let Some(config) = json.get_mut("config") {
        crate::config::drop_removed_json_keys_at_off(config);
    }
    serde_json::from_value(json)
}

/// Writes a checkpoint durably ([`write_folder`]), then keeps only the
/// newest [`KEEP_CHECKPOINTS`]. On an error (a full disk) nothing of the
/// new checkpoint is left and the earlier ones are as they were.
pub fn write_checkpoint(run_dir: &Path, agent: &dyn Agent, meta: &CheckpointMeta) -> Result<PathBuf, LearnerError> {
    let root = run_dir.join("checkpoints");
    std::fs::create_dir_all(&root).map_err(io(&root))?;
    let target = root.join(format!("ep{:06}", meta.episode));
    write_folder(&target, meta, |staging| {
        agent.save(staging, meta.config.run.save_replay)?;
        check_staged_finite(staging)
    })?;
    prune_checkpoints(&root, KEEP_CHECKPOINTS);
    Ok(target)
}

/// Writes the folder `target` whole or not at all, and durably:
/// 1. `fill` writes into the staging folder `.NAME.partial` beside it;
/// 2. `meta` goes in as checkpoint.json with the manifest of the files
///    (name and size, which [`check_intact`] checks), and every file and
///    the staging folder are flushed to disk (fsync);
/// 3. an existing `target` is renamed aside to `.NAME.old`, the staging
///    folder renamed to `target`, and the parent folder flushed;
/// 4. the old folder is deleted.
///
/// A kill at any point leaves the old folder or the new one whole: before
/// step 3 `target` is untouched; between its two renames `.NAME.old` is
/// the only copy, which [`recover_folder`] (at the next write or resume)
/// renames back and which the checkpoint listing meanwhile takes for
/// NAME. On an error (a full disk) the staging folder is removed, so it
/// does not keep the space it took, and `target` stays as it was.
pub fn write_folder(target: &Path, meta: &CheckpointMeta, fill: impl FnOnce(&Path) -> Result<(), LearnerError>) -> Result<(), LearnerError> {
    let staging = beside(target, "partial")?;
    // What a writer killed earlier left: the old folder moved aside, or a
    // half-written staging folder.
    recover_folder(target)?;
    remove_dir_if_present(&staging)?;
    let written = std::fs::create_dir_all(&staging).map_err(io(&staging)).and_then(|()| fill(&staging)).and_then(|()| seal(&staging, meta));
    if let Err(e) = written {
        discard(&staging);
        return Err(e);
    }
    swap_in(&staging, target)
}

/// `.NAME.SUFFIX` beside `target`: where [`write_folder`] stages
/// (`partial`) and moves the replaced folder aside (`old`).
fn beside(target: &Path, suffix: &str) -> Result<PathBuf, LearnerError> {
    let name = target.file_name().ok_or_else(|| LearnerError::Checkpoint(format!("{} names no folder", target.display())))?;
    Ok(target.with_file_name(format!(".{}.{suffix}", name.to_string_lossy())))
}

/// Step 2 of [`write_folder`]: every file flushed and listed in
/// checkpoint.json, then the folder's own entries flushed.
fn seal(staging: &Path, meta: &CheckpointMeta) -> Result<(), LearnerError> {
    let mut files = BTreeMap::new();
    for entry in std::fs::read_dir(staging).map_err(io(staging))? {
        let entry = entry.map_err(io(staging))?;
        let path = entry.path();
        if path.is_file() {
            sync_file(&path).map_err(io(&path))?;
            let len = entry.metadata().map_err(io(&path))?.len();
            files.insert(entry.file_name().to_string_lossy().into_owned(), len);
        }
    }
    let mut value = serde_json::to_value(meta).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    if let serde_json::Value::Object(fields) = &mut value {
        fields.insert("files".into(), serde_json::to_value(&files).map_err(|e| LearnerError::Checkpoint(e.to_string()))?);
    }
    let text = serde_json::to_string_pretty(&value).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    let path = staging.join("checkpoint.json");
    let mut file = std::fs::File::create(&path).map_err(io(&path))?;
    file.write_all(text.as_bytes()).and_then(|()| file.sync_all()).map_err(io(&path))?;
    sync_dir(staging).map_err(io(staging))
}

/// Steps 3 and 4 of [`write_folder`]. A failed rename puts things back as
/// they were and removes the staging folder.
fn swap_in(staging: &Path, target: &Path) -> Result<(), LearnerError> {
    let aside = beside(target, "old")?;
    let parent = folder_of(target);
    let replacing = target.exists();
    if replacing {
        if let Err(e) = std::fs::rename(target, &aside) {
            discard(staging);
            return Err(io(target)(e));
        }
    }
    if let Err(e) = std::fs::rename(staging, target) {
        if replacing {
            if let Err(back) = std::fs::rename(&aside, target) {
                tracing::warn!("cannot move {} back to {}: {back}; the next write or resume does", aside.display(), target.display());
            }
        }
        discard(staging);
        return Err(io(target)(e));
    }
    // The renames must be on disk before the old copy goes: otherwise a
    // power cut could bring back neither.
    sync_dir(parent).map_err(io(parent))?;
    if replacing {
        if let Err(e) = std::fs::remove_dir_all(&aside) {
            tracing::warn!("cannot remove the replaced folder {}: {e}; the next write or resume does", aside.display());
        }
    }
    Ok(())
}

/// Finishes or undoes what a writer killed inside [`write_folder`]'s swap
/// left: with `target` there, `.NAME.old` beside it is the replaced folder
/// and is deleted; with `target` missing it is the only whole copy and is
/// renamed back.
pub fn recover_folder(target: &Path) -> Result<(), LearnerError> {
    let aside = beside(target, "old")?;
    if !aside.is_dir() {
        return Ok(());
    }
    if target.exists() {
        return remove_dir_if_present(&aside);
    }
    std::fs::rename(&aside, target).map_err(io(target))?;
    tracing::warn!(folder = %target.display(), "recovered the folder a killed writer had moved aside");
    let parent = folder_of(target);
    sync_dir(parent).map_err(io(parent))
}

/// [`recover_folder`] for every folder in `root`, and the staging folders
/// (`.NAME.partial`) a killed writer left removed, so they do not keep
/// their space. For a resume: nothing else may write in `root` meanwhile.
pub fn recover_folders(root: &Path) -> Result<(), LearnerError> {
    let Ok(entries) = std::fs::read_dir(root) else { return Ok(()) };
    for entry in entries.filter_map(|e| e.ok()).filter(|e| e.file_type().is_ok_and(|t| t.is_dir())) {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(hidden) = name.strip_prefix('.') else { continue };
        if let Some(plain) = hidden.strip_suffix(".old") {
            recover_folder(&root.join(plain))?;
        } else if hidden.ends_with(".partial") {
            tracing::warn!(folder = %entry.path().display(), "removing a staging folder a killed writer left");
            remove_dir_if_present(&entry.path())?;
        }
    }
    Ok(())
}

fn remove_dir_if_present(dir: &Path) -> Result<(), LearnerError> {
    match std::fs::remove_dir_all(dir) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io(dir)(e)),
        _ => Ok(()),
    }
}

/// Removes a staging folder after a failure, which is already the error
/// reported: a second one is only logged.
fn discard(staging: &Path) {
    if let Err(e) = remove_dir_if_present(staging) {
        tracing::warn!("cannot remove the staging folder {}: {e}", staging.display());
    }
}

/// Checkpoints kept per run: each can hold a replay buffer of hundreds of
/// megabytes, so only the newest few stay.
pub const KEEP_CHECKPOINTS: usize = 3;

/// Deletes all but the newest `keep` checkpoints, in episode order.
fn prune_checkpoints(root: &Path, keep: usize) {
    // Counted by intact ones: damaged newer folders (which resume skips)
    // must not push the last good checkpoints out. Nothing newer than the
    // `keep`-th intact one is removed.
    let folders = checkpoint_folders(root);
    let mut intact = 0;
    let cut = folders.iter().rposition(|folder| {
        intact += usize::from(check_intact(folder).is_ok());
        intact == keep
    });
    for old in &folders[..cut.unwrap_or(0)] {
        if let Err(e) = std::fs::remove_dir_all(old) {
            tracing::warn!("cannot remove old checkpoint {}: {e}", old.display());
        }
    }
}

#[cfg(test)]
mod tests;
