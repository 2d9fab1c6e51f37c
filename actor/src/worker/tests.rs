//! Tests of `worker`.

use super::*;
use lcrl_learner::config::{Algo, Connection, TrainConfig};

/// An untrained policy of `env` with connection graph `mask` (None: all
/// ones) over `base`, published as `version`, as the learner would.
fn untrained_policy(env: &str, algo: Algo, mask: Option<Vec<Vec<u8>>>, base: Option<Vec<f64>>, version: u64) -> Policy {
    untrained_policy_reaching(env, algo, mask, base, version, 1.0)
}

/// The same, with the residual's reach `residual_scale` around `base`.
fn untrained_policy_reaching(env: &str, algo: Algo, mask: Option<Vec<Vec<u8>>>, base: Option<Vec<f64>>, version: u64, residual_scale: f64) -> Policy {
    let made = lcrl_sim::make_env(env).unwrap();
    let (m, n) = (made.spec().state_dim(), made.spec().action_dim());
    let cfg = TrainConfig::for_env(env).0;
    let mask = mask.unwrap_or_else(|| vec![vec![1u8; m]; n]);
    let agent = lcrl_learner::algo::algorithms::make_agent(algo, Connection::Local, &cfg, &mask, m, n).unwrap();
    let shape = lcrl_learner::policy::snapshot::ActorShape { env: env.into(), algo, connection: Connection::Local, state_dim: m, action_dim: n, mask };
    let architecture = lcrl_learner::policy::snapshot::Architecture { shape, network: cfg.network.clone(), base, residual_scale };
    let snapshot = lcrl_learner::policy::snapshot::snapshot(agent.as_ref(), &architecture, version).unwrap();
    Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version).unwrap()
}

/// An untrained lti-paper policy, version 7.
fn policy(algo: Algo) -> Policy {
    untrained_policy("lti-paper", algo, Some(vec![vec![1, 0, 0], vec![1, 1, 0], vec![0, 0, 1]]), None, 7)
}

fn settings(episodes: u64) -> RolloutSettings {
    RolloutSettings { envs: 3, batch: Some(50), noise: 0.1, seed: 4, episodes: Some(episodes), run_id: "r".into(), actor_id: "a".into() }
}

/// Start states beyond the bounds (issue 82: a served environment's
/// 1e30 start ended a run): about half of x₀ ~ U[0, 2·10⁴] lie beyond
/// 10⁴. Those episodes are skipped, counted as diverged_env against the
/// budget, and never acted on nor sent; the sound ones train. An
/// environment whose every start is unsound stops the actor with the
/// reason.
#[test]
fn unsound_start_states_are_skipped_never_sent() {
    let path = std::env::temp_dir().join(format!("lcrl-unsound-starts-{}.toml", std::process::id()));
    std::fs::write(&path, "kind = \"lti\"\ne = [[0.5]]\nf = [[1.0]]\ninitial_state_low = [0.0]\ninitial_state_high = [2e4]\nq = [[1e-9]]\nepisode_steps = 5\n").unwrap();
    let env = path.to_string_lossy().to_string();
    let (batches, metrics, rollout) = roll_out(&env, 40);
    let (skipped, trained) = (metrics.diverged_env.get(), metrics.episodes.get());
    assert!(skipped >= 5 && trained >= 5 && skipped + trained >= 40, "skipped {skipped}, trained {trained}");
    assert_eq!(skipped + trained, rollout.episodes_done(), "every skipped start counts, the first ones too");
    let sent: Vec<&Transition> = batches.iter().flat_map(|b| &b.transitions).collect();
    assert!(sent.iter().all(|t| t.state[0].abs() <= 1e4), "an unsound start was acted on");
    assert_eq!(batches.iter().map(|b| b.episodes.len() as u64).sum::<u64>(), trained);
    std::fs::write(&path, "kind = \"lti\"\ne = [[0.5]]\nf = [[1.0]]\ninitial_state_low = [1e30]\ninitial_state_high = [1e30]\nepisode_steps = 5\n").unwrap();
    let policy = untrained_policy(&env, Algo::Ddpg, None, None, 1);
    let refused = Rollout::new(settings_for_one(), &policy, Exploration { uniform: false, noise: 0.1 }).err().expect("every start is unsound");
    std::fs::remove_file(&path).ok();
    assert!(refused.to_string().contains("start states in a row beyond its bounds"), "{refused}");
}

