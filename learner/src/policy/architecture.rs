//! What identifies a trained actor: the environment and its sizes, the
//! algorithm, the connection and its mask ([`ActorShape`]), and with the
//! network and the base controller enough to rebuild it ([`Architecture`]).
//! A policy on the wire (snapshot.rs) and a checkpoint's metadata
//! (checkpoint.rs) both hold it, so it sits below both; it depends on the
//! configuration alone.

use serde::{Deserialize, Serialize};

use crate::config::{is_full_reach, residual_scale_fits, Algo, Connection, NetworkConfig};
use crate::LearnerError;

/// What identifies a run's actor: the environment and its sizes, the
/// algorithm, the connection and its mask. A published policy's
/// [`Architecture`] and a checkpoint's metadata both hold it (flattened:
/// their JSON lists these fields at the top level).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActorShape {
    pub env: String,
    pub algo: Algo,
    pub connection: Connection,
    pub state_dim: usize,
    pub action_dim: usize,
    /// The actor's connection mask (n × m).
    pub mask: Vec<Vec<u8>>,
}

impl ActorShape {
    /// The actor network's wiring (algo::agent::build_actor builds it).
    pub fn layout(&self) -> crate::algo::agent::ActorLayout<'_> {
        crate::algo::agent::ActorLayout { connection: self.connection, mask: &self.mask, state_dim: self.state_dim, action_dim: self.action_dim }
    }
}

/// Enough to rebuild the actor before loading its weights, and to step the
/// environment it was trained on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Architecture {
    #[serde(flatten)]
    pub shape: ActorShape,
    pub network: NetworkConfig,
    /// The base controller the actor acts around (residual RL,
    /// learner/src/policy/action.rs); None: the plain map onto the box.
    #[serde(default)]
    pub base: Option<Vec<f64>>,
    /// The residual's reach around the base (`[base] residual_scale`,
    /// learner/src/policy/action.rs); 1, the whole box, is left out of the JSON.
    #[serde(default = "full_reach", skip_serializing_if = "is_full_reach")]
    pub residual_scale: f64,
}

fn full_reach() -> f64 {
    1.0
}

/// Largest dimensions and layer widths a snapshot may ask an actor to
/// build: far above any real controller, far below what would exhaust
/// memory (a hostile or corrupt snapshot is refused, not allocated).
pub const MAX_DIM: usize = 4096;
pub const MAX_LAYERS: usize = 16;
/// 200 MB of f32 weights.
pub const MAX_ACTOR_PARAMS: usize = 50_000_000;

impl Architecture {
    /// Checks what a peer could get wrong before anything is built from it.
    pub fn validate(&self) -> Result<(), LearnerError> {
        let bad = |why: String| Err(LearnerError::Mismatch(format!("policy architecture: {why}")));
        let (m, n) = (self.shape.state_dim, self.shape.action_dim);
        if !(1..=MAX_DIM).contains(&m) || !(1..=MAX_DIM).contains(&n) {
            return bad(format!("state_dim {m} and action_dim {n} must lie in 1..={MAX_DIM}"));
        }
        if self.shape.mask.len() != n || self.shape.mask.iter().any(|row| row.len() != m || row.iter().any(|&v| v > 1)) {
            return bad(format!("the mask must be {n}×{m} of 0/1"));
        }
        // A local mask row of zeros is allowed: CS3 may find an action that
        // moves no state above the cut, and its subnetwork then learns a
        // constant (learner/src/algo/nets.rs builds and trains it).
        if let Some(base) = &self.base {
            if base.len() != n || base.iter().any(|b| !b.is_finite()) {
                return bad(format!("the base action must hold {n} finite numbers"));
            }
        }
        let reach = self.residual_scale;
        if !residual_scale_fits(reach, self.base.is_some()) {
            return bad(format!("residual_scale {reach} must lie in (0, 1], and be 1 without a base action"));
        }
        let net = &self.network;
        for (name, widths) in [("global_hidden", &net.global_hidden), ("subnet_hidden", &net.subnet_hidden), ("critic_hidden", &net.critic_hidden)] {
            if widths.is_empty() || widths.len() > MAX_LAYERS || widths.iter().any(|&w| !(1..=MAX_DIM).contains(&w)) {
                return bad(format!("network.{name} must list 1..={MAX_LAYERS} widths in 1..={MAX_DIM}"));
            }
        }
        let widths = if self.shape.connection == Connection::Global { &net.global_hidden } else { &net.subnet_hidden };
        let (nets, outputs) = if self.shape.connection == Connection::Global { (1, n) } else { (n, 1) };
        let layers: Vec<usize> = std::iter::once(m).chain(widths.iter().copied()).chain([outputs]).collect();
        let params = nets * layers.windows(2).map(|w| w[0] * w[1]).sum::<usize>();
        if params > MAX_ACTOR_PARAMS {
            return bad(format!("an actor of {params} weights is larger than the {MAX_ACTOR_PARAMS} this build accepts"));
        }
        Ok(())
    }
}
