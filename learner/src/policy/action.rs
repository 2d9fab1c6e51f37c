//! Between the agent's normalized action u ∈ [−1, 1]ⁿ and the environment's
//! action a ∈ [lb, ub] (docs/method.md eq. 15 on peg tasks), in one place.
//!
//! ```text
//! a = clip(b + s · u ⊙ (ub − lb)/2, lb, ub)
//! ```
//!
//! b is the base controller the agent acts around (residual RL). Without a
//! base, b is the box centre, s = 1 and the map is the plain linear one
//! onto the box (Table I's setting: u = 0 is the middle of the box, never
//! clipped). With a base, u = 0 is the base controller itself, and the
//! actor's near-zero initial output (nets.rs) makes the first policy the
//! base. s ∈ (0, 1] is the residual's reach (`[base] residual_scale`): the
//! policy never leaves b ± s·(ub − lb)/2, whatever it learns.

use lcrl_sim::EnvSpec;
use serde::Deserialize;

use crate::config::{BaseConfig, BaseController};
use crate::LearnerError;

/// The affine map from u to a, with its inverse.
#[derive(Debug, Clone, PartialEq)]
pub struct ActionMap {
    low: Vec<f64>,
    high: Vec<f64>,
    /// b: the base action, or the box centre without one.
    centre: Vec<f64>,
    /// s·(ub − lb)/2: how far u = ±1 moves each action from b.
    reach: Vec<f64>,
    /// The base action, when there is one (for reports).
    base: Option<Vec<f64>>,
}

impl ActionMap {
    /// The plain map onto the box (no base controller).
    pub fn plain(spec: &EnvSpec) -> Self {
        let centre = spec.action_low.iter().zip(&spec.action_high).map(|(lo, hi)| 0.5 * (lo + hi)).collect();
        let reach = Self::plain_reach(&spec.action_low, &spec.action_high);
        ActionMap { low: spec.action_low.clone(), high: spec.action_high.clone(), centre, reach, base: None }
    }

    /// The map around a base action (None: [`ActionMap::plain`]), which must
    /// have one finite component per action inside the box.
    pub fn new(spec: &EnvSpec, base: Option<&[f64]>) -> Result<Self, LearnerError> {
        let mut map = Self::plain(spec);
        if let Some(base) = base {
            check_base(spec, base)?;
            map.centre = base.to_vec();
            map.base = Some(base.to_vec());
        }
        Ok(map)
    }

    /// The map with the residual's reach s (`[base] residual_scale`): u = ±1
    /// moves each action s half-widths of its box from the base. Validated
    /// configurations and snapshots hold s ∈ (0, 1], 1 without a base.
    pub fn with_residual_scale(mut self, s: f64) -> Self {
        let full = Self::plain_reach(&self.low, &self.high);
        self.reach = full.iter().map(|half| s * half).collect();
        self
    }

    fn plain_reach(low: &[f64], high: &[f64]) -> Vec<f64> {
        low.iter().zip(high).map(|(lo, hi)| 0.5 * (hi - lo)).collect()
    }

    /// The base action, if the map has one.
    pub fn base(&self) -> Option<&[f64]> {
        self.base.as_deref()
    }

    /// a of a normalized action u (u clipped to [−1, 1], a to the box).
    pub fn to_env(&self, u: &[f32]) -> Vec<f64> {
        u.iter()
            .enumerate()
            .map(|(i, &u)| (self.centre[i] + f64::from(u).clamp(-1.0, 1.0) * self.reach[i]).clamp(self.low[i], self.high[i]))
            .collect()
    }

    /// The u that gives `a` (clipped to [−1, 1]); `to_env(to_normalized(a))
    /// == a` for every a in the box that the map reaches.
    pub fn to_normalized(&self, a: &[f64]) -> Vec<f32> {
        a.iter()
            .enumerate()
            .map(|(i, &a)| {
                let reach = self.reach[i];
                if reach > 0.0 { ((a - self.centre[i]) / reach).clamp(-1.0, 1.0) as f32 } else { 0.0 }
            })
            .collect()
    }
}