/// Two environments of the TOML `env`, an untrained DDPG policy with
/// noise 0.1, batches of 5, until `episodes` are done: every batch sent.
fn roll_out(env: &str, episodes: u64) -> (Vec<TransitionBatch>, ActorMetrics, Rollout) {
    let policy = untrained_policy(env, Algo::Ddpg, None, None, 1);
    let settings = RolloutSettings { envs: 2, batch: Some(5), episodes: Some(episodes), ..settings(episodes) };
    let mut rollout = Rollout::new(settings, &policy, Exploration { uniform: false, noise: 0.1 }).unwrap();
    let metrics = ActorMetrics::default();
    let mut batches = Vec::new();
    while !rollout.finished() {
        batches.extend(rollout.step(&policy, &metrics).unwrap());
    }
    batches.extend(rollout.take_batch(1));
    (batches, metrics, rollout)
}

fn settings_for_one() -> RolloutSettings {
    RolloutSettings { envs: 1, batch: Some(5), episodes: Some(10), ..settings(10) }
}

/// A simulator that blows up (x ← 30x + u): each episode ends at its first
/// step beyond the bounds, unsent and counted as diverged_env; the steps
/// before it go out, ending in a cut, and the actor keeps going.
#[test]
fn a_diverging_environment_ends_its_episodes_unsent() {
    let path = std::env::temp_dir().join(format!("lcrl-diverging-{}.toml", std::process::id()));
    std::fs::write(&path, "kind = \"lti\"\ne = [[30.0]]\nf = [[1.0]]\ninitial_state_low = [1.0]\ninitial_state_high = [1.0]\nepisode_steps = 20\n").unwrap();
    let env = path.to_string_lossy().to_string();
    let (batches, metrics, _) = roll_out(&env, 6);
    std::fs::remove_file(&path).ok();
    assert_eq!((metrics.diverged_env.get(), metrics.episodes.get()), (6, 0));
    let sent: Vec<&Transition> = batches.iter().flat_map(|b| &b.transitions).collect();
    assert!(batches.iter().all(|b| b.episodes.is_empty()));
    // From x = 1: x ≈ 30, then ≈ 900 (x² < 10⁶, sound), then ≈ 27,000,
    // beyond 10⁴: two steps sent per episode, and both environments
    // diverge at the same step.
    assert_eq!(sent.len(), 12);
    assert!(sent.iter().all(|t| f64::from(t.reward).abs() <= lcrl_sim::REWARD_LIMIT && t.next_state[0].abs() < 1e4));
    // Every episode's last sent step ends in a cut, never an end.
    assert!(sent.iter().all(|t| !t.terminated && !t.truncated));
    assert_eq!(sent.iter().filter(|t| t.cut && t.next_state[0].abs() > 100.0).count(), 6, "one cut per diverged episode");
}

/// A PPO policy run far off (here its std) samples u beyond the
/// learner's door; the actor sends them within it, so its batches are
/// not all refused ("bounds", issue 71), with log π of the u sent.
#[test]
fn sampled_actions_stay_within_the_learners_bound() {
    let policy = policy(Algo::Ppo);
    let mut rollout = Rollout::new(settings(4), &policy, Exploration { uniform: false, noise: 0.0 }).unwrap();
    rollout.std = vec![1e6; rollout.std.len()];
    let metrics = ActorMetrics::default();
    let mut batches = Vec::new();
    while !rollout.finished() {
        batches.extend(rollout.step(&policy, &metrics).unwrap());
    }
    let limit = lcrl_sim::SAMPLED_ACTION_BOUND as f32;
    let sampled: Vec<f32> = batches.iter().flat_map(|b| &b.transitions).flat_map(|t| t.sampled_action.clone()).collect();
    assert!(!sampled.is_empty());
    assert!(sampled.iter().all(|u| u.abs() <= limit), "a u beyond ±{limit} was sent");
    assert!(sampled.iter().filter(|u| u.abs() == limit).count() > sampled.len() / 2, "the std did not reach the bound: the test tests nothing");
}

