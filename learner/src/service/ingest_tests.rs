//! Tests of what the learner accepts (service/ingest.rs).
use super::*;
use lcrl_proto::v1::Transition;

fn batch(actor: &str, sequence: u64, state: Vec<f32>) -> TransitionBatch {
    TransitionBatch {
        run_id: "run-a".into(),
        actor_id: actor.into(),
        sequence,
        episode_id: 1,
        policy_version: 3,
        transitions: vec![Transition { state: state.clone(), action: vec![0.5, -1.0, 1.0], reward: -1.0, next_state: state, terminated: false, truncated: false, policy_version: 0, ..Default::default() }],
        ..Default::default()
    }
}

fn ingest(staleness: Option<u64>) -> Ingest {
    Ingest::new("run-a", lcrl_sim::make_env("lti-paper").unwrap(), staleness)
}

#[test]
fn a_batch_is_cut_after_the_last_episode_the_budget_allows() {
    let t = |end: bool| AgentTransition { obs: vec![], action: vec![], log_prob: None, reward: 0.0, next_obs: vec![], terminated: end, truncated: false, cut: false, policy_version: 0 };
    let e = || EpisodeSummary { episode_return: -1.0, length: 2, ..Default::default() };
    // Two episode ends (after transitions 2 and 4) and a started third.
    let batch = || Accepted { transitions: vec![t(false), t(true), t(false), t(true), t(false)], episodes: vec![e(), e()], policy_version: 1, stream: 0 };
    let mut one = batch();
    assert_eq!(one.keep_episodes(1), 3);
    assert_eq!((one.transitions.len(), one.episodes.len()), (2, 1));
    let mut all = batch();
    assert_eq!(all.keep_episodes(2), 0);
    assert_eq!(all.transitions.len(), 5, "within the budget nothing is cut");
    // A cut (the actor's batch end, mid-episode) is not an end.
    let mut cut = batch();
    cut.transitions[0].cut = true;
    assert_eq!(cut.keep_episodes(1), 3);
    let mut none = batch();
    assert_eq!(none.keep_episodes(0), 5);
    assert!(none.transitions.is_empty() && none.episodes.is_empty());
}

/// Finite but huge values are refused at the door, each by the bound
/// it breaks; values at the bounds pass (issue 71: one batch of 3e38
/// states turned every weight to NaN).
#[test]
fn values_beyond_the_environments_bounds_are_refused() {
    let mut ingest = ingest(None);
    let limit = lcrl_sim::STATE_LIMIT as f32;
    assert!(matches!(ingest.check(&batch("a1", 1, vec![limit, -limit, 0.0]), 3), Verdict::Accept(_)));
    let huge = batch("a1", 2, vec![0.0, 3e38, 0.0]);
    match ingest.check(&huge, 3) {
        Verdict::Reject { reason: "bounds", message } => assert!(message.contains("state component 1"), "{message}"),
        other => panic!("{other:?}"),
    }
    let mut next = batch("a1", 3, vec![0.0; 3]);
    next.transitions[0].next_state[2] = limit * 1.01;
    assert!(matches!(ingest.check(&next, 3), Verdict::Reject { reason: "bounds", .. }));
    let mut reward = batch("a1", 4, vec![0.0; 3]);
    reward.transitions[0].reward = -2e6;
    assert!(matches!(ingest.check(&reward, 3), Verdict::Reject { reason: "bounds", .. }));
    let mut sampled = batch("a1", 5, vec![0.0; 3]);
    sampled.transitions[0].sampled_action = vec![0.0, 1e12, 0.0];
    assert!(matches!(ingest.check(&sampled, 3), Verdict::Reject { reason: "bounds", .. }));
    assert_eq!(ingest.rejected.get("bounds"), Some(&4));
    assert_eq!(ingest.accepted, 1);
}

