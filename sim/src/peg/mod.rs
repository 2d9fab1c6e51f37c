//! Peg-in-hole assembly (docs/method.md §6): a square peg held by a robot with a
//! wrist force/torque sensor, inserted into a square hole by the adaptive
//! compliance controller whose revision factors are the action.
//!
//! State (eq. 14), in this order and these units:
//! `[x, y, z, alpha, beta, gamma, Fx, Fy, Fz, Mx, My, Mz]`
//! - x, y: peg-tip offset from the hole axis, mm;
//! - z: remaining insertion depth (tip height above the target depth), mm;
//! - alpha, beta, gamma: peg orientation, XYZ Euler angles, degrees;
//! - F: contact force the hole exerts on the peg, N, hole-frame axes;
//! - M: contact moment about the sensor origin (the flange, top-face centre
//!   of the peg), N·m, hole-frame axes.
//!
//! F and M are the sensor's readings: the exact contact wrench unless the
//! config's `[sensor]` is on (sensor.rs), when they carry noise and drift.
//!
//! Action (eq. 15): the six revision factors a of the compliance K.

pub mod config;
pub mod controller;
pub mod sensor;
pub mod world;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rapier3d_f64::math::{Pose, Rotation, Vector};

use crate::env::{Env, EnvError, EnvSpec, EpisodeMetrics, ReturnTerms, Step};
pub use config::PegConfig;
use sensor::Sensor;
use world::{angles_deg, pose_from, PegWorld};

/// Seeds the per-episode part draws apart from the pose draws.
const PARTS_STREAM: u64 = 0x9A27_5EED;

/// The best constant action of each registered preset, as `lcrl tune --env
/// NAME` (default settings) found it (docs/peg.md), for
/// `controller.base = "best-constant"`. A test checks that each one still
/// beats a = 0 on its preset.
pub fn measured_best_constant(name: &str) -> Option<[f64; 6]> {
    match name {
        "peg-group1" => Some([2.00, 2.00, 0.22, 0.05, 0.11, 1.61]),
        "peg-group2" => Some([2.00, 2.00, -0.69, 1.15, 1.43, 1.67]),
        "peg-experiment" => Some([2.00, 2.00, 0.42, -0.62, -0.82, 1.94]),
        // Over the randomized parts and errors (1500 evaluations, 100
        // held-out episodes: −166.6 against a = 0's −199.3; −93.7 against
        // −158.0).
        "peg-group1-rand" => Some([2.00, 2.00, 2.00, 0.52, 0.56, 2.19]),
        "peg-group2-rand" => Some([2.00, 2.00, -0.83, 1.50, 4.00, 1.57]),
        // The noise-free groups' constants, not re-tuned under noise (a
        // test checks that each still beats a = 0 on its noisy preset).
        "peg-group1-noisy" => measured_best_constant("peg-group1"),
        "peg-group2-noisy" => measured_best_constant("peg-group2"),
        _ => None,
    }
}

const STATE_NAMES: [&str; 12] = ["x", "y", "z", "alpha", "beta", "gamma", "Fx", "Fy", "Fz", "Mx", "My", "Mz"];
const ACTION_NAMES: [&str; 6] = ["dx", "dy", "dz", "dalpha", "dbeta", "dgamma"];

/// Why an episode ended early.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    Running,
    /// The target depth was reached.
    Inserted,
    /// ‖F‖ exceeded the force limit.
    ForceLimit,
    /// ‖M‖ exceeded the moment limit.
    MomentLimit,
}

