//! Where a run's settings come from: the files compiled in for each
//! registered environment, TOML files and override tables laid over them.

use std::path::Path;

use serde::Deserialize;

use super::{migrate_legacy_tables, TrainConfig};
use crate::LearnerError;

/// configs/lti-fast.toml, compiled in: the settings that work on lti-paper.
pub(super) const LTI_FAST: &str = include_str!("../../../configs/lti-fast.toml");
/// configs/peg.toml, compiled in: the settings that work on the peg tasks.
pub(super) const PEG: &str = include_str!("../../../configs/peg.toml");
/// configs/peg-experiment.toml, compiled in: peg-experiment's DDPG
/// settings, laid over configs/peg.toml.
const PEG_EXPERIMENT: &str = include_str!("../../../configs/peg-experiment.toml");
/// configs/peg-rand.toml, compiled in: the randomized presets' DDPG
/// settings, laid over configs/peg.toml.
const PEG_RAND: &str = include_str!("../../../configs/peg-rand.toml");
/// configs/peg-group1.toml, compiled in: peg-group1's DDPG settings, laid
/// over configs/peg.toml.
const PEG_GROUP1: &str = include_str!("../../../configs/peg-group1.toml");
/// configs/peg-group2.toml, compiled in: peg-group2's DDPG settings, laid
/// over configs/peg.toml.
const PEG_GROUP2: &str = include_str!("../../../configs/peg-group2.toml");

impl TrainConfig {
    /// What [`TrainConfig::for_env`] says its settings came from when an
    /// environment has none of its own: Table I's defaults.
    pub const TABLE1_SOURCE: &'static str = "Table I defaults";

    /// The training settings that work on a registered environment, used
    /// when no --config is given, and where they come from. lti-paper gets
    /// configs/lti-fast.toml and the peg presets configs/peg.toml (Table
    /// I's defaults diverge on both; docs/peg.md), with
    /// configs/peg-experiment.toml over it on peg-experiment,
    /// configs/peg-group1.toml and peg-group2.toml on the group presets and
    /// configs/peg-rand.toml on the randomized presets; every other environment
    /// gets Table I's defaults (configs/table1-ddpg.toml, table1-ppo.toml).
    pub fn for_env(env: &str) -> (TrainConfig, &'static str) {
        let peg = lcrl_sim::peg::PegConfig::preset(env);
        let embedded: Option<(&[&str], &str)> = match (env, peg) {
            ("lti-paper", _) => Some((&[LTI_FAST], "configs/lti-fast.toml (the settings for lti-paper)")),
            (name, _) if lcrl_sim::lti::LtiConfig::blocks_size(name).is_some() => Some((&[LTI_FAST], "configs/lti-fast.toml (the linear systems' settings, used for lti-blocks-N)")),
            ("peg-experiment", _) => Some((&[PEG, PEG_EXPERIMENT], "configs/peg.toml with configs/peg-experiment.toml (the settings for peg-experiment)")),
            (_, Some(peg)) if peg.randomize.is_some() => Some((&[PEG, PEG_RAND], "configs/peg.toml with configs/peg-rand.toml (the settings for the randomized peg presets)")),
            // A noisy preset is its group with a sensor: the group's settings.
            ("peg-group1" | "peg-group1-noisy", _) => Some((&[PEG, PEG_GROUP1], "configs/peg.toml with configs/peg-group1.toml (the settings for peg-group1)")),
            ("peg-group2" | "peg-group2-noisy", _) => Some((&[PEG, PEG_GROUP2], "configs/peg.toml with configs/peg-group2.toml (the settings for peg-group2)")),
            (_, Some(_)) => Some((&[PEG], "configs/peg.toml (the settings for the peg presets)")),
            (_, None) => None,
        };
        // The embedded files are checked by a unit test; a parse failure
        // here would be a build defect, and Table I's defaults stand in.
        let layered = |files: &[&str]| -> Option<TrainConfig> {
            let mut merged = toml::Table::new();
            for text in files {
                lcrl_sim::overlay(&mut merged, &toml::from_str::<toml::Table>(text).ok()?);
            }
            toml::Value::Table(merged).try_into().ok()
        };
        match embedded.and_then(|(files, source)| Some((layered(files)?, source))) {
            Some((cfg, source)) => (cfg, source),
            None => (TrainConfig::default(), Self::TABLE1_SOURCE),
        }
    }

