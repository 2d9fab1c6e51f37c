//! The DDPG update rule and its stabilizers, on small networks.

use super::*;
use crate::config::{Connection, TrainConfig};
use rand::Rng;

/// Table I's settings with 16-unit networks, for the update-rule tests.
fn small_nets() -> TrainConfig {
    let mut cfg = TrainConfig::default();
    cfg.network.global_hidden = vec![16];
    cfg.network.critic_hidden = vec![16];
    cfg
}

/// The actor's weights, flattened in the variables' sorted order.
fn actor_weights(agent: &Ddpg) -> Vec<f32> {
    agent.actor_variables().iter().flat_map(|(_, t)| Vec::<f32>::try_from(t.flatten(0, -1)).expect("f32 tensor")).collect()
}

/// A global agent on 2 states and 1 action.
fn agent(ddpg: &DdpgConfig, cfg: &TrainConfig) -> Ddpg {
    Ddpg::new(ddpg, &cfg.network, AgentSetup { connection: Connection::Global, mask: &[vec![1, 1]], state_dim: 2, action_dim: 1, seed: 5, device: Device::Cpu })
}

/// Fills `agent`'s buffer with `data.0` one-step episodes (s uniform in
/// [−1, 1]², a uniform in ±`data.1`, reward `reward(a)`), runs `updates`
/// updates and returns its actions on 20 fixed probe states.
fn probe_after_updates(mut agent: Ddpg, seed: u64, data: (usize, f32), reward: impl Fn(f32) -> f32, updates: usize) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for _ in 0..data.0 {
        let s = [rng.random_range(-1.0f32..1.0), rng.random_range(-1.0f32..1.0)];
        let a: f32 = rng.random_range(-data.1..data.1);
        agent.replay.push(&s, &[a], reward(a), &s, true).unwrap();
    }
    for _ in 0..updates {
        agent.update();
    }
    (0..20).map(|k| agent.act(&[k as f32 / 10.0 - 1.0, 1.0 - k as f32 / 10.0])[0]).collect()
}

/// `critic_warmup_updates`: the actor (the base controller, under one)
/// stays exactly as it started for that many updates while the critics
/// learn, and moves on the first update after.
#[test]
fn actor_waits_for_the_critics_head_start() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    let ddpg = DdpgConfig { batch_size: 8, warmup_steps: 0, critic_warmup_updates: 6, policy_delay: 2, ..cfg.ddpg };
    let mut agent = agent(&ddpg, &cfg);
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    for _ in 0..64 {
        let s = [rng.random_range(-1.0f32..1.0), rng.random_range(-1.0f32..1.0)];
        let a: f32 = rng.random_range(-1.0..1.0);
        agent.replay.push(&s, &[a], -(s[0] * s[0]) - a * a, &s, false).unwrap();
    }
    let critic = |agent: &Ddpg| -> Vec<f32> {
        crate::algo::agent::sorted_variables(&agent.critics[0].vs).iter().flat_map(|(_, t)| Vec::<f32>::try_from(t.flatten(0, -1)).expect("f32 tensor")).collect()
    };
    let (actor0, critic0) = (actor_weights(&agent), critic(&agent));
    for _ in 0..6 {
        agent.update();
    }
    assert_eq!(actor_weights(&agent), actor0, "the actor moved during the critics' head start");
    assert_ne!(critic(&agent), critic0, "the critic did not learn during the head start");
    // Update 7 is odd: no actor step under policy_delay = 2; update 8 is one.
    agent.update();
    assert_eq!(actor_weights(&agent), actor0);
    agent.update();
    assert_ne!(actor_weights(&agent), actor0, "the actor did not move after the head start");
}

