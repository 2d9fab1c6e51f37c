//! Whether a set of weights holds only finite numbers (issue 71): what
//! the learner checks before it publishes a policy or writes a checkpoint,
//! and what resume checks before it trusts one.

use crate::LearnerError;

/// Whether every F32 and F64 value in safetensors `bytes` is finite
/// (other dtypes, such as counters, are not weights and are skipped).
pub fn all_finite(bytes: &[u8]) -> Result<bool, LearnerError> {
    let tensors = safetensors::SafeTensors::deserialize(bytes).map_err(|e| LearnerError::Checkpoint(format!("decoding weights: {e:?}")))?;
    Ok(tensors.tensors().iter().all(|(_, view)| match view.dtype() {
        safetensors::Dtype::F32 => view.data().chunks_exact(4).all(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]).is_finite()),
        safetensors::Dtype::F64 => view.data().chunks_exact(8).all(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]).is_finite()),
        _ => true,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::snapshot::encode_weights;
    use tch::Tensor;

    #[test]
    fn a_nan_or_infinity_anywhere_makes_weights_not_finite() {
        let fine = encode_weights(&[("w".into(), Tensor::from_slice(&[1.0f32, -3e38, 0.0]))]).unwrap();
        assert!(all_finite(&fine).unwrap());
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let bytes = encode_weights(&[("ok".into(), Tensor::from_slice(&[1.0f32])), ("w".into(), Tensor::from_slice(&[1.0f32, bad]))]).unwrap();
            assert!(!all_finite(&bytes).unwrap(), "{bad}");
        }
        assert!(all_finite(b"garbage").is_err());
    }
}