/// A summary must agree with the rewards the batch holds for its
/// episode: exactly when the episode lies wholly in the batch, within
/// REWARD_LIMIT a step for the steps sent before.
#[test]
fn episode_returns_must_agree_with_their_rewards() {
    let step = |reward: f32, end: bool, cut: bool| Transition { state: vec![0.0; 3], action: vec![0.0; 3], reward, next_state: vec![0.0; 3], terminated: end, cut, ..Default::default() };
    let summary = |episode_return: f64, length: u32| EpisodeSummary { episode_return, length, ..Default::default() };
    let sent = |sequence: u64, transitions: Vec<Transition>, episodes: Vec<EpisodeSummary>| TransitionBatch { run_id: "run-a".into(), actor_id: "a".into(), sequence, transitions, episodes, ..Default::default() };
    let mut ingest = ingest(None);
    // An episode that began in an earlier batch (2 of 5 steps here),
    // then a whole one of 2 steps.
    let honest = sent(1, vec![step(-1.0, false, false), step(-0.5, true, false), step(-0.25, false, false), step(-0.25, true, false)], vec![summary(-4.5, 5), summary(-0.5, 2)]);
    assert!(matches!(ingest.check(&honest, 0), Verdict::Accept(_)));
    // The whole episode must claim exactly its sum and its length.
    let inflated = sent(2, vec![step(-1.0, true, false), step(-1.0, false, false), step(-1.0, true, false)], vec![summary(-1.0, 1), summary(1e30, 2)]);
    match ingest.check(&inflated, 0) {
        Verdict::Reject { reason: "returns", message } => assert!(message.starts_with("episode 1 claims return 1000000000000000000000000000000 over 2 steps"), "{message}"),
        other => panic!("{other:?}"),
    }
    let longer = sent(3, vec![step(-1.0, true, false), step(-1.0, false, false), step(-1.0, true, false)], vec![summary(-1.0, 1), summary(-2.0, 3)]);
    assert!(matches!(ingest.check(&longer, 0), Verdict::Accept(_)), "the first episode's start may lie before this batch");
    let shorter = sent(4, vec![step(-1.0, false, false), step(-1.0, true, false)], vec![summary(-2.0, 1)]);
    assert!(matches!(ingest.check(&shorter, 0), Verdict::Reject { reason: "returns", .. }), "fewer steps than the batch holds");
    // After a cut (another environment's stream), the unseen steps
    // bound the claim: 3 unseen steps allow 3 × REWARD_LIMIT more.
    let bound = 3.0 * lcrl_sim::REWARD_LIMIT;
    let within = sent(5, vec![step(-1.0, false, true), step(-1.0, true, false)], vec![summary(-1.0 - bound, 4)]);
    assert!(matches!(ingest.check(&within, 0), Verdict::Accept(_)));
    let beyond = sent(6, vec![step(-1.0, false, true), step(-1.0, true, false)], vec![summary(-1.0 - 1.01 * bound, 4)]);
    assert!(matches!(ingest.check(&beyond, 0), Verdict::Reject { reason: "returns", .. }));
    assert_eq!(ingest.rejected.get("returns"), Some(&(3 + 2 + 2)));
}

/// A sequence far ahead of the clock would make every later batch of
/// that actor id a duplicate (issue 71: 2⁶⁴−1 silently discarded an
/// honest actor's 337k transitions).
#[test]
fn a_sequence_far_ahead_of_the_clock_is_refused() {
    let mut ingest = ingest(None);
    assert!(matches!(ingest.check(&batch("a1", u64::MAX, vec![0.0; 3]), 3), Verdict::Reject { reason: "sequence", .. }));
    // Clock-numbered and zero-based actors both pass, and the refused
    // batch left the honest actor's numbering alone.
    assert!(matches!(ingest.check(&batch("a1", now_micros(), vec![0.0; 3]), 3), Verdict::Accept(_)));
    assert!(matches!(ingest.check(&batch("a2", 1, vec![0.0; 3]), 3), Verdict::Accept(_)));
    assert!(matches!(ingest.check(&batch("a1", now_micros() + 1_000_000, vec![0.0; 3]), 3), Verdict::Accept(_)));
}

#[test]
fn accepts_and_normalizes() {
    let mut ingest = ingest(None);
    match ingest.check(&batch("a1", 1, vec![0.1, 0.2, 0.3]), 3) {
        Verdict::Accept(accepted) => {
            assert_eq!(accepted.transitions[0].action, vec![0.5, -1.0, 1.0]); // bounds are ±1
            assert_eq!(accepted.transitions[0].obs, vec![0.1, 0.2, 0.3]);
        }
        other => panic!("{other:?}"),
    }
    assert!(ingest.rejected.is_empty());
}