/// `proximal_l2`: the actor's first step is unchanged by it (the actor
/// equals its target then, so the term and its gradient are 0), and
/// over later steps on the same batches it keeps the actor's actions
/// closer to where they started.
#[test]
fn the_trust_region_slows_the_actor_without_changing_its_first_step() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    // The best action is a = 0.8 everywhere: the actor must move.
    let run = |proximal_l2: f64, updates: usize| -> Vec<f32> {
        let ddpg = DdpgConfig { batch_size: 16, warmup_steps: 0, proximal_l2, tau: 0.01, ..cfg.ddpg.clone() };
        probe_after_updates(agent(&ddpg, &cfg), 6, (256, 1.0), |a| -(a - 0.8) * (a - 0.8), updates)
    };
    let start = run(0.0, 0);
    assert_eq!(run(0.0, 1), run(100.0, 1), "the first step differs");
    let moved = |actions: &[f32]| actions.iter().zip(&start).map(|(a, b)| (a - b).abs()).sum::<f32>() / start.len() as f32;
    let (free, held) = (moved(&run(0.0, 300)), moved(&run(100.0, 300)));
    assert!(free > 0.2, "without the trust region the actor moves toward 0.8: {free}");
    assert!(held < 0.5 * free, "the trust region did not slow the actor: {held} against {free}");
}

/// Warm-up actions spread uniformly over the box.
#[test]
fn warm_up_acts_uniformly() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    let ddpg = DdpgConfig { warmup_steps: 10, noise_start: 0.1, ..cfg.ddpg.clone() };
    let mut agent = agent(&ddpg, &cfg);
    assert_eq!(agent.exploration(0).map(|(uniform, _)| uniform), Some(true));
    let actions: Vec<f32> = (0..2000).flat_map(|_| agent.explore(&[0.3, -0.2], 0)).collect();
    let rms = (actions.iter().map(|a| a * a).sum::<f32>() / actions.len() as f32).sqrt();
    assert!(rms > 0.5, "uniform over [-1, 1] has an rms of about 0.58, got {rms}");
}

/// The update rule, without the on-policy feedback loop: on exploratory
/// data of s' = s + a with r = −(s² + 0.1a²), DDPG's actor must move to
/// the optimal gain. With γ = 0.95 the Riccati solution is P ≈ 1.09 and
/// a* = −γP/(0.1 + γP)·s ≈ −0.91·s. Also with twin critics: the minimum
/// of two critics in y must not bias the gain away from the optimum.
#[test]
fn update_rule_finds_the_optimal_gain_on_exploratory_data() {
    // One intra-op thread, as training runs use: libtorch's default (one
    // per core) spin-waits against the other test process on 2 cores.
    tch::set_num_threads(1);
    for twin_critics in [false, true] {
        let mut cfg = TrainConfig::default();
        cfg.network.global_hidden = vec![64, 64];
        cfg.network.critic_hidden = vec![64, 64];
        let ddpg = DdpgConfig { actor_lr: 1e-3, critic_lr: 1e-3, tau: 0.01, gamma: 0.95, batch_size: 128, warmup_steps: 0, twin_critics, ..cfg.ddpg };
        let mut agent = Ddpg::new(&ddpg, &cfg.network, AgentSetup { connection: Connection::Global, mask: &[vec![1]], state_dim: 1, action_dim: 1, seed: 3, device: Device::Cpu });
        assert_eq!(agent.critics.len(), if twin_critics { 2 } else { 1 });
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for _ in 0..5000 {
            let s: f32 = rng.random_range(-2.0..2.0);
            let a: f32 = rng.random_range(-1.0..1.0);
            agent.replay.push(&[s], &[a], -(s * s + 0.1 * a * a), &[s + a], false).unwrap();
        }
        for _ in 0..4000 {
            agent.update();
        }
        for s in [-0.5f32, -0.25, 0.25, 0.5] {
            let a = agent.act(&[s])[0];
            assert!((a + 0.91 * s).abs() < 0.1, "twin critics {twin_critics}: μ({s}) = {a}, optimum {}", -0.91 * s);
        }
    }
}

