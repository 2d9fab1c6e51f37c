//! PPO's unit tests: log-probabilities, advantages across cut batches,
//! batched evaluation, checkpoints mid-rollout, non-finite updates.

use super::*;
use crate::config::Connection;

/// PPO with the default settings and a local actor that sees every state.
fn local_ppo(m: usize, n: usize, seed: u64) -> Ppo {
    let mask = vec![vec![1; m]; n];
    Ppo::new(&PpoConfig::default(), &NetworkConfig::default(), AgentSetup { connection: Connection::Local, mask: &mask, state_dim: m, action_dim: n, seed, device: Device::Cpu })
}

/// The log-probability an actor sends (plain Rust, exploration.rs) is
/// the one PPO computes on tensors for its ratio, and a stored
/// transition's own log-probability is the one the rollout keeps.
#[test]
fn actor_and_learner_log_probs_agree_and_a_sent_one_is_kept() {
    let cfg = PpoConfig { log_std_init: -0.7, ..PpoConfig::default() };
    let (m, n) = (4, 3);
    let mask = vec![vec![1, 1, 0, 0], vec![0, 1, 1, 0], vec![0, 0, 1, 1]];
    let mut ppo = Ppo::new(&cfg, &NetworkConfig::default(), AgentSetup { connection: Connection::Local, mask: &mask, state_dim: m, action_dim: n, seed: 3, device: Device::Cpu });
    let obs = [0.3f32, -0.2, 0.9, 0.1];
    let std: Vec<f64> = Vec::<f32>::try_from(ppo.log_std.exp()).unwrap().iter().map(|&s| f64::from(s)).collect();
    for u in [[0.0f32, 0.0, 0.0], [1.7, -1.3, 0.2], [-3.0, 2.5, 0.9]] {
        let tensor = tch::no_grad(|| f32::try_from(ppo.log_prob(&ppo.actor.forward(&batch(&obs, m, Device::Cpu)), &batch(&u, n, Device::Cpu)).get(0)).unwrap());
        let plain = exploration::gaussian_log_prob(&ppo.act(&obs), &std, &u);
        assert!((tensor - plain).abs() < 1e-4, "{u:?}: tensor {tensor}, plain {plain}");
    }
    let t = |log_prob| Transition { obs: &obs, action: &[0.5, 0.5, 0.5], reward: -1.0, next_obs: &obs, terminated: false, truncated: false, log_prob, ..Default::default() };
    ppo.store(t(Some(-42.0)));
    ppo.store(t(None));
    ppo.evaluate_pending();
    assert_eq!(ppo.rollout.log_probs[0], -42.0, "the actor's behaviour log-probability is kept");
    assert!((ppo.rollout.log_probs[1] - exploration::gaussian_log_prob(&ppo.act(&obs), &std, &[0.5, 0.5, 0.5])).abs() < 1e-4);
}

/// The values and the missing log-probabilities are evaluated in one
/// batch when the rollout is used: each row's V(s) and V(s') are the
/// critic's one-row forward passes (V(s') = 0 after a termination), a
/// row stored without log π gets the actor's, one sent is kept, and
/// rows evaluated in two goes get the same.
#[test]
fn rollout_values_equal_one_row_evaluations() {
    tch::set_num_threads(1);
    let (m, n) = (3, 2);
    let ppo = || local_ppo(m, n, 4);
    let state = |k: usize| vec![k as f32 * 0.3 - 1.0, (k as f32).cos(), 0.5 - (k % 3) as f32];
    let store = |p: &mut Ppo, k: usize| {
        let (obs, next) = (state(k), state(k + 1));
        let log_prob = (!k.is_multiple_of(3)).then_some(-1.0);
        p.store(Transition { obs: &obs, action: &[0.2, -0.1], reward: -1.0, next_obs: &next, terminated: k == 6, truncated: false, log_prob, ..Default::default() });
    };
    let (mut at_once, mut in_two) = (ppo(), ppo());
    (0..10).for_each(|k| store(&mut at_once, k));
    at_once.advantages();
    (0..5).for_each(|k| store(&mut in_two, k));
    in_two.advantages();
    assert_eq!(in_two.rollout.values.len(), 5);
    (5..10).for_each(|k| store(&mut in_two, k));
    in_two.advantages();
    let one_row = |s: &[f32]| tch::no_grad(|| f32::try_from(at_once.critic.forward(&batch(s, m, Device::Cpu)).flatten(0, -1).get(0)).unwrap());
    let log_prob = |s: &[f32]| tch::no_grad(|| f32::try_from(at_once.log_prob(&at_once.actor.forward(&batch(s, m, Device::Cpu)), &batch(&[0.2, -0.1], n, Device::Cpu)).get(0)).unwrap());
    for p in [&at_once, &in_two] {
        let r = &p.rollout;
        assert_eq!((r.values.len(), r.next_values.len(), r.unvalued_next_obs.len(), r.unscored_rows.len()), (10, 10, 0, 0));
        for k in 0..10usize {
            let sent = if k.is_multiple_of(3) { log_prob(&state(k)) } else { -1.0 };
            assert!((r.log_probs[k] - sent).abs() < 1e-5, "log π of row {k}: {} against {sent}", r.log_probs[k]);
            assert!((r.values[k] - one_row(&state(k))).abs() < 1e-6, "V(s) of row {k}");
            let next = if k == 6 { 0.0 } else { one_row(&state(k + 1)) };
            assert!((r.next_values[k] - next).abs() < 1e-6, "V(s') of row {k}");
        }
    }
}