// Which reaches a map can take is the configuration's rule (config checks
// it, and snapshots with it).
pub use crate::config::residual_scale_fits;

fn check_base(spec: &EnvSpec, base: &[f64]) -> Result<(), LearnerError> {
    let n = spec.action_dim();
    if base.len() != n {
        return Err(LearnerError::Config(format!("base.action has {} components but {} has {n} actions", base.len(), spec.name)));
    }
    for (i, &b) in base.iter().enumerate() {
        let (lo, hi) = (spec.action_low[i], spec.action_high[i]);
        if !(b.is_finite() && (lo..=hi).contains(&b)) {
            return Err(LearnerError::Config(format!(
                "base.action[{i}] = {b} lies outside the action box [{lo}, {hi}] of {} ({})",
                spec.name, spec.action_names[i]
            )));
        }
    }
    Ok(())
}

/// What `lcrl tune` writes (best_constant.json, best_policy.json): only the
/// field a base controller needs.
#[derive(Debug, Deserialize)]
struct TunedAction {
    action: Vec<f64>,
}

/// Reads the `action` of a best_constant.json.
pub fn read_best_constant(path: &std::path::Path) -> Result<Vec<f64>, LearnerError> {
    let text = std::fs::read_to_string(path).map_err(|source| LearnerError::Io { path: path.into(), source })?;
    let tuned: TunedAction = serde_json::from_str(&text).map_err(|e| {
        LearnerError::Config(format!("{}: not a best_constant.json of `lcrl tune` (an object with an `action` list): {e}", path.display()))
    })?;
    Ok(tuned.action)
}

