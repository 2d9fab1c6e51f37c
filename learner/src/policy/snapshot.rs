//! A policy as it travels between processes: the actor's architecture
//! (JSON) and its weights (safetensors bytes, in memory).

use std::path::Path;

use tch::Tensor;

use lcrl_proto::v1::PolicySnapshot;

use crate::algo::agent::Agent;
use crate::LearnerError;

// What a snapshot describes lives below both it and the checkpoint store,
// which records it too (learner/src/policy/architecture.rs).
pub use crate::policy::architecture::{ActorShape, Architecture, MAX_ACTOR_PARAMS, MAX_DIM, MAX_LAYERS};

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
    let meta = crate::policy::checkpoint::read_meta(dir)?;
    let path = dir.join("actor.safetensors");
    let weights = std::fs::read(&path).map_err(|source| LearnerError::Io { path, source })?;
    policy_snapshot(&meta.architecture(), weights, meta.policy_version)
}

/// A policy version as it travels: the architecture as JSON beside the
/// safetensors bytes; exploration is set by the publisher.
fn policy_snapshot(architecture: &Architecture, weights: Vec<u8>, version: u64) -> Result<PolicySnapshot, LearnerError> {
    let architecture = serde_json::to_string(architecture).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    Ok(PolicySnapshot { version, weights: weights.into(), architecture, ..Default::default() })
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
