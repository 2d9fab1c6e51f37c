//! Every parameter of the peg-in-hole task (docs/method.md §6), its presets, and
//! TOML overrides checked on load.
//!
//! Units, written once here and used everywhere in `peg`:
//! - lengths in millimetres, angles in degrees, forces in newtons, moments
//!   in newton-millimetres (N·mm) inside the controller and N·m in the state;
//! - compliance k̂ (eq. 20): translational mm/N, rotational deg/(N·mm), so
//!   p_c = K·F moves the pose by millimetres and degrees per control step;
//! - reward (eqs. 16–17): SI units, depth z in metres, force in N, moment
//!   in N·m, as the publication's reward magnitudes imply (docs/peg.md): the
//!   depth term then costs about 1 per episode, and the return is decided by
//!   the contact terms, which the actions change.

use serde::{Deserialize, Serialize};

use super::sensor::SensorConfig;
use crate::env::EnvError;

/// The whole task. Sections mirror the TOML file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PegConfig {
    pub geometry: Geometry,
    pub contact: Contact,
    pub coupling: Coupling,
    pub controller: Controller,
    pub reward: Reward,
    pub limits: Limits,
    pub episode: Episode,
    pub physics: Physics,
    /// How states are scaled for learning (`Env::normalize_state`).
    #[serde(default)]
    pub observation: Observation,
    /// Part and contact drawn anew every episode (the `-rand` presets);
    /// absent: every episode has the parts above.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub randomize: Option<Randomize>,
    /// The wrist sensor's noise and drift (docs/peg.md, "A sensor that is
    /// not perfect"); absent: off, the exact wrench.
    #[serde(default)]
    pub sensor: SensorConfig,
}

/// The divisors of the state for learning, in the state's order and units
/// (mm, degrees, N, N·m). The defaults are the root-mean-square values of
/// a = 0 episodes on peg-group1 (8 episodes, docs/peg.md "Inputs"),
/// rounded, with z divided by the insertion depth L: typical inputs are
/// then of order 1. The force and moment limits (50 N, 1.5 N·m) as
/// divisors left the wrench at 0.01–0.04.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Observation {
    pub scale: [f64; 12],
}

impl Default for Observation {
    fn default() -> Self {
        Observation { scale: [0.05, 0.05, 30.0, 0.3, 0.3, 0.3, 1.0, 1.0, 2.0, 0.015, 0.015, 0.01] }
    }
}

/// Per-episode ranges, each [low, high], drawn uniformly at reset from the
/// episode's seed (docs/peg.md, "Randomized presets").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Randomize {
    /// Coulomb friction between peg and hole.
    pub friction: [f64; 2],
    /// Clearance, hole side minus peg side, mm: the hole is resized, the
    /// peg kept.
    pub clearance_mm: [f64; 2],
    /// 45° chamfer on the peg's bottom edges, mm.
    pub peg_chamfer_mm: [f64; 2],
}

impl Randomize {
    /// The parts of one episode: `nominal` with every range drawn by `draw`
    /// (a uniform draw in [low, high]).
    pub fn apply(&self, nominal: &PegConfig, draw: &mut dyn FnMut([f64; 2]) -> f64) -> PegConfig {
        let mut cfg = nominal.clone();
        cfg.contact.friction = draw(self.friction);
        cfg.geometry.hole_side_mm = cfg.geometry.peg_side_mm + draw(self.clearance_mm);
        cfg.geometry.peg_chamfer_mm = draw(self.peg_chamfer_mm);
        cfg.randomize = None;
        cfg
    }
}

/// Part dimensions (Table I / Table III).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Geometry {
    /// Side of the square peg.
    pub peg_side_mm: f64,
    /// Axis length of the peg.
    pub peg_length_mm: f64,
    /// 45° chamfer on the peg's bottom edges (0: sharp edges).
    pub peg_chamfer_mm: f64,
    /// Side of the square hole.
    pub hole_side_mm: f64,
    pub hole_depth_mm: f64,
    /// 45° chamfer on the hole's entrance edges (0: sharp edges).
    pub hole_chamfer_mm: f64,
    /// Wall thickness of the block the hole is cut in.
    pub wall_mm: f64,
    /// Target insertion depth L, measured from the hole entrance.
    pub target_depth_mm: f64,
}