#[test]
fn the_sampled_action_is_stored_as_sent_and_the_applied_one_only_without_it() {
    let mut ingest = ingest(None);
    // u outside [−1, 1] (a PPO sample) whose applied action the box clipped.
    let mut sent = batch("a1", 1, vec![0.1, 0.2, 0.3]);
    sent.transitions[0].sampled_action = vec![1.7, -1.0, 0.25];
    sent.transitions[0].log_prob = Some(-2.5);
    match ingest.check(&sent, 3) {
        Verdict::Accept(accepted) => {
            assert_eq!(accepted.transitions[0].action, vec![1.7, -1.0, 0.25]);
            assert_eq!(accepted.transitions[0].log_prob, Some(-2.5));
        }
        other => panic!("{other:?}"),
    }
    let mut short = batch("a1", 2, vec![0.0; 3]);
    short.transitions[0].sampled_action = vec![0.5];
    assert!(matches!(ingest.check(&short, 3), Verdict::Reject { reason: "dimensions", .. }));
    let mut nan = batch("a1", 3, vec![0.0; 3]);
    nan.transitions[0].log_prob = Some(f32::NAN);
    assert!(matches!(ingest.check(&nan, 3), Verdict::Reject { reason: "non_finite", .. }));
}

#[test]
fn rejects_bad_batches_and_counts_them() {
    let mut ingest = ingest(None);
    let mut wrong_run = batch("a1", 1, vec![0.0; 3]);
    wrong_run.run_id = "run-b".into();
    assert!(matches!(ingest.check(&wrong_run, 3), Verdict::Reject { reason: "unknown_run", .. }));
    assert!(matches!(ingest.check(&batch("a1", 2, vec![0.0; 4]), 3), Verdict::Reject { reason: "dimensions", .. }));
    assert!(matches!(ingest.check(&batch("a1", 3, vec![0.0, f32::NAN, 0.0]), 3), Verdict::Reject { reason: "non_finite", .. }));
    let mut nan_return = batch("a1", 4, vec![0.0; 3]);
    nan_return.transitions[0].terminated = true;
    nan_return.episodes.push(EpisodeSummary { episode_return: f64::NAN, length: 1, ..Default::default() });
    assert!(matches!(ingest.check(&nan_return, 3), Verdict::Reject { reason: "non_finite", .. }));
    let mut nan_force = batch("a1", 4, vec![0.0; 3]);
    nan_force.transitions[0].terminated = true;
    nan_force.episodes.push(EpisodeSummary { episode_return: -1.0, length: 1, peak_force_n: Some(f64::INFINITY), ..Default::default() });
    assert!(matches!(ingest.check(&nan_force, 3), Verdict::Reject { reason: "non_finite", .. }));
    let mut nan_term = batch("a1", 4, vec![0.0; 3]);
    nan_term.transitions[0].terminated = true;
    let terms = lcrl_proto::v1::ReturnTerms { failure: f64::NAN, ..Default::default() };
    nan_term.episodes.push(EpisodeSummary { episode_return: -1.0, length: 1, return_terms: Some(terms), ..Default::default() });
    assert!(matches!(ingest.check(&nan_term, 3), Verdict::Reject { reason: "non_finite", .. }));
    // Summaries and ends must pair up: a summary without an end, an end
    // without a summary (a cut is not an end and needs none).
    let mut no_end = batch("a1", 5, vec![0.0; 3]);
    no_end.episodes.push(EpisodeSummary { episode_return: -1.0, length: 1, ..Default::default() });
    assert!(matches!(ingest.check(&no_end, 3), Verdict::Reject { reason: "episodes", .. }));
    let mut no_summary = batch("a1", 6, vec![0.0; 3]);
    no_summary.transitions[0].truncated = true;
    assert!(matches!(ingest.check(&no_summary, 3), Verdict::Reject { reason: "episodes", .. }));
    assert_eq!(ingest.rejected.values().sum::<u64>(), 8);
    assert_eq!(ingest.rejected["episodes"], 2);
    // A rejected batch does not consume its sequence number.
    assert!(matches!(ingest.check(&batch("a1", 1, vec![0.0; 3]), 3), Verdict::Accept(_)));
    let mut cut = batch("a1", 2, vec![0.0; 3]);
    cut.transitions[0].cut = true;
    assert!(matches!(ingest.check(&cut, 3), Verdict::Accept(_)), "a cut needs no summary");
}

/// A restarted learner's versions count from its checkpoint again:
/// an on-policy learner drops a batch of its previous process however
/// new its version looks; an off-policy one stores it; a client that
/// names no incarnation is not checked.
#[test]
fn batches_of_another_incarnation_are_stale_for_an_on_policy_learner() {
    let mut ppo = ingest(Some(0)).with_incarnation(77);
    let mut old = batch("a1", 1, vec![0.0; 3]);
    old.incarnation = 76;
    old.policy_version = 9;
    assert_eq!(ppo.check(&old, 3), Verdict::Stale);
    assert_eq!(ppo.rejected.get("stale_incarnation"), Some(&1));
    let mut own = batch("a1", 2, vec![0.0; 3]);
    own.incarnation = 77;
    assert!(matches!(ppo.check(&own, 3), Verdict::Accept(_)));
    assert!(matches!(ppo.check(&batch("a2", 1, vec![0.0; 3]), 3), Verdict::Accept(_)), "0: not said, not checked");
    let mut ddpg = ingest(None).with_incarnation(77);
    old.sequence = 3;
    assert!(matches!(ddpg.check(&old, 3), Verdict::Accept(_)));
}