    /// `env`'s settings (see [`TrainConfig::for_env`]) with a table of
    /// overrides laid over them (sections merge key by key), checked.
    pub fn for_env_with(env: &str, overrides: &toml::Table) -> Result<TrainConfig, LearnerError> {
        let (defaults, _) = Self::for_env(env);
        let mut merged = toml::Table::try_from(&defaults).map_err(|e| LearnerError::Config(e.to_string()))?;
        let mut overrides = overrides.clone();
        migrate_legacy_tables(&mut overrides);
        lcrl_sim::overlay(&mut merged, &overrides);
        replace_preset_reach(&mut merged, &overrides);
        let cfg: TrainConfig = toml::Value::Table(merged).try_into().map_err(|e: toml::de::Error| LearnerError::Config(e.to_string()))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads a TOML file whose missing keys keep `env`'s settings.
    pub fn load_for_env(path: &Path, env: &str) -> Result<Self, LearnerError> {
        let text = std::fs::read_to_string(path).map_err(|source| LearnerError::Io { path: path.into(), source })?;
        Self::parse_for_env(&text, env).map_err(|e| LearnerError::Config(format!("{}: {e}", path.display())))
    }

    /// [`TrainConfig::load_for_env`] on a file's text (fuzzed by
    /// fuzz/fuzz_targets/toml_config.rs).
    pub fn parse_for_env(text: &str, env: &str) -> Result<Self, LearnerError> {
        let table: toml::Table = toml::from_str(text).map_err(|e| LearnerError::Config(e.to_string()))?;
        Self::for_env_with(env, &table)
    }

    /// Reads a TOML file (missing keys keep their defaults).
    pub fn load(path: &Path) -> Result<Self, LearnerError> {
        let text = std::fs::read_to_string(path).map_err(|source| LearnerError::Io { path: path.into(), source })?;
        let mut table: toml::Table = toml::from_str(&text).map_err(|e| LearnerError::Config(format!("{}: {e}", path.display())))?;
        migrate_legacy_tables(&mut table);
        let cfg = TrainConfig::deserialize(toml::Value::Table(table)).map_err(|e| LearnerError::Config(format!("{}: {e}", path.display())))?;
        cfg.validate()?;
        Ok(cfg)
    }
}

/// Where overrides (already laid over `merged`) replace an environment's
/// own DDPG reach (`[ddpg] residual_scale`, configs/peg-group2.toml) with
/// `[base]`'s. A preset's DDPG reach was measured around its best constant,
/// so a user who sets a reach in `[base]` (for both algorithms), or another
/// base than the best constant (e.g. "a = 0", training from scratch), gets
/// `[base]`'s reach for DDPG too. Overrides that set `[ddpg]
/// residual_scale` themselves keep it. The reach is written out, not
/// removed: a resolved config whose `[base]` reach is the default 1 leaves
/// that key out, and read back it must not bring the preset's reach back.
fn replace_preset_reach(merged: &mut toml::Table, overrides: &toml::Table) {
    let section = |name: &str| overrides.get(name).and_then(toml::Value::as_table);
    if section("ddpg").is_some_and(|ddpg| ddpg.contains_key("residual_scale")) {
        return;
    }
    let Some(base) = section("base") else { return };
    let other_base = base.get("action").is_some_and(|action| action.as_str() != Some("best-constant"));
    if !(base.contains_key("residual_scale") || other_base) {
        return;
    }
    let default_reach = toml::Value::Float(super::BaseConfig::default().residual_scale);
    let base_reach = merged.get("base").and_then(|b| b.get("residual_scale")).cloned().unwrap_or(default_reach);
    if let Some(toml::Value::Table(ddpg)) = merged.get_mut("ddpg") {
        if ddpg.contains_key("residual_scale") {
            ddpg.insert("residual_scale".into(), base_reach);
        }
    }
}