/// Contact material.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Contact {
    /// Coulomb friction coefficient between peg and hole (ABS on ABS ≈ 0.3).
    pub friction: f64,
}

/// The robot–peg coupling: the stiffness of robot and wrist sensor, between
/// the commanded flange pose and the peg (a spring-damper acting at the
/// flange, which is the sensor origin and the peg's top face centre).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Coupling {
    /// Lateral (x, y) stiffness, N/mm.
    pub lateral_stiffness_n_per_mm: f64,
    /// Axial (z) stiffness, N/mm.
    pub axial_stiffness_n_per_mm: f64,
    /// Rotational stiffness about each axis, N·mm/rad.
    pub rotational_stiffness_nmm_per_rad: f64,
    /// Damping ratio of each coupling axis (1: critical).
    pub damping_ratio: f64,
    /// Mass moving with the peg (robot reflected mass at the flange), kg.
    /// With the default stiffnesses, 5 kg (and 2000 kg·mm²) puts every
    /// coupling mode at ω ≤ 100 rad/s, so ω·dt ≤ 0.25 at the default 2.5 ms
    /// physics step: stable and accurate for the explicit spring.
    pub moving_mass_kg: f64,
    /// Its rotational inertia about the flange (isotropic), kg·mm².
    pub moving_inertia_kg_mm2: f64,
}

/// The adaptive compliance controller (eqs. 18–20).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Controller {
    /// k̂: [x, y, z] in mm/N, then [alpha, beta, gamma] in deg/(N·mm).
    pub compliance: [f64; 6],
    /// Lower action bounds lb (revision factors).
    pub action_low: [f64; 6],
    /// Upper action bounds ub.
    pub action_high: [f64; 6],
    /// Planned insertion steps: the planned advance is L / steps (eq. 18).
    pub target_steps: usize,
    /// Control period, seconds.
    pub control_period_s: f64,
}

/// Reward coefficients (eqs. 16–17).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Reward {
    pub h_z: f64,
    pub h_f: f64,
    pub h_m: f64,
    /// Sparse bonus on success with forces and moments within limits.
    pub r_s: f64,
}

/// Safety limits and the success tolerance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Limits {
    /// The episode ends (terminated, failure) when ‖F‖ exceeds this, N.
    pub force_limit_n: f64,
    /// ... or when ‖M‖ exceeds this, N·m.
    pub moment_limit_nm: f64,
    /// Success when the remaining depth is at most this, mm.
    pub success_tolerance_mm: f64,
}

/// Episode start and length.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Episode {
    /// Height of the peg tip above the hole entrance before the pose error.
    pub start_height_mm: f64,
    /// Initial position error, uniform in ± this per axis (x, y, z), mm.
    pub position_error_mm: f64,
    /// Initial orientation error, uniform in ± this per axis, degrees.
    pub angle_error_deg: f64,
    /// Step cap: the episode is truncated after this many control steps.
    pub max_steps: usize,
    /// Centre of the initial pose error: the start's tip offset (x, y), mm,
    /// default 0 (the publication's centred distribution). A shifted
    /// distribution and its mirror image test the physics' symmetry.
    #[serde(default)]
    pub position_offset_mm: [f64; 2],
    /// Centre of the initial orientation error (alpha, beta, gamma), degrees.
    #[serde(default)]
    pub angle_offset_deg: [f64; 3],
}

/// Numerical settings of the physics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Physics {
    /// Physics steps per control step. 8 (2.5 ms) keeps penetration at a few
    /// µm; 6 lets it reach 15–20 µm, 4 about 40 µm (group 1, 40 episodes).
    pub substeps: usize,
    /// rapier solver iterations per physics step (2: 2.4 µm worst
    /// penetration at ~6,000 control steps/s; 4 is ~25% slower).
    pub solver_iterations: usize,
}

