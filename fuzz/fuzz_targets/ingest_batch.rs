//! `lcrl.v1` transition batches as the learner's gRPC front end receives
//! them: protobuf bytes, decoded, then the ingestion check
//! (learner/src/service/ingest.rs). Whatever a peer sends, the check never
//! panics, and what it accepts is what the training thread can store:
//! the run's dimensions, every number finite, episodes cut exactly.
#![no_main]

use libfuzzer_sys::fuzz_target;
use lcrl_learner::service::ingest::{Accepted, Ingest, Verdict};
use lcrl_proto::v1::TransitionBatch;
use prost::Message;

fuzz_target!(|data: &[u8]| {
    let Ok(batch) = TransitionBatch::decode(data) else { return };
    let env = lcrl_sim::make_env("lti-paper").expect("lti-paper is built in");
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    let mut ingest = Ingest::new(&batch.run_id, env, Some(2));
    let Verdict::Accept(mut accepted) = ingest.check(&batch, 3) else { return };
    for t in &accepted.transitions {
        assert_eq!((t.obs.len(), t.next_obs.len(), t.action.len()), (m, m, n));
        assert!(t.obs.iter().chain(&t.next_obs).chain(&t.action).chain([&t.reward]).chain(&t.log_prob).all(|v| v.is_finite()));
    }
    assert!(accepted.episodes.iter().all(|e| e.episode_return.is_finite()));
    // One summary per episode end (a cut is not an end).
    let ends = |a: &Accepted| a.transitions.iter().filter(|t| t.terminated || t.truncated).count();
    assert_eq!(ends(&accepted), accepted.episodes.len());
    // The budget's cut keeps whole episodes and never grows a batch.
    let (before, episodes_before) = (accepted.transitions.len(), accepted.episodes.len());
    let keep = data.len() % 3;
    let dropped = accepted.keep_episodes(keep);
    assert_eq!(accepted.transitions.len() + dropped, before);
    assert_eq!(accepted.episodes.len(), episodes_before.min(keep));
    assert_eq!(ends(&accepted), accepted.episodes.len());
    if dropped > 0 {
        // What is kept ends at an episode end (or is nothing).
        assert!(accepted.transitions.last().is_none_or(|t| t.terminated || t.truncated));
    }
    // The same batch again is a duplicate, never stored twice.
    assert_eq!(ingest.check(&batch, 3), Verdict::Duplicate);
});
