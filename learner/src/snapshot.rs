//! A policy as it travels between processes: the actor's architecture
//! (JSON) and its weights (safetensors bytes, in memory).

use std::path::Path;

use serde::{Deserialize, Serialize};
use tch::Tensor;

use lcrl_proto::v1::PolicySnapshot;

use crate::agent::Agent;
use crate::config::{Algo, Connection, NetworkConfig};
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

/// Enough to rebuild the actor before loading its weights, and to step the
/// environment it was trained on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Architecture {
    #[serde(flatten)]
    pub shape: ActorShape,
    pub network: NetworkConfig,
    /// The base controller the actor acts around (residual RL,
    /// learner/src/action.rs); None: the plain map onto the box.
    #[serde(default)]
    pub base: Option<Vec<f64>>,
    /// The residual's reach around the base (`[base] residual_scale`,
    /// learner/src/action.rs); 1, the whole box, is left out of the JSON.
    #[serde(default = "full_reach", skip_serializing_if = "crate::config::is_full_reach")]
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
        // constant (learner/src/nets.rs builds and trains it).
        if let Some(base) = &self.base {
            if base.len() != n || base.iter().any(|b| !b.is_finite()) {
                return bad(format!("the base action must hold {n} finite numbers"));
            }
        }
        let reach = self.residual_scale;
        if !crate::action::residual_scale_fits(reach, self.base.is_some()) {
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

/// Named f32 tensors as a safetensors byte buffer.
pub fn encode_weights(named: &[(String, Tensor)]) -> Result<Vec<u8>, LearnerError> {
    // All in one copy: from a GPU each copy back waits for its queue to
    // drain, and the training thread publishes while it updates.
    let flat: Vec<Tensor> = named.iter().map(|(_, t)| t.to_kind(tch::Kind::Float).reshape([-1])).collect();
    let sizes: Vec<i64> = flat.iter().map(|t| t.numel() as i64).collect();
    let on_host = Tensor::cat(&flat, 0).to_device(tch::Device::Cpu).split_with_sizes(sizes.as_slice(), 0);
    let owned: Vec<(String, Vec<usize>, Vec<u8>)> = named
        .iter()
        .zip(on_host)
        .map(|((name, t), host)| {
            let shape = t.size().iter().map(|&d| d as usize).collect();
            let values: Vec<f32> = Vec::try_from(host)
                .map_err(|e| LearnerError::Checkpoint(format!("weights {name}: {e}")))?;
            let bytes = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            Ok((name.clone(), shape, bytes))
        })
        .collect::<Result<_, LearnerError>>()?;
    let views = owned
        .iter()
        .map(|(name, shape, bytes)| {
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape.clone(), bytes)
                .map(|view| (name.clone(), view))
                .map_err(|e| LearnerError::Checkpoint(format!("weights {name}: {e:?}")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    safetensors::tensor::serialize(views, &None).map_err(|e| LearnerError::Checkpoint(format!("encoding weights: {e:?}")))
}

/// The inverse of [`encode_weights`].
pub fn decode_weights(bytes: &[u8]) -> Result<Vec<(String, Tensor)>, LearnerError> {
    let tensors = safetensors::SafeTensors::deserialize(bytes).map_err(|e| LearnerError::Checkpoint(format!("decoding weights: {e:?}")))?;
    tensors
        .tensors()
        .into_iter()
        .map(|(name, view)| {
            Tensor::try_from(view).map(|t| (name.clone(), t)).map_err(|e| LearnerError::Checkpoint(format!("weights {name}: {e}")))
        })
        .collect()
}

/// Encodes the agent's actor as policy version `version`: what actors,
/// validation and the hand-over evaluation build their copies from.
pub fn snapshot(agent: &dyn Agent, architecture: &Architecture, version: u64) -> Result<PolicySnapshot, LearnerError> {
    policy_snapshot(architecture, encode_weights(&agent.actor_variables())?, version)
}

/// The snapshot of a `checkpoints/epNNNNNN` or `selected` folder (its
/// checkpoint.json and actor.safetensors), as version
/// `policy_version` of its metadata.
pub fn read_snapshot(dir: &Path) -> Result<PolicySnapshot, LearnerError> {
    let meta = crate::checkpoint::read_meta(dir)?;
    let path = dir.join("actor.safetensors");
    let weights = std::fs::read(&path).map_err(|source| LearnerError::Io { path, source })?;
    policy_snapshot(&meta.architecture(), weights, meta.policy_version)
}

/// A policy version as it travels: the architecture as JSON beside the
/// safetensors bytes; exploration is set by the publisher.
fn policy_snapshot(architecture: &Architecture, weights: Vec<u8>, version: u64) -> Result<PolicySnapshot, LearnerError> {
    let architecture = serde_json::to_string(architecture).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    Ok(PolicySnapshot { version, weights, architecture, ..Default::default() })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_round_trip_exactly() {
        let a = Tensor::from_slice(&[1.5f32, -2.0, 3.25, 0.0]).view([2, 2]);
        let b = Tensor::from_slice(&[7.0f32]);
        let bytes = encode_weights(&[("w0".into(), a.shallow_clone()), ("b0".into(), b.shallow_clone())]).unwrap();
        let back = decode_weights(&bytes).unwrap();
        let find = |n: &str| back.iter().find(|(name, _)| name == n).map(|(_, t)| t.shallow_clone()).unwrap();
        assert!(find("w0").equal(&a) && find("b0").equal(&b));
        assert!(decode_weights(b"not safetensors").is_err());
    }
}