impl PegConfig {
    /// Table I, group 1: 9.9 mm peg in a 10 mm hole, 30 mm deep. The
    /// publication's simulation gives no chamfer; a sharp square peg offset
    /// by up to 0.2 mm against 0.05 mm clearance cannot enter without a search
    /// strategy, so the peg carries the experiment's 0.5 mm chamfer (Table III).
    pub fn group1() -> Self {
        PegConfig {
            geometry: Geometry {
                peg_side_mm: 9.9,
                peg_length_mm: 30.0,
                peg_chamfer_mm: 0.5,
                hole_side_mm: 10.0,
                hole_depth_mm: 30.0,
                hole_chamfer_mm: 0.0,
                wall_mm: 10.0,
                target_depth_mm: 30.0,
            },
            contact: Contact { friction: 0.3 },
            coupling: Coupling {
                lateral_stiffness_n_per_mm: 20.0,
                axial_stiffness_n_per_mm: 50.0,
                rotational_stiffness_nmm_per_rad: 2.0e4,
                damping_ratio: 1.0,
                moving_mass_kg: 5.0,
                moving_inertia_kg_mm2: 2.0e3,
            },
            controller: Controller {
                compliance: [5e-3, 5e-3, 5e-5, 1e-3, 1e-3, 1e-3],
                action_low: [-1.0; 6],
                action_high: [2.0, 2.0, 2.0, 4.0, 4.0, 4.0],
                target_steps: 50,
                control_period_s: 0.02,
            },
            reward: Reward { h_z: 1.0, h_f: 0.1, h_m: 1.0, r_s: 2.0 },
            limits: Limits { force_limit_n: 50.0, moment_limit_nm: 1.5, success_tolerance_mm: 0.1 },
            episode: Episode {
                start_height_mm: 1.0,
                position_error_mm: 0.2,
                angle_error_deg: 0.5,
                max_steps: 100,
                position_offset_mm: [0.0; 2],
                angle_offset_deg: [0.0; 3],
            },
            physics: Physics { substeps: 8, solver_iterations: 2 },
            observation: Observation::default(),
            randomize: None,
            sensor: SensorConfig::default(),
        }
    }

    /// Table I, group 2: 7.95 mm peg in an 8 mm hole, 20 mm deep.
    pub fn group2() -> Self {
        let mut cfg = Self::group1();
        cfg.geometry.peg_side_mm = 7.95;
        cfg.geometry.peg_length_mm = 20.0;
        cfg.geometry.hole_side_mm = 8.0;
        cfg.geometry.hole_depth_mm = 20.0;
        cfg.geometry.target_depth_mm = 20.0;
        cfg.observation.scale[2] = 20.0;
        cfg
    }

    /// Table III, the physical experiment: 0.5 mm peg chamfer, no hole
    /// chamfer, 250 steps, ±0.4 mm / ±1°, k̂ = diag(1e-3, 1e-3, 1e-5, 8e-4 ×3).
    pub fn experiment() -> Self {
        let mut cfg = Self::group1();
        cfg.controller.compliance = [1e-3, 1e-3, 1e-5, 8e-4, 8e-4, 8e-4];
        cfg.controller.target_steps = 250;
        cfg.episode.position_error_mm = 0.4;
        cfg.episode.angle_error_deg = 1.0;
        cfg.episode.max_steps = 500;
        cfg
    }

    /// A group preset as a task family (docs/peg.md, "Randomized
    /// presets"): friction, clearance and peg chamfer drawn per episode,
    /// initial errors twice Table I's (±0.4 mm, ±1°).
    pub fn randomized(mut self) -> Self {
        self.episode.position_error_mm *= 2.0;
        self.episode.angle_error_deg *= 2.0;
        self.randomize = Some(Randomize { friction: [0.1, 0.6], clearance_mm: [0.03, 0.2], peg_chamfer_mm: [0.45, 0.8] });
        self
    }