/// A checkpoint taken mid-rollout holds its pending rows as they are
/// (a resumed run evaluates them in the same batch as an uninterrupted
/// one), and they load back to the same rollout; a file of an earlier
/// build, every row evaluated and without the pending lists, loads; one
/// whose columns disagree is refused by name.
#[test]
fn a_rollout_saved_mid_way_loads_back_and_a_broken_one_is_refused() {
    tch::set_num_threads(1);
    let (m, n) = (3, 2);
    let ppo = || local_ppo(m, n, 6);
    let mut saved = ppo();
    for k in 0..7 {
        let obs = [k as f32 * 0.1, -0.3, 0.2];
        let log_prob = (k % 2 == 0).then_some(-1.5);
        saved.store(Transition { obs: &obs, action: &[0.1, 0.2], reward: -1.0, next_obs: &obs, terminated: k == 3, truncated: false, log_prob, ..Default::default() });
    }
    let dir = tempfile::tempdir().unwrap();
    saved.save(dir.path(), false).unwrap();
    let mut loaded = ppo();
    loaded.load(dir.path()).unwrap();
    assert_eq!((loaded.rollout.unscored_rows.len(), loaded.rollout.unvalued_next_obs.len()), (3, 7 * m), "pending rows stay pending");
    saved.evaluate_pending();
    loaded.evaluate_pending();
    let columns = |p: &Ppo| (p.rollout.log_probs.clone(), p.rollout.values.clone(), p.rollout.next_values.clone());
    assert_eq!(columns(&loaded), columns(&saved));

    // An earlier build's file: every row evaluated, no pending lists.
    saved.save(dir.path(), false).unwrap();
    let path = dir.path().join("agent.json");
    let read = || -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap() };
    let mut state = read();
    let rollout = state["rollout"].as_object_mut().unwrap();
    assert!(rollout.remove("unvalued_next_obs").is_some() && rollout.remove("unscored_rows").is_some());
    std::fs::write(&path, state.to_string()).unwrap();
    let mut earlier = ppo();
    earlier.load(dir.path()).unwrap();
    earlier.evaluate_pending();
    assert_eq!(columns(&earlier), columns(&saved));

    // Broken files, each refused with what is wrong, before anything loads.
    type Break = fn(&mut serde_json::Value);
    let breaks: [(&str, Break); 3] = [
        ("7 numbers in next_values, 6 expected for its 6 rows", |r| drop(r["values"].as_array_mut().unwrap().pop())),
        ("lists row 99 as unscored", |r| r["unscored_rows"] = serde_json::json!([99])),
        ("joins row 5 to row 2", |r| r["joins"] = serde_json::json!([[5, 2]])),
    ];
    let whole = read();
    for (message, break_it) in breaks {
        let mut state = whole.clone();
        break_it(&mut state["rollout"]);
        std::fs::write(&path, state.to_string()).unwrap();
        // Another seed's weights: loading the file's would change them.
        let mut fresh = local_ppo(m, n, 7);
        let before: Vec<Tensor> = fresh.actor_opt.buffers().iter().map(|t| t.copy()).collect();
        let error = fresh.load(dir.path()).unwrap_err().to_string();
        assert!(error.contains("agent.json") && error.contains(message), "{message}: {error}");
        assert!(fresh.actor_opt.buffers().iter().zip(&before).all(|(a, b)| a.equal(b)), "{message}: weights loaded before the refusal");
    }
}