/// The numeric base action of a controller setting on `spec`'s environment:
/// None without a base; the best constant from `base.best_constant_file`,
/// else the one measured for a registered peg preset (docs/peg.md).
pub fn resolve_base(controller: &BaseConfig, spec: &EnvSpec) -> Result<Option<Vec<f64>>, LearnerError> {
    let base = match &controller.action {
        BaseController::None => return Ok(None),
        BaseController::Zero => vec![0.0; spec.action_dim()],
        BaseController::Action(a) => a.clone(),
        BaseController::BestConstant => match &controller.best_constant_file {
            Some(path) => read_best_constant(path)?,
            None => lcrl_sim::peg::measured_best_constant(&spec.name).map(|a| a.to_vec()).ok_or_else(|| {
                LearnerError::Config(format!(
                    "base.action = \"best-constant\": no best constant is recorded for {}; run `lcrl tune --env {}` and set \
                     base.best_constant_file (or pass --base-action best_constant.json)",
                    spec.name, spec.name
                ))
            })?,
        },
    };
    check_base(spec, &base)?;
    Ok(Some(base))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> EnvSpec {
        lcrl_sim::make_env("peg-group1").unwrap().spec().clone()
    }

    #[test]
    fn without_a_base_the_map_is_the_linear_one_onto_the_box() {
        let spec = spec();
        let map = ActionMap::plain(&spec);
        // u = −1, 0, 1 are the box's low end, centre and high end.
        let u = [-1.0f32, 0.0, 1.0, -1.0, 0.0, 1.0];
        let a = map.to_env(&u);
        assert_eq!(a, vec![-1.0, 0.5, 2.0, -1.0, 1.5, 4.0]);
        let back = map.to_normalized(&a);
        assert!(back.iter().zip(&u).all(|(x, y)| (x - y).abs() < 1e-6), "{back:?}");
    }

    #[test]
    fn a_base_is_what_u_zero_does_and_actions_stay_in_the_box() {
        let spec = spec();
        let base = [2.0, 2.0, 0.22, 0.05, 0.11, 1.61];
        let map = ActionMap::new(&spec, Some(&base)).unwrap();
        assert_eq!(map.to_env(&[0.0; 6]), base.to_vec());
        // dx sits on its upper bound: a push up is clipped, a push down moves it.
        let a = map.to_env(&[1.0, -0.5, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(a[0], 2.0);
        assert!((a[1] - (2.0 - 0.5 * 1.5)).abs() < 1e-12, "{a:?}");
        let a = map.to_env(&[-1.0; 6]);
        assert!(a.iter().zip(&spec.action_low).all(|(a, lo)| a >= lo));
        // The inverse recovers u wherever the box did not clip.
        let u = [-0.3f32, -0.2, 0.1, 0.4, -0.1, 0.2];
        let back = map.to_normalized(&map.to_env(&u));
        assert!(back.iter().zip(&u).all(|(x, y)| (x - y).abs() < 1e-6), "{back:?}");
    }

    #[test]
    fn the_residual_scale_bounds_the_policy_around_its_base() {
        let spec = spec();
        let base = [1.0, 0.5, 0.0, 1.5, 1.0, 2.0];
        let map = ActionMap::new(&spec, Some(&base)).unwrap().with_residual_scale(0.25);
        assert_eq!(map.to_env(&[0.0; 6]), base.to_vec());
        // u = ±1 reaches a quarter of each half-width (1.5 on [−1, 2],
        // 2.5 on [−1, 4]), nowhere near the box's edges.
        let up = map.to_env(&[1.0; 6]);
        let down = map.to_env(&[-1.0; 6]);
        for i in 0..6 {
            let half = 0.5 * (spec.action_high[i] - spec.action_low[i]);
            assert!((up[i] - (base[i] + 0.25 * half)).abs() < 1e-12, "{up:?}");
            assert!((down[i] - (base[i] - 0.25 * half)).abs() < 1e-12, "{down:?}");
        }
        // u beyond ±1 stays at the reach; the inverse recovers u.
        assert_eq!(map.to_env(&[3.0; 6]), up);
        let u = [-0.9f32, -0.2, 0.1, 0.4, -0.1, 0.7];
        let back = map.to_normalized(&map.to_env(&u));
        assert!(back.iter().zip(&u).all(|(x, y)| (x - y).abs() < 1e-6), "{back:?}");
        // Scale 1 is the unscaled map.
        let full = ActionMap::new(&spec, Some(&base)).unwrap();
        assert_eq!(full.clone().with_residual_scale(1.0), full);
    }

    #[test]
    fn bad_bases_are_refused_with_the_component() {
        let spec = spec();
        let err = ActionMap::new(&spec, Some(&[0.0; 5])).unwrap_err().to_string();
        assert!(err.contains("5 components"), "{err}");
        let err = ActionMap::new(&spec, Some(&[0.0, 0.0, 0.0, 9.0, 0.0, 0.0])).unwrap_err().to_string();
        assert!(err.contains("base.action[3]") && err.contains("dalpha"), "{err}");
    }

    #[test]
    fn named_bases_resolve() {
        let spec = spec();
        let mut c = BaseConfig::default();
        assert_eq!(resolve_base(&c, &spec).unwrap(), None);
        c.action = BaseController::Zero;
        assert_eq!(resolve_base(&c, &spec).unwrap(), Some(vec![0.0; 6]));
        c.action = BaseController::BestConstant;
        let measured = lcrl_sim::peg::measured_best_constant("peg-group1").unwrap().to_vec();
        assert_eq!(resolve_base(&c, &spec).unwrap(), Some(measured));
        // From a file, as `lcrl tune` writes it.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("best_constant.json");
        std::fs::write(&path, r#"{"env": "peg-group1", "action": [1.0, 1.0, 0.0, 0.5, 0.5, 0.5], "mean_return": -3.0}"#).unwrap();
        c.best_constant_file = Some(path.clone());
        assert_eq!(resolve_base(&c, &spec).unwrap(), Some(vec![1.0, 1.0, 0.0, 0.5, 0.5, 0.5]));
        std::fs::write(&path, "{}").unwrap();
        assert!(resolve_base(&c, &spec).unwrap_err().to_string().contains("not a best_constant.json"));
        // No recorded constant for an unregistered environment.
        c.best_constant_file = None;
        let lti = lcrl_sim::make_env("lti-paper").unwrap().spec().clone();
        assert!(resolve_base(&c, &lti).unwrap_err().to_string().contains("lcrl tune --env lti-paper"));
    }
}