    /// A preset read through an imperfect wrist sensor (the `-noisy`
    /// presets): the default sensor class, switched on.
    pub fn noisy(mut self) -> Self {
        self.sensor = SensorConfig::noisy();
        self
    }

    /// The registered preset names, in the order help texts list them.
    pub const NAMES: [&'static str; 7] =
        ["peg-group1", "peg-group2", "peg-experiment", "peg-group1-rand", "peg-group2-rand", "peg-group1-noisy", "peg-group2-noisy"];

    /// The preset of a registered name.
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "peg-group1" => Some(Self::group1()),
            "peg-group2" => Some(Self::group2()),
            "peg-experiment" => Some(Self::experiment()),
            "peg-group1-rand" => Some(Self::group1().randomized()),
            "peg-group2-rand" => Some(Self::group2().randomized()),
            "peg-group1-noisy" => Some(Self::group1().noisy()),
            "peg-group2-noisy" => Some(Self::group2().noisy()),
            _ => None,
        }
    }

    /// Applies a TOML table of overrides (same sections and keys as the
    /// struct) on top of this config, then validates the result.
    pub fn with_overrides(&self, overrides: &toml::Table, source: &str) -> Result<Self, EnvError> {
        let mut merged = toml::Table::try_from(self).map_err(|e| EnvError::invalid("(preset)", e.to_string()))?;
        crate::overlay::overlay(&mut merged, overrides);
        let cfg: PegConfig = merged
            .try_into()
            .map_err(|e: toml::de::Error| EnvError::Parse { path: source.to_string(), message: e.to_string() })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// The largest remaining depth any episode can start from, mm: the
    /// start height plus its error plus L. The depth term of the reward is
    /// clamped to [0, this], which bounds every dense step cost.
    pub fn max_depth_mm(&self) -> f64 {
        self.episode.start_height_mm + self.episode.position_error_mm + self.geometry.target_depth_mm
    }

    /// The remaining depth z (mm) as the reward counts it: metres, clamped
    /// to [0, max_depth_mm].
    pub fn clamped_depth_m(&self, remaining_mm: f64) -> f64 {
        remaining_mm.clamp(0.0, self.max_depth_mm()) * 1e-3
    }

    /// The most one step within the limits can cost:
    /// c_max = h_z·z_max + h_F·F_limit + h_M·M_limit (SI units).
    pub fn max_step_cost(&self) -> f64 {
        let r = &self.reward;
        r.h_z * self.clamped_depth_m(self.max_depth_mm()) + r.h_f * self.limits.force_limit_n + r.h_m * self.limits.moment_limit_nm
    }

    /// The failure charge C = max_steps · c_max. A successful episode has at
    /// most max_steps steps, each within the limits, so it loses at most C
    /// to the dense terms and scores at least r_s − C; a failed one scores
    /// at most −C minus its own (positive) costs. Failure never pays.
    pub fn failure_charge(&self) -> f64 {
        self.episode.max_steps as f64 * self.max_step_cost()
    }

    /// Checks every value, naming the field of the first bad one.
    pub fn validate(&self) -> Result<(), EnvError> {
        check_geometry(&self.geometry)?;
        non_negative("contact.friction", self.contact.friction)?;
        check_coupling(&self.coupling)?;
        check_controller(&self.controller)?;
        let r = &self.reward;
        non_negative("reward.h_z", r.h_z)?;
        non_negative("reward.h_f", r.h_f)?;
        non_negative("reward.h_m", r.h_m)?;
        finite("reward.r_s", r.r_s)?;
        positive("limits.force_limit_n", self.limits.force_limit_n)?;
        positive("limits.moment_limit_nm", self.limits.moment_limit_nm)?;
        positive("limits.success_tolerance_mm", self.limits.success_tolerance_mm)?;
        let e = &self.episode;
        non_negative("episode.start_height_mm", e.start_height_mm)?;
        non_negative("episode.position_error_mm", e.position_error_mm)?;
        non_negative("episode.angle_error_deg", e.angle_error_deg)?;
        for (i, v) in e.position_offset_mm.iter().enumerate() {
            finite(&format!("episode.position_offset_mm[{i}]"), *v)?;
        }
        for (i, v) in e.angle_offset_deg.iter().enumerate() {
            finite(&format!("episode.angle_offset_deg[{i}]"), *v)?;
        }
        if e.max_steps == 0 {
            return Err(EnvError::invalid("episode.max_steps", "must be at least 1"));
        }
        if self.physics.substeps == 0 {
            return Err(EnvError::invalid("physics.substeps", "must be at least 1"));
        }
        if self.physics.solver_iterations == 0 {
            return Err(EnvError::invalid("physics.solver_iterations", "must be at least 1"));
        }
        for (i, &s) in self.observation.scale.iter().enumerate() {
            positive(&format!("observation.scale[{i}]"), s)?;
        }
        self.sensor.validate()?;
        if let Some(r) = &self.randomize {
            for (field, [lo, hi]) in [("randomize.friction", r.friction), ("randomize.clearance_mm", r.clearance_mm), ("randomize.peg_chamfer_mm", r.peg_chamfer_mm)] {
                if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                    return Err(EnvError::invalid(field, format!("must be [low, high] with low ≤ high, got [{lo}, {hi}]")));
                }
            }
            if r.clearance_mm[0] <= 0.0 {
                return Err(EnvError::invalid("randomize.clearance_mm", "the clearance must stay above 0"));
            }
            // Every draw must be a valid task: the range's corners are.
            for pick in [0, 1] {
                let corner = r.apply(self, &mut |range| range[pick]);
                corner.validate().map_err(|e| EnvError::invalid("randomize", format!("a part at the range's {} end is invalid: {e}", ["low", "high"][pick])))?;
            }
        }
        Ok(())
    }
}