/// Two actors' episodes arriving cut into interleaved batches get the
/// advantages they get stored whole, one after the other (as
/// `lcrl train` stores an episode); a cut whose stream does not go on
/// from its state (a batch lost in between), or goes on only in
/// another actor's steps, ends the sum as a truncation does.
#[test]
fn advantages_run_on_across_an_actors_batch_ends() {
    let (m, n) = (3, 2);
    let ppo = || local_ppo(m, n, 5);
    // Stream s, step k: distinct states; the episode ends at its last step.
    let len = 12;
    let state = |s: usize, k: usize| vec![(s * 31 + k) as f32 * 0.07 - 1.0, ((s + 2) * k) as f32 * 0.05, (k as f32).sin()];
    let store = |ppo: &mut Ppo, s: usize, k: usize, cut: bool, stream: u64| {
        let (obs, next) = (state(s, k), state(s, k + 1));
        let action = [0.1 * k as f32, -0.2];
        ppo.store(Transition { obs: &obs, action: &action, reward: -(k as f32) * 0.3 - s as f32, next_obs: &next, terminated: false, truncated: k + 1 == len, log_prob: Some(-1.0), cut, stream });
    };
    let mut whole = ppo();
    for s in 0..2 {
        (0..len).for_each(|k| store(&mut whole, s, k, false, 0));
    }
    let (expected, _) = whole.advantages();

    // Actor 0 sends steps 0–4, 5–8, 9–11; actor 1 steps 0–3, 4–11.
    let (a, b) = (crate::service::ingest::stream_of("actor-0"), crate::service::ingest::stream_of("actor-1"));
    let batches = [(0, a, 0..5), (1, b, 0..4), (0, a, 5..9), (1, b, 4..len), (0, a, 9..len)];
    let mut cut = ppo();
    let mut rows = Vec::new();
    for (s, stream, steps) in batches {
        for k in steps.clone() {
            store(&mut cut, s, k, k + 1 == steps.end && steps.end < len, stream);
            rows.push(s * len + k);
        }
    }
    let (advantages, _) = cut.advantages();
    for (row, &whole_row) in rows.iter().enumerate() {
        assert_eq!(advantages[row], expected[whole_row], "stream {} step {}", whole_row / len, whole_row % len);
    }
    assert!(cut.rollout.open_cuts.is_empty() && cut.rollout.joins.len() == 3);
    assert_eq!((cut.counters.cuts, cut.counters.cuts_joined), (3, 3));

    // Actor 0's middle batch lost: its first cut ends the sum at step 4,
    // and the later rows are their own segment. Actor 1's first batch
    // sent as actor 0's: its cut opens in another stream and stays open.
    let mut lost = ppo();
    for k in 0..5 {
        store(&mut lost, 0, k, k == 4, a);
    }
    for k in 9..len {
        store(&mut lost, 0, k, false, a);
    }
    for k in 0..4 {
        store(&mut lost, 1, k, k == 3, a);
    }
    for k in 4..len {
        store(&mut lost, 1, k, false, b);
    }
    let (advantages, _) = lost.advantages();
    let r = &lost.rollout;
    let gamma = PpoConfig::default().gamma as f32;
    let delta = |t: usize| r.rewards[t] + gamma * r.next_values[t] - r.values[t];
    assert_eq!(advantages[4], delta(4), "an unjoined cut bootstraps and stops");
    assert_eq!(advantages[11], delta(11), "so does a cut whose stream goes on in another actor");
    assert!(r.joins.is_empty() && r.open_cuts.len() == 2);
    assert_eq!((lost.counters.cuts, lost.counters.cuts_joined), (2, 0));
    assert_ne!(advantages[3], delta(3), "inside a segment the sum runs on");

    // A peer marking an episode's last step cut as well opens nothing.
    let mut ended = ppo();
    store(&mut ended, 0, len - 1, true, a);
    assert!(ended.rollout.open_cuts.is_empty());
}

/// Issue 71: a rollout of states and rewards of 3e38 (finite, but
/// their sums and squares are not) makes every minibatch's loss
/// non-finite. Each update is skipped and counted, no weight or moment
/// moves, and a clean rollout trains again.
#[test]
fn an_update_with_a_non_finite_loss_is_skipped_and_counted() {
    tch::set_num_threads(1);
    let cfg = PpoConfig { rollout_steps: 8, epochs: 2, minibatch_size: 4, ..PpoConfig::default() };
    let (m, n) = (2, 1);
    let mask = vec![vec![1; m]; n];
    let ppo = || Ppo::new(&cfg, &NetworkConfig::default(), AgentSetup { connection: Connection::Global, mask: &mask, state_dim: m, action_dim: n, seed: 9, device: Device::Cpu });
    let weights = |p: &Ppo| [p.actor_opt.buffers(), p.critic_opt.buffers()].concat().iter().map(|t| t.copy()).collect::<Vec<_>>();
    let feed = |p: &mut Ppo, value: f32| {
        for k in 0..8 {
            let obs = [value, k as f32 / 8.0];
            p.store(Transition { obs: &obs, action: &[0.1], reward: value, next_obs: &obs, terminated: k == 7, truncated: false, log_prob: Some(-1.0), ..Default::default() });
        }
        p.train_step();
    };
    let mut huge = ppo();
    let before = weights(&huge);
    feed(&mut huge, 3e38);
    let c = huge.counters();
    assert_eq!((c.skipped_updates, c.updates, c.critic_updates), (4, 0, 0), "2 epochs of 2 minibatches, all skipped");
    assert!(weights(&huge).iter().zip(&before).all(|(a, b)| a.equal(b)), "a weight or moment moved");
    let mut clean = ppo();
    feed(&mut clean, 0.5);
    let c = clean.counters();
    assert_eq!((c.skipped_updates, c.updates, c.critic_updates), (0, 4, 4));
    assert!(!weights(&clean).iter().zip(&before).all(|(a, b)| a.equal(b)), "a clean rollout trains");
}