/// Without `--batch`, DDPG sends short batches (policy lag) and PPO
/// long ones (fewer cuts in its advantage estimates).
#[test]
fn the_default_batch_follows_the_algorithm() {
    for (algo, expected) in [(Algo::Ddpg, DDPG_BATCH), (Algo::Ppo, PPO_BATCH)] {
        let policy = policy(algo);
        let settings = RolloutSettings { batch: None, episodes: Some(20), ..settings(20) };
        let mut rollout = Rollout::new(settings, &policy, Exploration { uniform: false, noise: 0.0 }).unwrap();
        let metrics = ActorMetrics::default();
        let first = loop {
            if let Some(batch) = rollout.step(&policy, &metrics).unwrap() {
                break batch;
            }
        };
        // Three environments step together: a batch closes at the
        // first whole round at or past the size.
        assert_eq!(first.transitions.len(), expected.div_ceil(3) * 3, "{algo:?}");
    }
    assert!(DDPG_BATCH < PPO_BATCH && PPO_BATCH <= lcrl_proto::shm::MAX_TRANSITIONS);
}

fn run(algo: Algo, episodes: u64) -> Vec<TransitionBatch> {
    let policy = policy(algo);
    let mut rollout = Rollout::new(settings(episodes), &policy, Exploration { uniform: false, noise: 0.0 }).unwrap();
    let metrics = ActorMetrics::default();
    let mut batches = Vec::new();
    while !rollout.finished() {
        batches.extend(rollout.step(&policy, &metrics).unwrap());
    }
    assert_eq!(metrics.episodes.get(), rollout.episodes_done());
    assert_eq!(metrics.env_steps.get(), batches.iter().map(|b| b.transitions.len() as u64).sum::<u64>());
    batches
}

/// Batch sizes a learner would refuse are refused at start, with the
/// size that fits: by bytes on wide states, by count on narrow ones.
#[test]
fn a_batch_the_learner_would_refuse_is_refused_at_start() {
    // lti-blocks-32: 64 states, 32 actions, 832 bytes a transition.
    assert!(check_batch_fits(1200, 1, 64, 32).is_ok());
    let wide = check_batch_fits(1300, 1, 64, 32).unwrap_err().to_string();
    assert!(wide.contains("lower --batch to at most 1260"), "{wide}");
    assert!(check_batch_fits(4096, 1, 3, 3).is_ok());
    let many = check_batch_fits(4096, 8, 3, 3).unwrap_err().to_string();
    assert!(many.contains("4103 transitions") && many.contains("at most 4089"), "{many}");
}

/// A batch taken early (the policy is about to change hands) holds
/// what was collected, cut where it ends, under the version given; the
/// next batch goes on from there with the next sequence number, and
/// nothing is taken twice.
#[test]
fn a_batch_taken_early_holds_what_was_collected_and_nothing_twice() {
    let policy = policy(Algo::Ddpg);
    let mut rollout = Rollout::new(settings(100), &policy, Exploration { uniform: false, noise: 0.0 }).unwrap();
    let metrics = ActorMetrics::default();
    assert!(rollout.take_batch(7).is_none(), "nothing collected yet");
    assert!(rollout.step(&policy, &metrics).unwrap().is_none());
    let early = rollout.take_batch(6).expect("the step's transitions");
    assert_eq!((early.transitions.len() as u64, early.policy_version), (metrics.env_steps.get(), 6));
    assert!(early.transitions.iter().all(|t| t.cut || t.terminated || t.truncated), "each environment's stream is cut there");
    assert!(rollout.take_batch(6).is_none(), "nothing twice");
    let next = loop {
        if let Some(batch) = rollout.step(&policy, &metrics).unwrap() {
            break batch;
        }
    };
    assert!(next.sequence > early.sequence, "sequences rise");
    assert_eq!(next.policy_version, 7);
    assert_eq!(metrics.env_steps.get(), (early.transitions.len() + next.transitions.len()) as u64);
}