/// The part sizes: each positive, the peg smaller than the hole, the
/// chamfers and the target depth within the parts.
fn check_geometry(g: &Geometry) -> Result<(), EnvError> {
    positive("geometry.peg_side_mm", g.peg_side_mm)?;
    positive("geometry.peg_length_mm", g.peg_length_mm)?;
    positive("geometry.hole_side_mm", g.hole_side_mm)?;
    positive("geometry.hole_depth_mm", g.hole_depth_mm)?;
    positive("geometry.wall_mm", g.wall_mm)?;
    positive("geometry.target_depth_mm", g.target_depth_mm)?;
    non_negative("geometry.peg_chamfer_mm", g.peg_chamfer_mm)?;
    non_negative("geometry.hole_chamfer_mm", g.hole_chamfer_mm)?;
    if g.peg_side_mm >= g.hole_side_mm {
        return Err(EnvError::invalid(
            "geometry.peg_side_mm",
            format!("{} mm must be smaller than hole_side_mm ({} mm) to leave a clearance", g.peg_side_mm, g.hole_side_mm),
        ));
    }
    if 2.0 * g.peg_chamfer_mm >= g.peg_side_mm || g.peg_chamfer_mm >= g.peg_length_mm {
        return Err(EnvError::invalid("geometry.peg_chamfer_mm", "must be less than half the peg side and the peg length"));
    }
    if g.hole_chamfer_mm >= g.wall_mm.min(g.hole_depth_mm) {
        return Err(EnvError::invalid("geometry.hole_chamfer_mm", "must be less than the wall thickness and the hole depth"));
    }
    if g.target_depth_mm > g.hole_depth_mm || g.target_depth_mm > g.peg_length_mm {
        return Err(EnvError::invalid("geometry.target_depth_mm", "cannot exceed the hole depth or the peg length"));
    }
    Ok(())
}

/// The compliant coupling's stiffnesses, damping and moving mass.
fn check_coupling(c: &Coupling) -> Result<(), EnvError> {
    positive("coupling.lateral_stiffness_n_per_mm", c.lateral_stiffness_n_per_mm)?;
    positive("coupling.axial_stiffness_n_per_mm", c.axial_stiffness_n_per_mm)?;
    positive("coupling.rotational_stiffness_nmm_per_rad", c.rotational_stiffness_nmm_per_rad)?;
    non_negative("coupling.damping_ratio", c.damping_ratio)?;
    positive("coupling.moving_mass_kg", c.moving_mass_kg)?;
    positive("coupling.moving_inertia_kg_mm2", c.moving_inertia_kg_mm2)?;
    Ok(())
}

