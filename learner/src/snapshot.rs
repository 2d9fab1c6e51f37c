//! A policy as it travels between processes: the actor's architecture
//! (JSON) and its weights (safetensors bytes, in memory).

use serde::{Deserialize, Serialize};
use tch::Tensor;

use crate::config::{Algo, Connection, NetworkConfig};
use crate::LearnerError;

/// Enough to rebuild the actor before loading its weights, and to step the
/// environment it was trained on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Architecture {
    pub env: String,
    pub algo: Algo,
    pub connection: Connection,
    pub state_dim: usize,
    pub action_dim: usize,
    /// The actor's connection mask (n × m).
    pub mask: Vec<Vec<u8>>,
    pub network: NetworkConfig,
}

/// Named f32 tensors as a safetensors byte buffer.
pub fn encode_weights(named: &[(String, Tensor)]) -> Result<Vec<u8>, LearnerError> {
    let owned: Vec<(String, Vec<usize>, Vec<u8>)> = named
        .iter()
        .map(|(name, t)| {
            let shape = t.size().iter().map(|&d| d as usize).collect();
            let values: Vec<f32> = Vec::try_from(t.to_kind(tch::Kind::Float).flatten(0, -1).to_device(tch::Device::Cpu))
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
