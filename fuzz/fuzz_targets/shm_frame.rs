//! The shared-memory transport's frames (learner/src/service/shm.rs): any
//! bytes a publisher could leave in a `TransitionSample` are unpacked
//! without panicking, into a batch within the sample's limits, which the
//! ingestion check then takes as it takes a gRPC batch.
#![no_main]

use libfuzzer_sys::fuzz_target;
use lcrl_learner::service::ingest::{Ingest, Verdict};
use lcrl_proto::shm::{TransitionSample, MAX_ACTION, MAX_EPISODES, MAX_STATE, MAX_TRANSITIONS};

fuzz_target!(|data: &[u8]| {
    // A frame is the sample's bytes as iceoryx2 delivers them: whatever
    // the input does not cover stays zero.
    let mut bytes = vec![0u8; std::mem::size_of::<TransitionSample>()];
    let len = data.len().min(bytes.len());
    bytes[..len].copy_from_slice(&data[..len]);
    // SAFETY: TransitionSample is #[repr(C)] of integers, floats and arrays
    // of them: every bit pattern is a valid value, and the buffer has its size.
    let sample: TransitionSample = unsafe { std::ptr::read_unaligned(bytes.as_ptr().cast()) };
    let batch = sample.to_batch("run");
    assert!(batch.transitions.len() <= MAX_TRANSITIONS && batch.episodes.len() <= MAX_EPISODES);
    assert!(batch.transitions.iter().all(|t| t.state.len() <= MAX_STATE && t.action.len() <= MAX_ACTION && t.state.len() == t.next_state.len()));
    // What unpacks packs back to the same batch.
    if let Ok(again) = TransitionSample::from_batch(&batch) {
        let round = again.to_batch("run");
        assert_eq!(format!("{round:?}"), format!("{batch:?}"));
    }
    let env = lcrl_sim::make_env("lti-paper").expect("lti-paper is built in");
    let mut ingest = Ingest::new("run", env, None);
    if let Verdict::Accept(accepted) = ingest.check(&batch, 0) {
        assert_eq!(accepted.transitions.len(), batch.transitions.len());
    }
});