/// The controller's compliances, action box and timing.
fn check_controller(k: &Controller) -> Result<(), EnvError> {
    for (i, v) in k.compliance.iter().enumerate() {
        non_negative(&format!("controller.compliance[{i}]"), *v)?;
    }
    for i in 0..6 {
        let (lo, hi) = (k.action_low[i], k.action_high[i]);
        finite(&format!("controller.action_low[{i}]"), lo)?;
        finite(&format!("controller.action_high[{i}]"), hi)?;
        // −1 switches the compliance off; below that K would flip sign.
        if !(-1.0..=0.0).contains(&lo) || hi < 0.0 {
            return Err(EnvError::invalid(
                format!("controller.action_low[{i}]/action_high[{i}]"),
                format!("need −1 ≤ low ≤ 0 ≤ high, got [{lo}, {hi}]"),
            ));
        }
    }
    if k.target_steps == 0 {
        return Err(EnvError::invalid("controller.target_steps", "must be at least 1"));
    }
    positive("controller.control_period_s", k.control_period_s)?;
    Ok(())
}

fn finite(field: &str, v: f64) -> Result<(), EnvError> {
    if v.is_finite() { Ok(()) } else { Err(EnvError::invalid(field, format!("must be finite, got {v}"))) }
}

fn positive(field: &str, v: f64) -> Result<(), EnvError> {
    if v.is_finite() && v > 0.0 { Ok(()) } else { Err(EnvError::invalid(field, format!("must be a finite number > 0, got {v}"))) }
}

fn non_negative(field: &str, v: f64) -> Result<(), EnvError> {
    if v.is_finite() && v >= 0.0 { Ok(()) } else { Err(EnvError::invalid(field, format!("must be a finite number ≥ 0, got {v}"))) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_are_valid_and_follow_the_tables() {
        for name in ["peg-group1", "peg-group2", "peg-experiment"] {
            PegConfig::preset(name).unwrap().validate().unwrap();
        }
        let g2 = PegConfig::group2();
        assert_eq!((g2.geometry.peg_side_mm, g2.geometry.hole_side_mm, g2.geometry.target_depth_mm), (7.95, 8.0, 20.0));
        let ex = PegConfig::experiment();
        assert_eq!(ex.controller.target_steps, 250);
        assert_eq!(ex.controller.compliance[2], 1e-5);
    }

    #[test]
    fn overrides_merge_and_bad_values_name_the_field() {
        let base = PegConfig::group1();
        let table: toml::Table = toml::from_str("[contact]\nfriction = 0.5\n[physics]\nsubsteps = 8\n").unwrap();
        let cfg = base.with_overrides(&table, "x.toml").unwrap();
        assert_eq!((cfg.contact.friction, cfg.physics.substeps), (0.5, 8));
        assert_eq!(cfg.geometry, base.geometry);

        let field = |text: &str| match base.with_overrides(&toml::from_str(text).unwrap(), "x.toml") {
            Err(EnvError::Invalid { field, .. }) => field,
            Err(EnvError::Parse { message, .. }) => format!("parse: {message}"),
            other => panic!("expected an error, got {other:?}"),
        };
        assert_eq!(field("[geometry]\npeg_side_mm = 10.5\n"), "geometry.peg_side_mm");
        assert_eq!(field("[contact]\nfriction = -0.1\n"), "contact.friction");
        assert_eq!(field("[coupling]\nmoving_mass_kg = nan\n"), "coupling.moving_mass_kg");
        assert!(field("[geometry]\npeg_sid_mm = 1.0\n").contains("peg_sid_mm"));
        assert!(field("[controller]\ncompliance = [1.0, 2.0]\n").contains("compliance"));
    }
}