/// The peg-in-hole environment.
#[derive(Clone)]
pub struct PegEnv {
    /// The task as configured (with its randomization ranges, if any).
    cfg: PegConfig,
    /// The parts of the current episode: `cfg`, or a draw from its ranges.
    episode_cfg: PegConfig,
    spec: EnvSpec,
    world: PegWorld,
    /// Commanded tip pose (the robot's).
    command: Pose,
    /// Last sensor reading: force N, moment N·mm (the controller's units).
    /// The controller and the state see this.
    wrench: [f64; 6],
    /// The imperfect sensor's state, None where `[sensor]` is off (then
    /// the reading is the exact wrench).
    sensor: Option<Sensor>,
    state: Vec<f64>,
    steps: usize,
    outcome: Outcome,
    peak_force_n: f64,
    peak_moment_nm: f64,
    max_penetration_mm: f64,
    /// The reward terms of the episode so far.
    terms: ReturnTerms,
}

impl PegEnv {
    pub fn new(name: &str, cfg: PegConfig) -> Result<Self, EnvError> {
        cfg.validate()?;
        let k = &cfg.controller;
        let spec = EnvSpec {
            name: name.to_string(),
            state_names: STATE_NAMES.iter().map(|s| s.to_string()).collect(),
            action_names: ACTION_NAMES.iter().map(|s| s.to_string()).collect(),
            action_low: k.action_low.to_vec(),
            action_high: k.action_high.to_vec(),
        };
        let start = pose_from([0.0, 0.0, cfg.episode.start_height_mm], [0.0; 3]);
        let mut env = PegEnv {
            world: PegWorld::new(&cfg, start),
            sensor: Sensor::new(&cfg.sensor),
            episode_cfg: cfg.clone(),
            cfg,
            spec,
            command: start,
            wrench: [0.0; 6],
            state: vec![0.0; 12],
            steps: 0,
            outcome: Outcome::Running,
            peak_force_n: 0.0,
            peak_moment_nm: 0.0,
            max_penetration_mm: 0.0,
            terms: ReturnTerms::default(),
        };
        env.start_at(start);
        Ok(env)
    }

    pub fn config(&self) -> &PegConfig {
        &self.cfg
    }

    /// The parts of the current episode (friction, clearance and chamfer
    /// drawn at reset on randomized presets; otherwise the config's).
    pub fn episode_config(&self) -> &PegConfig {
        &self.episode_cfg
    }

    pub fn outcome(&self) -> Outcome {
        self.outcome
    }

    /// Starts an episode with the peg tip at an exact pose: position (mm)
    /// and XYZ angles (degrees), at rest, commanded where it is. A noisy
    /// sensor is tared and continues its draw stream (`reset` restarts it
    /// from the episode's seed).
    pub fn reset_to(&mut self, position_mm: [f64; 3], angles_deg: [f64; 3]) -> Vec<f64> {
        self.start_at(pose_from(position_mm, angles_deg));
        self.state.clone()
    }

    fn start_at(&mut self, pose: Pose) {
        self.world = PegWorld::new(&self.episode_cfg, pose);
        self.command = pose;
        self.wrench = [0.0; 6];
        if let Some(sensor) = &mut self.sensor {
            // Out of contact the true wrench is 0: the first reading is
            // the sensor's own noise.
            sensor.tare();
            self.wrench = measured(sensor, self.wrench, 0.0);
        }
        self.steps = 0;
        self.outcome = Outcome::Running;
        self.peak_force_n = 0.0;
        self.peak_moment_nm = 0.0;
        self.max_penetration_mm = self.world.penetration_mm();
        self.terms = ReturnTerms::default();
        self.state = self.observe();
    }

    /// The state vector of eq. 14 from the world and the last reading.
    fn observe(&self) -> Vec<f64> {
        let tip = self.world.tip_pose();
        let [a, b, c] = angles_deg(&tip.rotation);
        let t = tip.translation;
        let remaining = t.z + self.cfg.geometry.target_depth_mm;
        let w = self.wrench;
        vec![t.x, t.y, remaining, a, b, c, w[0], w[1], w[2], w[3] * 1e-3, w[4] * 1e-3, w[5] * 1e-3]
    }

    /// The tip's current pose (position mm, angles degrees), for tests and traces.
    pub fn tip(&self) -> ([f64; 3], [f64; 3]) {
        let tip = self.world.tip_pose();
        (tip.translation.to_array(), angles_deg(&tip.rotation))
    }