/// Issue 71: a buffer holding states of 3e38 (finite, but their squares
/// are not) makes an update's numbers infinite. The check after the 8th
/// update finds it; all 8 are undone and counted, every weight is finite
/// and as it was, and updates on a clean buffer go on.
#[test]
fn an_update_that_leaves_a_non_finite_number_is_undone_and_counted() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    let ddpg = DdpgConfig { batch_size: 8, warmup_steps: 0, policy_delay: 1, ..cfg.ddpg };
    let mut agent = agent(&ddpg, &cfg);
    for _ in 0..16 {
        agent.replay.push(&[3e38, -3e38], &[0.5], 1.0, &[3e38, 3e38], false).unwrap();
    }
    let (actor0, buffers0) = (actor_weights(&agent), agent.copy_of_buffers());
    for _ in 0..8 {
        agent.update();
    }
    assert_eq!(agent.counters().skipped_updates, 8);
    assert_eq!((agent.counters().updates, agent.counters().critic_updates), (0, 0), "an undone update is not counted as run");
    assert_eq!(actor_weights(&agent), actor0);
    assert!(agent.copy_of_buffers().equal(&buffers0), "a buffer changed");
    assert!(agent.buffers_finite());
    // A clean buffer trains again.
    let mut clean = self::agent(&ddpg, &cfg);
    for k in 0..16 {
        clean.replay.push(&[k as f32 / 16.0, 0.5], &[0.1], -1.0, &[0.5, 0.5], false).unwrap();
    }
    clean.update();
    assert_eq!((clean.counters().skipped_updates, clean.counters().updates), (0, 1));
    assert_ne!(actor_weights(&clean), actor_weights(&self::agent(&ddpg, &cfg)));
}

/// Issue 72: with `policy_delay` 2, six updates are six critic steps and
/// three actor steps, and the counters name them apart.
#[test]
fn critic_and_actor_updates_are_counted_apart() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    let ddpg = DdpgConfig { batch_size: 8, warmup_steps: 0, critic_warmup_updates: 0, policy_delay: 2, ..cfg.ddpg };
    let mut agent = agent(&ddpg, &cfg);
    for k in 0..16 {
        agent.replay.push(&[k as f32 / 16.0, 0.5], &[0.1], -1.0, &[0.5, 0.5], false).unwrap();
    }
    for _ in 0..6 {
        agent.update();
    }
    let c = agent.counters();
    assert_eq!((c.critic_updates, c.updates, c.skipped_updates), (6, 3, 0));
}

/// A rewind goes back to the last rewind point (every 32 updates): the
/// updates since then are undone with the one that failed, and the counts
/// say so.
#[test]
fn a_failed_update_rewinds_to_the_last_rewind_point() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    let ddpg = DdpgConfig { batch_size: 8, warmup_steps: 0, critic_warmup_updates: 0, policy_delay: 1, ..cfg.ddpg };
    let mut agent = agent(&ddpg, &cfg);
    for k in 0..16 {
        agent.replay.push(&[k as f32 / 16.0, 0.5], &[0.1], -1.0, &[0.5, 0.5], false).unwrap();
    }
    for _ in 0..32 {
        agent.update();
    }
    let at_point = agent.copy_of_buffers();
    for _ in 0..8 {
        agent.update();
    }
    // An infinity in the actor's weights: no update after it is finite.
    // The check after update 48 finds it and undoes the 16 since 32.
    tch::no_grad(|| {
        let _ = agent.actor_opt.buffers()[0].get(0).fill_(f64::INFINITY);
    });
    for _ in 0..8 {
        agent.update();
    }
    let c = agent.counters();
    assert_eq!((c.updates, c.critic_updates, c.skipped_updates), (32, 32, 16));
    assert!(agent.copy_of_buffers().equal(&at_point));
    agent.update();
    assert_eq!(agent.counters().updates, 33, "training goes on from the rewind point");
}