/// Actor ids are kept: one too long is refused, and beyond MAX_ACTORS
/// a new one is refused until an old one has been silent long enough.
#[test]
fn actor_ids_are_bounded_in_length_and_number() {
    let mut ingest = ingest(None);
    let long = "x".repeat(lcrl_runtime::limits::MAX_ACTOR_ID_BYTES + 1);
    assert!(matches!(ingest.check(&batch(&long, 1, vec![0.0; 3]), 3), Verdict::Reject { reason: "actor_id", .. }));
    assert!(matches!(ingest.check(&batch(&long[1..], 1, vec![0.0; 3]), 3), Verdict::Accept(_)));
    for k in 1..MAX_ACTORS {
        assert!(matches!(ingest.check(&batch(&format!("a{k}"), 1, vec![0.0; 3]), 3), Verdict::Accept(_)));
    }
    assert!(matches!(ingest.check(&batch("one-too-many", 1, vec![0.0; 3]), 3), Verdict::Reject { reason: "actors", .. }));
    assert!(matches!(ingest.check(&batch("a7", 2, vec![0.0; 3]), 3), Verdict::Accept(_)), "known actors go on");
    // An actor silent past the limit gives its place up.
    let forgotten = ingest.last_seen.get_mut("a1").unwrap();
    *forgotten = forgotten.checked_sub(ACTOR_SILENCE_TO_FORGET).expect("a machine up for ten minutes");
    assert!(matches!(ingest.check(&batch("one-too-many", 1, vec![0.0; 3]), 3), Verdict::Accept(_)));
    assert!(!ingest.sequences().contains_key("a1"));
    assert_eq!(ingest.sequences().len(), MAX_ACTORS);
    assert_eq!(ingest.rejected.get("actors"), Some(&1));
}

#[test]
fn duplicates_and_stale_batches_are_not_stored() {
    let mut ingest = ingest(Some(1));
    assert!(matches!(ingest.check(&batch("a1", 5, vec![0.0; 3]), 3), Verdict::Accept(_)));
    assert_eq!(ingest.check(&batch("a1", 5, vec![0.0; 3]), 3), Verdict::Duplicate);
    assert_eq!(ingest.check(&batch("a1", 4, vec![0.0; 3]), 3), Verdict::Duplicate);
    assert!(matches!(ingest.check(&batch("a2", 5, vec![0.0; 3]), 3), Verdict::Accept(_)));
    // Version 3 batches are two versions old at version 5: beyond the bound.
    assert_eq!(ingest.check(&batch("a1", 6, vec![0.0; 3]), 5), Verdict::Stale);
    assert_eq!(ingest.rejected.get("duplicate"), Some(&2));
    assert_eq!(ingest.rejected.get("stale"), Some(&1));
}

/// An actor id belongs to the live stream that first sent it (issue 71:
/// a hijacker's batch under an honest actor's id). Another stream's batch
/// under it is refused and counted, the holder goes on, and once the
/// holder's stream ends the id may come back on a new one (an actor that
/// reconnected); shared memory (no stream) cannot take a held id either.
#[test]
fn an_actor_id_is_bound_to_the_stream_that_holds_it() {
    let mut ingest = ingest(None);
    let (honest, hijacker) = (Origin { stream: 7, peer: None }, Origin { stream: 8, peer: None });
    assert!(matches!(ingest.check_from(&batch("a1", 1, vec![0.0; 3]), 3, honest), Verdict::Accept(_)));
    match ingest.check_from(&batch("a1", 1_000, vec![0.0; 3]), 3, hijacker) {
        Verdict::Reject { reason: "actor_id_bound", message } => assert!(message.contains("--actor-id"), "{message}"),
        other => panic!("{other:?}"),
    }
    assert!(matches!(ingest.check(&batch("a1", 2_000, vec![0.0; 3]), 3), Verdict::Reject { reason: "actor_id_bound", .. }));
    assert!(matches!(ingest.check_from(&batch("a1", 2, vec![0.0; 3]), 3, honest), Verdict::Accept(_)), "the holder's next batch is stored");
    assert_eq!(ingest.rejected.get("actor_id_bound"), Some(&2));
    ingest.release_stream(7);
    assert!(matches!(ingest.check_from(&batch("a1", 3, vec![0.0; 3]), 3, hijacker), Verdict::Accept(_)), "a released id binds anew");
    assert!(matches!(ingest.check_from(&batch("a1", 2, vec![0.0; 3]), 3, hijacker), Verdict::Duplicate), "its sequences stay");
}

