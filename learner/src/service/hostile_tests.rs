//! Hostile input, property-tested: arbitrary transition batches (gRPC),
//! arbitrary bytes in shared-memory samples, arbitrary policy snapshots.
//! Each is either accepted with exactly the dimensions the run needs and
//! finite numbers, or refused and counted; nothing panics, nothing of a
//! refused batch is stored.

use proptest::prelude::*;

use crate::policy::trained::Policy;
use crate::service::ingest::{Ingest, Verdict};
use lcrl_proto::shm::{TransitionSample, MAX_EPISODES, MAX_TRANSITIONS};
use lcrl_proto::v1::{EpisodeSummary, Transition, TransitionBatch};

fn value() -> impl Strategy<Value = f32> {
    prop_oneof![4 => -10.0f32..10.0, 1 => any::<f32>(), 1 => Just(f32::NAN), 1 => Just(f32::INFINITY)]
}

/// Mostly the right sizes (lti-paper: 3 states, 3 actions), sometimes not.
fn vector() -> impl Strategy<Value = Vec<f32>> {
    prop_oneof![3 => proptest::collection::vec(value(), 3), 1 => proptest::collection::vec(value(), 0..9)]
}

fn transition() -> impl Strategy<Value = Transition> {
    (vector(), vector(), value(), vector(), any::<(bool, bool)>(), any::<u64>()).prop_map(|(state, action, reward, next_state, (terminated, truncated), policy_version)| Transition {
        state,
        action,
        reward,
        next_state,
        terminated,
        truncated,
        policy_version,
        ..Default::default()
    })
}

fn batch() -> impl Strategy<Value = TransitionBatch> {
    (
        prop_oneof![4 => Just("run-a".to_string()), 1 => ".{0,40}"],
        ".{0,80}",
        any::<u64>(),
        any::<u64>(),
        proptest::collection::vec(transition(), 0..40),
        proptest::collection::vec((any::<f64>(), any::<u32>(), any::<Option<bool>>()), 0..5),
        prop::bool::weighted(0.75),
    )
        .prop_map(|(run_id, actor_id, sequence, policy_version, transitions, summaries, paired)| {
            let mut episodes: Vec<EpisodeSummary> = summaries.into_iter().map(|(episode_return, length, success)| EpisodeSummary { episode_return, length, success, ..Default::default() }).collect();
            // Mostly one summary per episode end, as actors send them (so
            // that most batches reach the checks after that one).
            if paired {
                let ends = transitions.iter().filter(|t| t.terminated || t.truncated).count();
                episodes.resize(ends, EpisodeSummary { episode_return: -1.0, length: 1, ..Default::default() });
            }
            TransitionBatch { run_id, actor_id, sequence, episode_id: 0, policy_version, transitions, episodes, ..Default::default() }
        })
}

fn ingest() -> Ingest {
    Ingest::new("run-a", lcrl_sim::make_env("lti-paper").expect("registered"), Some(2))
}