/// Batches carry whole per-environment segments (each cut at its end),
/// every finished episode once, rising sequence numbers and the
/// policy's version; the last, partial batch is sent when the budget
/// ends; the same seed gives the same batches.
#[test]
fn batches_hold_whole_segments_and_every_episode() {
    for algo in [Algo::Ddpg, Algo::Ppo] {
        let batches = run(algo, 5);
        let episodes: Vec<&EpisodeSummary> = batches.iter().flat_map(|b| &b.episodes).collect();
        assert!(episodes.len() >= 5, "{algo:?}: {} episodes", episodes.len());
        let steps: u64 = batches.iter().map(|b| b.transitions.len() as u64).sum();
        let finished: u64 = episodes.iter().map(|e| u64::from(e.length)).sum();
        assert!(steps >= finished, "every finished episode's steps were sent");
        for (k, batch) in batches.iter().enumerate() {
            assert!(batch.transitions.len() >= 50 || k == batches.len() - 1, "only the last batch may be short");
            assert!(batch.transitions.iter().all(|t| t.policy_version == 7 && t.state.len() == 3 && t.action.len() == 3));
            // Contiguity: within a segment next_state is the next state.
            for pair in batch.transitions.windows(2) {
                if !(pair[0].terminated || pair[0].truncated || pair[0].cut) {
                    assert_eq!(pair[0].next_state, pair[1].state, "{algo:?}: a segment was interleaved");
                }
            }
            let last = batch.transitions.last().unwrap();
            assert!(last.terminated || last.truncated || last.cut, "each batch ends a segment");
            assert!(batch.transitions.iter().all(|t| !(t.cut && (t.terminated || t.truncated))), "a cut is not an episode end");
            if k > 0 {
                assert!(batch.sequence > batches[k - 1].sequence, "sequences rise");
            }
        }
        let again = run(algo, 5);
        let strip = |b: &[TransitionBatch]| b.iter().map(|b| (b.transitions.clone(), b.episodes.clone())).collect::<Vec<_>>();
        assert_eq!(strip(&batches), strip(&again), "{algo:?}: same seed, same batches");
    }
}

/// An untrained peg-group1 policy over its best constant with half the
/// box's reach (`[base] residual_scale = 0.5`), version 1.
fn peg_policy(algo: Algo) -> Policy {
    let base = lcrl_sim::peg::measured_best_constant("peg-group1").expect("measured").to_vec();
    untrained_policy_reaching("peg-group1", algo, None, Some(base), 1, 0.5)
}

/// The residual's reach travels in the snapshot (its architecture's
/// JSON) to the actor, whose actions then stay within it.
#[test]
fn the_residual_reach_travels_with_the_snapshot() {
    let policy = peg_policy(Algo::Ddpg);
    let env = lcrl_sim::make_env("peg-group1").unwrap();
    let spec = env.spec();
    let base = lcrl_sim::peg::measured_best_constant("peg-group1").expect("measured");
    let map = policy.action_map(env.as_ref()).unwrap();
    let (low, high) = (map.to_env(&[-1.0; 6]), map.to_env(&[1.0; 6]));
    for i in 0..6 {
        let half = 0.5 * (spec.action_high[i] - spec.action_low[i]);
        assert!((low[i] - (base[i] - 0.5 * half).max(spec.action_low[i])).abs() < 1e-12, "{low:?}");
        assert!((high[i] - (base[i] + 0.5 * half).min(spec.action_high[i])).abs() < 1e-12, "{high:?}");
    }
}