/// An honest actor whose connection broke without the learner noticing
/// comes back on a new stream while the old one is still held: with its
/// key it is taken at once and the binding moves; another key, or none, is
/// still refused. Streams released by a predicate (shared-memory
/// publishers that left) free their ids.
#[test]
fn the_holders_key_moves_its_binding_to_a_new_stream() {
    let mut ingest = ingest(None);
    let keyed = |sequence: u64, key: u64| TransitionBatch { actor_key: key, ..batch("a1", sequence, vec![0.0; 3]) };
    let on = |stream: u64| Origin { stream, peer: None };
    assert!(matches!(ingest.check_from(&keyed(1, 0xfeed), 3, on(7)), Verdict::Accept(_)));
    assert!(matches!(ingest.check_from(&keyed(2, 0xfeed), 3, on(9)), Verdict::Accept(_)), "the same actor on a new stream");
    for (key, stream) in [(0, 8), (0xbad, 8), (0, 7)] {
        assert!(matches!(ingest.check_from(&keyed(3, key), 3, on(stream)), Verdict::Reject { reason: "actor_id_bound", .. }), "key {key:x} on stream {stream}");
    }
    ingest.release_stream(7);
    assert!(matches!(ingest.check_from(&keyed(3, 0), 3, on(8)), Verdict::Reject { reason: "actor_id_bound", .. }), "stream 9 holds it now");
    ingest.release_streams(|stream| stream >= 9);
    assert!(matches!(ingest.check_from(&keyed(3, 0xbad), 3, on(8)), Verdict::Accept(_)), "released with its publisher");
}

/// One peer address brings at most MAX_ACTORS_PER_PEER ids into the
/// table; its known ids go on, its silent ids make room for new ones,
/// other peers still get places, and loopback (IPv4-mapped included) is
/// not counted.
#[test]
fn one_peer_cannot_fill_the_actor_table() {
    let mut ingest = ingest(None);
    let peer = |ip: &str| Origin { stream: 1, peer: Some(ip.parse().unwrap()) };
    for k in 0..MAX_ACTORS_PER_PEER {
        assert!(matches!(ingest.check_from(&batch(&format!("f{k}"), 1, vec![0.0; 3]), 3, peer("203.0.113.9")), Verdict::Accept(_)), "id {k}");
    }
    match ingest.check_from(&batch("one-more", 1, vec![0.0; 3]), 3, peer("203.0.113.9")) {
        Verdict::Reject { reason: "actors_per_peer", message } => assert!(message.contains("203.0.113.9"), "{message}"),
        other => panic!("{other:?}"),
    }
    assert!(matches!(ingest.check_from(&batch("f0", 2, vec![0.0; 3]), 3, peer("203.0.113.9")), Verdict::Accept(_)), "a known id goes on");
    // Ids of restarted actors fall silent: once one has been silent long
    // enough, the peer's next new id takes its place.
    let long_ago = std::time::Instant::now().checked_sub(ACTOR_SILENCE_TO_FORGET).unwrap();
    ingest.last_seen.insert("f1".into(), long_ago);
    assert!(matches!(ingest.check_from(&batch("restarted", 1, vec![0.0; 3]), 3, peer("203.0.113.9")), Verdict::Accept(_)), "a silent id makes room");
    assert!(!ingest.sequences().contains_key("f1"));
    assert!(matches!(ingest.check_from(&batch("other", 1, vec![0.0; 3]), 3, Origin { stream: 2, ..peer("198.51.100.4") }), Verdict::Accept(_)));
    for (k, ip) in ["127.0.0.1", "::1", "::ffff:127.0.0.1"].into_iter().cycle().take(MAX_ACTORS_PER_PEER + 3).enumerate() {
        let origin = Origin { stream: 3, ..peer(ip) };
        assert!(matches!(ingest.check_from(&batch(&format!("local{k}"), 1, vec![0.0; 3]), 3, origin), Verdict::Accept(_)), "loopback id {k}");
    }
}