/// Checks one batch and the invariants of its verdict.
fn check_invariants(ingest: &mut Ingest, batch: &TransitionBatch) -> Result<(), TestCaseError> {
    let (accepted_before, refused_before) = (ingest.accepted, ingest.rejected.values().sum::<u64>());
    match ingest.check(batch, 5) {
        Verdict::Accept(accepted) => {
            prop_assert_eq!(accepted.transitions.len(), batch.transitions.len());
            let ends = accepted.transitions.iter().filter(|t| t.terminated || t.truncated).count();
            prop_assert_eq!(ends, accepted.episodes.len(), "one summary per episode end");
            prop_assert_eq!(ingest.accepted, accepted_before + batch.transitions.len() as u64);
            for t in &accepted.transitions {
                prop_assert!(t.obs.len() == 3 && t.next_obs.len() == 3 && t.action.len() == 3);
                prop_assert!(t.obs.iter().chain(&t.next_obs).chain(&t.action).all(|v| v.is_finite()) && t.reward.is_finite());
                prop_assert!(t.action.iter().all(|a| (-1.0..=1.0).contains(a)));
            }
        }
        _ => {
            prop_assert_eq!(ingest.accepted, accepted_before, "a refused batch stores nothing");
            prop_assert!(ingest.rejected.values().sum::<u64>() > refused_before, "every refusal is counted");
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_batches_are_accepted_whole_or_refused_and_counted(batches in proptest::collection::vec(batch(), 1..6)) {
        let mut ingest = ingest();
        for batch in &batches {
            check_invariants(&mut ingest, batch)?;
        }
    }

    #[test]
    fn garbage_in_shared_memory_samples_is_clamped_and_checked(
        count in any::<u32>(),
        state_dim in any::<u32>(),
        action_dim in any::<u32>(),
        episode_count in any::<u32>(),
        actor_id in proptest::collection::vec(any::<u8>(), 64),
        pokes in proptest::collection::vec((any::<usize>(), value()), 0..64),
    ) {
        let empty = TransitionBatch { run_id: "run-a".into(), ..Default::default() };
        let mut sample = TransitionSample::from_batch(&empty).expect("an empty batch fits");
        (sample.count, sample.state_dim, sample.action_dim, sample.episode_count) = (count, state_dim, action_dim, episode_count);
        sample.actor_id.copy_from_slice(&actor_id);
        for (at, v) in pokes {
            let k = at % sample.states.len();
            sample.states[k] = v;
            sample.actions[at % sample.actions.len()] = v;
            sample.rewards[at % MAX_TRANSITIONS] = v;
        }
        let batch = sample.to_batch("run-a");
        prop_assert!(batch.transitions.len() <= MAX_TRANSITIONS && batch.episodes.len() <= MAX_EPISODES);
        check_invariants(&mut ingest(), &batch)?;
    }
}

/// A real snapshot's architecture, as JSON.
fn architecture() -> serde_json::Value {
    serde_json::json!({
        "env": "lti-paper", "algo": "ppo", "connection": "local", "state_dim": 3, "action_dim": 3,
        "mask": [[1, 0, 0], [1, 1, 0], [0, 0, 1]],
        "network": { "global_hidden": [8], "subnet_hidden": [4], "critic_hidden": [8], "activation": "relu" }
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn hostile_policy_snapshots_are_refused_not_built(
        field in 0usize..7,
        number in prop_oneof![Just(0u64), Just(1u64 << 40), any::<u64>(), 1u64..10],
        weights in proptest::collection::vec(any::<u8>(), 0..256),
    ) {
        let mut a = architecture();
        match field {
            0 => a["state_dim"] = number.into(),
            1 => a["action_dim"] = number.into(),
            2 => a["mask"] = serde_json::json!([[number, 0], [1]]),
            3 => a["network"]["subnet_hidden"] = serde_json::json!([number, number]),
            4 => a["network"]["global_hidden"] = serde_json::json!(vec![8; (number % 64) as usize]),
            // A reach without a base, or outside (0, 1].
            5 => a["residual_scale"] = serde_json::json!(number as f64 / 4.0),
            _ => a["env"] = serde_json::json!(number),
        }
        // Arbitrary bytes as weights: refused unless they decode, fit the
        // architecture and are finite.
        match Policy::from_snapshot(&a.to_string(), &weights, 1) {
            Ok(policy) => {
                // This architecture has no base: only the full reach fits.
                prop_assert!(field != 5 || number == 4, "residual_scale {} accepted without a base", number as f64 / 4.0);
                prop_assert!(policy.act_normalized(&[0.1, 0.2, 0.3]).iter().all(|v| v.is_finite()))
            }
            Err(e) => prop_assert!(!e.to_string().is_empty()),
        }
    }
}

#[test]
fn snapshot_weights_with_nan_or_the_wrong_shape_are_refused() {
    use tch::Tensor;
    let a = architecture().to_string();
    let good = Policy::from_snapshot(&a, &valid_weights(None), 1);
    assert!(good.is_ok(), "{:?}", good.err());
    let nan = valid_weights(Some(f32::NAN));
    assert!(Policy::from_snapshot(&a, &nan, 1).err().map(|e| e.to_string()).unwrap_or_default().contains("non-finite"));
    let wrong = crate::policy::snapshot::encode_weights(&[("nets.0.layer0.weight".into(), Tensor::zeros([2, 2], (tch::Kind::Float, tch::Device::Cpu)))]).expect("encodes");
    assert!(Policy::from_snapshot(&a, &wrong, 1).is_err());
}

/// The weights of a freshly built actor of `architecture()`, optionally
/// with one value replaced.
fn valid_weights(poison: Option<f32>) -> Vec<u8> {
    weights_of(architecture(), poison)
}

/// The weights of a freshly built actor of `architecture`.
fn weights_of(architecture: serde_json::Value, poison: Option<f32>) -> Vec<u8> {
    let arch: crate::policy::snapshot::Architecture = serde_json::from_value(architecture).expect("valid architecture");
    let vs = tch::nn::VarStore::new(tch::Device::Cpu);
    let _actor = crate::algo::agent::build_actor(&vs.root(), arch.shape.layout(), &arch.network, 0);
    let named: Vec<(String, tch::Tensor)> = vs
        .variables()
        .into_iter()
        .enumerate()
        .map(|(k, (name, t))| {
            let t = t.detach().copy();
            if let (0, Some(v)) = (k, poison) {
                let _ = t.view(-1).get(0).fill_(f64::from(v));
            }
            (name, t)
        })
        .collect();
    crate::policy::snapshot::encode_weights(&named).expect("encodes")
}

/// A checkpoint folder is a file anyone can edit: `checkpoint.json` is
/// checked as a peer's snapshot is, before a network is built from it (it
/// was not before, and a 2^40-wide state would have been allocated).
#[test]
fn checkpoints_are_checked_as_snapshots_are() {
    let arch: crate::policy::snapshot::Architecture = serde_json::from_value(architecture()).expect("valid architecture");
    let shape = arch.shape.clone();
    let mut config = crate::config::TrainConfig::default();
    config.network = arch.network.clone();
    let meta = crate::policy::checkpoint::CheckpointMeta::start(&shape.env, shape.algo, shape.connection, shape.state_dim, shape.action_dim, shape.mask.clone(), config);
    let good = Policy::from_checkpoint(&serde_json::to_string(&meta).expect("writes"), &valid_weights(None));
    assert!(good.is_ok(), "{:?}", good.err());
    let mut huge = serde_json::to_value(&meta).expect("writes");
    huge["state_dim"] = (1u64 << 40).into();
    let err = Policy::from_checkpoint(&huge.to_string(), &valid_weights(None)).err().map(|e| e.to_string()).unwrap_or_default();
    assert!(err.contains("state_dim"), "{err}");
    let nan = Policy::from_checkpoint(&serde_json::to_string(&meta).expect("writes"), &valid_weights(Some(f32::NAN)));
    assert!(nan.err().map(|e| e.to_string()).unwrap_or_default().contains("non-finite"));
}

/// CS3 may leave an action without an edge (peg-group2 at T = 1 leaves dz
/// unconnected): that actor's subnetwork sees no state and outputs a
/// learned constant; snapshots and checkpoints of it load and act.
#[test]
fn a_local_actor_with_an_unconnected_action_loads_and_acts() {
    let mut a = architecture();
    a["mask"] = serde_json::json!([[0, 0, 0], [1, 1, 0], [0, 0, 1]]);
    let policy = Policy::from_snapshot(&a.to_string(), &weights_of(a.clone(), None), 1).expect("loads");
    let first = policy.act_normalized(&[0.1, 0.2, 0.3]);
    let second = policy.act_normalized(&[-0.5, 0.9, 0.3]);
    assert!(first.iter().chain(&second).all(|v| v.is_finite()));
    assert_eq!(first[0], second[0], "the unconnected action ignores the state");
    assert_ne!(first[1], second[1]);
}