/// With several environments a batch lists its episodes in the order
/// their ends appear in its transitions (segment by segment), and only
/// real ends count: batch-end cuts carry `cut`, not `truncated`. So
/// the learner's `keep_episodes` keeps exactly the episodes it counts.
/// A peg task with a 12 N force limit, acted on uniformly at random,
/// fails at varying steps, so the three environments' ends interleave
/// in time; one batch holds all of them.
#[test]
fn a_batchs_episodes_follow_their_ends_and_cuts_are_not_ends() {
    use lcrl_learner::service::ingest::{Ingest, Verdict};
    let dir = std::env::temp_dir().join(format!("lcrl-cut-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let name = dir.join("fragile.toml").display().to_string();
    std::fs::write(&name, "kind = \"peg\"\npreset = \"peg-group1\"\n[limits]\nforce_limit_n = 12.0\n").unwrap();
    let policy = untrained_policy(&name, Algo::Ddpg, None, None, 1);

    let settings = RolloutSettings { envs: 3, batch: Some(100_000), noise: 0.3, seed: 2, episodes: Some(9), run_id: "r".into(), actor_id: "a".into() };
    let mut rollout = Rollout::new(settings, &policy, Exploration { uniform: true, noise: 0.3 }).unwrap();
    let metrics = ActorMetrics::default();
    let batch = loop {
        if let Some(batch) = rollout.step(&policy, &metrics).unwrap() {
            break batch;
        }
    };
    let lengths: Vec<u32> = batch.episodes.iter().map(|e| e.length).collect();
    assert!(lengths.iter().any(|&l| l != lengths[0]), "episodes of one length end together and would not test the order: {lengths:?}");
    // Returns summed between ends, in transition order (a segment
    // starts where an episode does: this batch is the run's first).
    let (mut returns, mut sum) = (Vec::new(), 0.0f64);
    for t in &batch.transitions {
        sum += f64::from(t.reward);
        if t.terminated || t.truncated {
            returns.push(sum);
        }
        if t.terminated || t.truncated || t.cut {
            sum = 0.0;
        }
    }
    let cuts = batch.transitions.iter().filter(|t| t.cut).count();
    assert!((1..=3).contains(&cuts), "each environment's unfinished episode is cut once: {cuts} cuts");
    assert_eq!(returns.len(), batch.episodes.len());
    for (k, (summed, sent)) in returns.iter().zip(&batch.episodes).enumerate() {
        assert!((summed - sent.episode_return).abs() < 1e-3 * sent.episode_return.abs().max(1.0), "episode {k}: {summed} vs {}", sent.episode_return);
    }
    let mut ingest = Ingest::new("r", lcrl_sim::make_env(&name).unwrap(), None);
    let Verdict::Accept(mut accepted) = ingest.check(&batch, 1) else { panic!("the batch was not accepted") };
    accepted.keep_episodes(4);
    let ends = accepted.transitions.iter().filter(|t| t.terminated || t.truncated).count();
    assert_eq!((ends, accepted.episodes.len()), (4, 4));
    assert!(accepted.transitions.last().is_some_and(|t| t.terminated || t.truncated), "the kept transitions end with the fourth episode");
    let _ = std::fs::remove_dir_all(&dir);
}

/// One transition, one meaning (docs/architecture.md): an actor's
/// episode, through the learner's ingestion, is stored as `lcrl train`'s
/// loop stores the same steps, field by field. peg-group1 around its
/// best constant puts dx and dy on the box's upper edge, so every
/// sampled u > 0 there is clipped in the applied action: the test
/// checks that such steps occur and that u, not the applied action's
/// inverse, is what both loops store.
#[test]
fn an_actors_episode_is_stored_as_lcrl_train_stores_it() {
    use lcrl_learner::service::ingest::{Ingest, Verdict};
    use lcrl_learner::algo::agent::observe;
    use lcrl_learner::run::trainer::step_env;
    let name = "peg-group1";
    for algo in [Algo::Ddpg, Algo::Ppo] {
        let mut env = lcrl_sim::make_env(name).unwrap();
        let policy = peg_policy(algo);

        // The actor: one environment, one episode, one batch.
        let settings = RolloutSettings { envs: 1, batch: Some(100_000), noise: 0.3, seed: 5, episodes: Some(1), run_id: "r".into(), actor_id: "a".into() };
        let first_seed = settings.seed_before_first_episode() + 1;
        let mut rollout = Rollout::new(settings, &policy, Exploration { uniform: false, noise: 0.3 }).unwrap();
        let metrics = ActorMetrics::default();
        let mut batch = None;
        while batch.is_none() {
            batch = rollout.step(&policy, &metrics).unwrap();
        }
        let batch = batch.unwrap();
        let map = policy.action_map(env.as_ref()).unwrap();
        let mut ingest = Ingest::new("r", lcrl_sim::make_env(name).unwrap(), None).with_actions(map.clone());
        let stored = match ingest.check(&batch, 1) {
            Verdict::Accept(accepted) => accepted.transitions,
            other => panic!("{other:?}"),
        };

        // `lcrl train`'s loop on the same episode with the same u.
        let mut state = env.reset(first_seed).unwrap();
        let mut clipped = 0;
        assert_eq!(stored.len(), batch.transitions.len());
        for (k, (sent, stored)) in batch.transitions.iter().zip(&stored).enumerate() {
            let obs = observe(env.as_ref(), &state);
            let u = &sent.sampled_action;
            let (step, next_obs) = step_env(env.as_mut(), &map, u).unwrap();
            // States cross the wire as f32: normalized, they agree to
            // f32 rounding, not bit for bit.
            let close = |a: &[f32], b: &[f32]| a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-5 * x.abs().max(1.0));
            assert!(close(&stored.obs, &obs), "{algo:?} step {k}: obs {:?} vs {obs:?}", stored.obs);
            assert!(close(&stored.next_obs, &next_obs), "{algo:?} step {k}: next_obs");
            assert_eq!(&stored.action, u, "{algo:?} step {k}: the stored action is the sampled u");
            assert_eq!(stored.reward, step.reward as f32, "{algo:?} step {k}: reward");
            assert_eq!((stored.terminated, stored.truncated, stored.cut), (step.terminated, step.truncated, false), "{algo:?} step {k}: flags");
            match algo {
                // PPO's behaviour log-probability of u under the policy that acted.
                Algo::Ppo => {
                    let std: Vec<f64> = policy.exploration_std().unwrap().iter().map(|&s| f64::from(s)).collect();
                    let expected = exploration::gaussian_log_prob(&policy.act_normalized(&obs), &std, u);
                    let sent = stored.log_prob.expect("PPO actors send log π(u|s)");
                    assert!((sent - expected).abs() <= 1e-4 * expected.abs().max(1.0), "{algo:?} step {k}: log-prob {sent} vs {expected}");
                }
                Algo::Ddpg => assert_eq!(stored.log_prob, None),
            }
            // The old path (the applied action, inverted) differs here.
            let back = map.to_normalized(&map.to_env(u));
            clipped += back.iter().zip(u).filter(|(b, u)| (*b - *u).abs() > 1e-6).count();
            state = step.state;
            if step.terminated || step.truncated {
                assert_eq!(k + 1, batch.transitions.len(), "the episode ends with the batch");
            }
        }
        assert!(clipped > 0, "{algo:?}: no step had a u the box clipped, so the test would not see the difference");
    }
}

/// During the learner's warm-up (DDPG) actions are uniform over the box,
/// not the untrained policy's near-zero output.
#[test]
fn uniform_warm_up_covers_the_box() {
    let policy = policy(Algo::Ddpg);
    let mut rollout = Rollout::new(settings(2), &policy, Exploration { uniform: true, noise: 0.0 }).unwrap();
    let metrics = ActorMetrics::default();
    let mut batches = Vec::new();
    while !rollout.finished() {
        batches.extend(rollout.step(&policy, &metrics).unwrap());
    }
    let spread = batches.iter().flat_map(|b| &b.transitions).flat_map(|t| t.action.clone()).fold(0.0f32, |m, a| m.max(a.abs()));
    let env = lcrl_sim::make_env("lti-paper").unwrap();
    let high = env.spec().action_high[0] as f32;
    assert!(spread > 0.8 * high, "uniform actions reach {spread} of a box up to {high}");
}
