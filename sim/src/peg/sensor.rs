//! The wrist force/torque sensor that is not perfect (docs/peg.md, "A sensor
//! that is not perfect"): a peg config's `[sensor]` section.
//!
//! Off (the default, and on every published preset) the sensor reports the
//! simulator's contact wrench exactly, as before. On, every reading is
//!
//! ```text
//! reading_i(t) = true_i(t) + b_i(t) + σ_i·n_i(t),   b_i(t) = b_i(t − Δt) + d·σ_i·√Δt·w_i(t)
//! ```
//!
//! per channel i of (Fx, Fy, Fz, Mx, My, Mz), with n and w independent
//! standard normal draws, Δt the control period, and b_i = 0 at each
//! episode start (the sensor is tared before each insertion). σ for the
//! forces is the named class's published force resolution, taken as the
//! standard deviation of white noise (an assumption: a data sheet's
//! resolution is not a noise figure). Moment noise and drift are not
//! published for these classes: σ for the moments is the force σ times a
//! lever arm (0.05 m by default), and the drift d is half a σ per √s; both
//! are assumptions and parameters.
//!
//! The draws come from a stream of their own, seeded from the episode seed,
//! so the same seed gives the same episode and the sensor never touches the
//! pose or part draws.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::env::EnvError;

/// A sensor class and its published force resolution, N (docs/peg.md,
/// "A sensor that is not perfect", from a third-party sensor comparison).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorClass {
    pub name: &'static str,
    pub resolution_n: f64,
}

/// The accepted `sensor.class` names.
pub const CLASSES: [SensorClass; 4] = [
    // Robotiq FT 300-S: 300 N (30 N·m) range, 100 Hz.
    SensorClass { name: "robotiq-ft300s", resolution_n: 0.1 },
    // ATI Gamma SI-32-2.5: 32 N range, 7 kHz.
    SensorClass { name: "ati-gamma", resolution_n: 6.25e-3 },
    // Bota SensONE: 200 N range, 2 kHz.
    SensorClass { name: "bota-sensone", resolution_n: 0.1 },
    // OnRobot HEX-E QC: 200 N range.
    SensorClass { name: "onrobot-hexe", resolution_n: 0.2 },
];

/// The class a `[sensor]` section without `class` gets.
pub const DEFAULT_CLASS: &str = "robotiq-ft300s";

/// `[sensor]`: the sensor model and its parameters (assumptions named).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorConfig {
    /// Whether readings carry noise and drift; false: the exact wrench.
    pub enabled: bool,
    /// One of [`CLASSES`]: its force resolution is the force noise σ.
    pub class: String,
    /// Force noise σ per channel, N; absent: the class's resolution.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub force_std_n: Option<f64>,
    /// Moment noise σ per channel, N·m; absent: force σ × `lever_arm_m`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub moment_std_nm: Option<f64>,
    /// The lever arm that turns force noise into moment noise, m
    /// (assumption: 0.05 m, of the order of a wrist sensor's radius and
    /// of the peg's length).
    pub lever_arm_m: f64,
    /// Bias drift: each channel's bias is a random walk whose step has
    /// standard deviation this × the channel's σ × √(control period in s)
    /// (assumption: 0.5, so on a 2 s group episode the bias ends about 0.7 σ
    /// from zero).
    pub drift_per_sqrt_s: f64,
}

impl Default for SensorConfig {
    fn default() -> Self {
        SensorConfig { enabled: false, class: DEFAULT_CLASS.to_string(), force_std_n: None, moment_std_nm: None, lever_arm_m: 0.05, drift_per_sqrt_s: 0.5 }
    }
}

impl SensorConfig {
    /// The default class, switched on (the `-noisy` presets).
    pub fn noisy() -> Self {
        SensorConfig { enabled: true, ..Self::default() }
    }

    /// The named class, if it is one of [`CLASSES`].
    pub fn class_of(name: &str) -> Option<SensorClass> {
        CLASSES.iter().copied().find(|c| c.name == name)
    }