    /// Penetration of the peg into the hole block right now, mm (parry).
    pub fn penetration_mm(&self) -> f64 {
        self.world.penetration_mm()
    }
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

/// The sensor's reading of the true wrench `truth` (force N, moment N·mm),
/// `dt` seconds after its previous reading, in the same units.
fn measured(sensor: &mut Sensor, truth: [f64; 6], dt: f64) -> [f64; 6] {
    let e = sensor.error(dt);
    std::array::from_fn(|i| if i < 3 { truth[i] + e[i] } else { truth[i] + e[i] * 1e3 })
}

impl Env for PegEnv {
    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    /// Draws the initial pose error uniformly (±position_error_mm per axis,
    /// ±angle_error_deg per angle) around the start pose above the hole
    /// (shifted by the episode's offsets, 0 by default).
    fn reset(&mut self, seed: u64) -> Result<Vec<f64>, EnvError> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let e = &self.cfg.episode;
        let mut draw = |r: f64| if r > 0.0 { rng.random_range(-r..=r) } else { 0.0 };
        let [ox, oy] = e.position_offset_mm;
        let [oa, ob, oc] = e.angle_offset_deg;
        let position = [ox + draw(e.position_error_mm), oy + draw(e.position_error_mm), e.start_height_mm + draw(e.position_error_mm)];
        let angles = [oa + draw(e.angle_error_deg), ob + draw(e.angle_error_deg), oc + draw(e.angle_error_deg)];
        if let Some(sensor) = &mut self.sensor {
            sensor.start_episode(seed);
        }
        // The parts come from a stream of their own, so the pose draws (and
        // every unrandomized preset's episodes) do not depend on them.
        self.episode_cfg = match &self.cfg.randomize {
            Some(ranges) => {
                let mut parts = ChaCha8Rng::seed_from_u64(seed ^ PARTS_STREAM);
                ranges.apply(&self.cfg, &mut |[lo, hi]| if hi > lo { parts.random_range(lo..=hi) } else { lo })
            }
            None => self.cfg.clone(),
        };
        Ok(self.reset_to(position, angles))
    }

    fn state(&self) -> &[f64] {
        &self.state
    }

