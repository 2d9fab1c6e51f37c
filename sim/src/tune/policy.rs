//! The headroom policy as data: a state-feedback controller of a simple
//! family and how it acts, and what a best_policy.json of `lcrl tune
//! --policy` holds. Below both the search that finds it (`super::feedback`)
//! and the evaluator of references that runs it (`crate::evaluate`).

use serde::{Deserialize, Serialize};

use crate::env::{action_of, Env};

/// The policy families `lcrl tune --policy` searches.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Family {
    /// u = clip(u₀ + K ŝ).
    Affine,
    /// Two gain matrices, switched on insertion depth.
    DepthSwitched,
}

impl Family {
    /// The name `lcrl tune --policy` takes.
    pub fn name(self) -> &'static str {
        match self {
            Family::Affine => "affine",
            Family::DepthSwitched => "depth-switched",
        }
    }
}

/// A state-feedback policy of one family.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeedbackPolicy {
    pub family: Family,
    /// u₀, in the box mapped to [−1, 1].
    pub u0: Vec<f64>,
    /// K per phase (one for affine; entry, then deep for depth-switched),
    /// each n × m, on the normalized state.
    pub gains: Vec<Vec<Vec<f64>>>,
    /// Remaining depth (mm) below which the second gains apply
    /// (depth-switched only), and the state index of the depth.
    pub switch_depth_mm: Option<f64>,
}

impl FeedbackPolicy {
    /// The action for a raw state.
    pub fn act(&self, env: &dyn Env, state: &[f64]) -> Vec<f64> {
        let s = env.normalize_state(state);
        let phase = match self.switch_depth_mm {
            // State index 2 is the remaining depth on peg tasks.
            Some(depth) if state.get(2).is_some_and(|&z| z < depth) => 1,
            _ => 0,
        };
        let k = &self.gains[phase.min(self.gains.len() - 1)];
        let u: Vec<f64> = self.u0.iter().zip(k).map(|(u0, row)| u0 + row.iter().zip(&s).map(|(g, x)| g * x).sum::<f64>()).collect();
        action_of(env.spec(), &u)
    }
}

/// The parts of a best_policy.json a reader needs: the policy and where
/// its figures were measured.
#[derive(Debug, Clone, Deserialize)]
pub struct StoredPolicy {
    pub env: String,
    pub mean_return: f64,
    pub policy: FeedbackPolicy,
    pub eval_episodes: usize,
    pub eval_seed: u64,
}