    /// Checks every value, naming the field of the first bad one. Checked
    /// whether or not the sensor is on, so an error shows before it is used.
    pub fn validate(&self) -> Result<(), EnvError> {
        if Self::class_of(&self.class).is_none() {
            let accepted: Vec<String> = CLASSES.iter().map(|c| format!("\"{}\"", c.name)).collect();
            return Err(EnvError::invalid("sensor.class", format!("unknown sensor class \"{}\"; accepted: {}", self.class, accepted.join(", "))));
        }
        let numbers = [
            ("sensor.force_std_n", self.force_std_n),
            ("sensor.moment_std_nm", self.moment_std_nm),
            ("sensor.lever_arm_m", Some(self.lever_arm_m)),
            ("sensor.drift_per_sqrt_s", Some(self.drift_per_sqrt_s)),
        ];
        for (field, v) in numbers.into_iter().filter_map(|(field, v)| Some((field, v?))) {
            if !(v.is_finite() && v >= 0.0) {
                return Err(EnvError::invalid(field, format!("must be a finite number ≥ 0, got {v}")));
            }
        }
        Ok(())
    }

    /// The force noise σ, N: `force_std_n`, else the class's resolution
    /// (0 for an unknown class, which [`Self::validate`] refuses).
    pub fn force_std(&self) -> f64 {
        self.force_std_n.unwrap_or_else(|| Self::class_of(&self.class).map_or(0.0, |c| c.resolution_n))
    }

    /// The moment noise σ, N·m: `moment_std_nm`, else force σ × lever arm.
    pub fn moment_std(&self) -> f64 {
        self.moment_std_nm.unwrap_or(self.force_std() * self.lever_arm_m)
    }

    /// The white-noise σ of each channel: N for forces, N·m for moments.
    pub fn stds(&self) -> [f64; 6] {
        let (f, m) = (self.force_std(), self.moment_std());
        [f, f, f, m, m, m]
    }
}

/// Seeds the sensor's draws apart from the pose and part draws.
pub const SENSOR_STREAM: u64 = 0x5E45_50A7;

/// A switched-on sensor's state: its draw stream and each channel's bias.
#[derive(Debug, Clone)]
pub struct Sensor {
    std: [f64; 6],
    drift: f64,
    bias: [f64; 6],
    rng: ChaCha8Rng,
}

impl Sensor {
    /// The sensor of `cfg`, or None where it is off (exact readings).
    pub fn new(cfg: &SensorConfig) -> Option<Self> {
        cfg.enabled.then(|| Sensor { std: cfg.stds(), drift: cfg.drift_per_sqrt_s, bias: [0.0; 6], rng: ChaCha8Rng::seed_from_u64(SENSOR_STREAM) })
    }

    /// A new episode of seed `seed`: the stream restarts from the seed.
    pub fn start_episode(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed ^ SENSOR_STREAM);
    }

    /// Re-seeds the draws, keeping the bias (CS3's two branches:
    /// `Env::reseed_noise`).
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// Zeroes the bias (the sensor is tared at each episode's start).
    pub fn tare(&mut self) {
        self.bias = [0.0; 6];
    }

    /// The current bias of each channel (N, N·m).
    pub fn bias(&self) -> [f64; 6] {
        self.bias
    }

    /// The error of one reading, `dt` seconds after the previous one: the
    /// bias walks on, then white noise is added. N for forces, N·m for
    /// moments; draws in channel order, the six drift steps first.
    pub fn error(&mut self, dt: f64) -> [f64; 6] {
        let step = self.drift * dt.max(0.0).sqrt();
        for i in 0..6 {
            let w: f64 = StandardNormal.sample(&mut self.rng);
            self.bias[i] += step * self.std[i] * w;
        }
        std::array::from_fn(|i| {
            let n: f64 = StandardNormal.sample(&mut self.rng);
            self.bias[i] + self.std[i] * n
        })
    }
}
