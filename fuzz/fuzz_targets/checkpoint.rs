//! Checkpoint folders (`lcrl eval`, `lcrl serve`, a resumed run's
//! policy): `checkpoint.json` and `actor.safetensors` as any file could
//! hold them. The input is split at a 2-byte length into the two files.
//! Loading refuses what does not fit with a message; what loads acts.
#![no_main]

use libfuzzer_sys::fuzz_target;
use lcrl_learner::policy::trained::Policy;

fuzz_target!(|data: &[u8]| {
    if data.len() < 2 {
        return;
    }
    let split = (usize::from(u16::from_le_bytes([data[0], data[1]])) + 2).min(data.len());
    let meta = String::from_utf8_lossy(&data[2..split]);
    let weights = &data[split..];
    let Ok(policy) = Policy::from_checkpoint(&meta, weights) else { return };
    let shape = &policy.architecture.shape;
    let action = policy.act_normalized(&vec![0.5; shape.state_dim]);
    assert_eq!(action.len(), shape.action_dim);
});