    #[tracing::instrument(level = "trace", skip_all)]
    fn step(&mut self, action: &[f64]) -> Result<Step, EnvError> {
        self.spec.check_action(action)?;
        if self.outcome != Outcome::Running {
            return Err(EnvError::EpisodeOver);
        }
        let clipped = self.spec.clip_action(action);
        let a: [f64; 6] = std::array::from_fn(|i| clipped[i]);
        let depth = self.cfg.geometry.target_depth_mm;
        let planned_left = self.command.translation.z + depth;
        let change = controller::pose_change(&self.cfg.controller, depth, planned_left, &a, &self.wrench);
        let [da, db, dc] = [change[3], change[4], change[5]].map(f64::to_radians);
        let rotation = Rotation::from_euler(rapier3d_f64::glamx::EulerRot::XYZ, da, db, dc) * self.command.rotation;
        let next = Pose::from_parts(self.command.translation + Vector::new(change[0], change[1], change[2]), rotation);

        let reading = self.world.advance(&self.command, &next);
        self.command = next;
        let [fx, fy, fz] = reading.force_n;
        let [mx, my, mz] = reading.moment_nmm;
        let truth = [fx, fy, fz, mx, my, mz];
        self.wrench = match &mut self.sensor {
            Some(sensor) => measured(sensor, truth, self.cfg.controller.control_period_s),
            None => truth,
        };
        self.state = self.observe();
        self.steps += 1;

        // The reward charges the wrench as measured (the state's), as the
        // publication's does; the failure rule and the peaks are physical
        // and use the true wrench (the same numbers with the sensor off).
        let force = norm(&self.state[6..9]);
        let moment = norm(&self.state[9..12]);
        let (true_force, true_moment) = (norm(&[fx, fy, fz]), norm(&[mx * 1e-3, my * 1e-3, mz * 1e-3]));
        self.peak_force_n = self.peak_force_n.max(true_force);
        self.peak_moment_nm = self.peak_moment_nm.max(true_moment);
        self.max_penetration_mm = self.max_penetration_mm.max(self.world.penetration_mm());

        let remaining = self.state[2];
        let limits = &self.cfg.limits;
        self.outcome = if true_force > limits.force_limit_n {
            Outcome::ForceLimit
        } else if true_moment > limits.moment_limit_nm {
            Outcome::MomentLimit
        } else if remaining <= limits.success_tolerance_mm {
            Outcome::Inserted
        } else {
            Outcome::Running
        };
        // Eqs. 16–17 in SI units (depth m, force N, moment N·m; docs/peg.md).
        // Reaching the depth ends the episode at once, and exceeding a limit
        // ends it as a failure, so an inserted episode stayed within limits
        // throughout and earns r_s.
        let r = &self.cfg.reward;
        let terms = ReturnTerms {
            depth: -r.h_z * self.cfg.clamped_depth_m(remaining),
            force: -r.h_f * force,
            moment: -r.h_m * moment,
            bonus: if self.outcome == Outcome::Inserted { r.r_s } else { 0.0 },
            // Failure must never pay (docs/peg.md, "the failure rule"): the
            // charge is the most any episode can lose to the dense terms, so
            // a failed episode scores below every successful one.
            failure: if matches!(self.outcome, Outcome::ForceLimit | Outcome::MomentLimit) { -self.cfg.failure_charge() } else { 0.0 },
        };
        self.terms = self.terms.add(&terms);
        let reward = terms.total();
        Ok(Step {
            state: self.state.clone(),
            reward,
            terminated: self.outcome != Outcome::Running,
            truncated: self.outcome == Outcome::Running && self.steps >= self.cfg.episode.max_steps,
        })
    }

    fn fresh(&self) -> Box<dyn Env> {
        Box::new(self.clone())
    }

    fn as_any(&self) -> &dyn std::any::Any {
        self
    }

    fn as_any_mut(&mut self) -> &mut dyn std::any::Any {
        self
    }

    fn snapshot(&self) -> Result<Box<dyn Env>, EnvError> {
        Ok(Box::new(self.clone()))
    }

    /// The noisy sensor's draws are the system's own randomness: CS3's two
    /// branches read through independent noise, as two real runs would.
    fn reseed_noise(&mut self, seed: u64) {
        if let Some(sensor) = &mut self.sensor {
            sensor.reseed(seed);
        }
    }

    fn is_stochastic(&self) -> bool {
        self.sensor.is_some()
    }

    /// Divides each component by its typical size (`observation.scale`,
    /// measured on real episodes), so inputs are of order 1.
    fn state_scale(&self) -> Option<&[f64]> {
        Some(&self.cfg.observation.scale)
    }

    fn control_period_s(&self) -> f64 {
        self.cfg.controller.control_period_s
    }

    /// Episode starts are above the hole, out of contact; the couplings
    /// that matter (docs/peg.md) show in contact, mid-insertion.
    fn prefers_trajectory_starts(&self) -> bool {
        true
    }

    fn depth_reference_mm(&self) -> Option<f64> {
        Some(self.cfg.geometry.target_depth_mm)
    }

    fn episode_metrics(&self) -> EpisodeMetrics {
        EpisodeMetrics {
            success: Some(self.outcome == Outcome::Inserted),
            peak_force_n: Some(self.peak_force_n),
            peak_moment_nm: Some(self.peak_moment_nm),
            max_penetration_mm: Some(self.max_penetration_mm),
            return_terms: Some(self.terms),
        }
    }
}

#[cfg(test)]
mod physics_tests;

#[cfg(test)]
mod sensor_tests;
