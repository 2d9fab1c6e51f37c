//! The DDPG update rule and its stabilizers, on small networks.

use super::*;
use crate::config::TrainConfig;
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
    Ddpg::new(ddpg, &cfg.network, Connection::Global, &[vec![1, 1]], 2, 1, 5, Device::Cpu)
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

/// `temporal_smoothness` (CAPS): the best action follows the state
/// (a = 0.8·s₁) and every transition's next state is the mirror −s, so
/// a plain actor's actions on s and −s end far apart, and the term pulls
/// them together. Where the next state is the state itself the term and
/// its gradient are 0, and the run is the plain one to the bit.
#[test]
fn temporal_smoothness_pulls_the_actions_of_consecutive_states_together() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    let run = |temporal_smoothness: f64, mirrored: bool| -> (Vec<f32>, f32) {
        let ddpg = DdpgConfig { batch_size: 32, warmup_steps: 0, temporal_smoothness, ..cfg.ddpg.clone() };
        let mut agent = agent(&ddpg, &cfg);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..512 {
            let s = [rng.random_range(-1.0f32..1.0), rng.random_range(-1.0f32..1.0)];
            let a: f32 = rng.random_range(-1.0..1.0);
            let next = if mirrored { [-s[0], -s[1]] } else { s };
            agent.replay.push(&s, &[a], -(a - 0.8 * s[0]).powi(2), &next, true).unwrap();
        }
        for _ in 0..400 {
            agent.update();
        }
        let probes: Vec<[f32; 2]> = (0..20).map(|k| [k as f32 / 10.0 - 1.0, 0.5 - k as f32 / 20.0]).collect();
        let gap = probes.iter().map(|s| (agent.act(s)[0] - agent.act(&[-s[0], -s[1]])[0]).abs()).sum::<f32>() / probes.len() as f32;
        (actor_weights(&agent), gap)
    };
    assert_eq!(run(0.0, false).0, run(10.0, false).0, "with s′ = s the term changed the updates");
    let ((_, free), (_, smooth)) = (run(0.0, true), run(10.0, true));
    assert!(free > 0.5, "the plain actor did not follow the state: gap {free} between s and −s");
    assert!(smooth < 0.5 * free, "the term did not pull consecutive actions together: gap {smooth} against {free}");
}

/// `critic_disagreement`: the buffer holds only actions near 0 with a
/// reward that rises with a, so both critics praise larger actions but
/// agree only inside the band they saw. The plain actor follows the
/// first critic out of the band; a pessimistic one stays nearer it.
#[test]
fn pessimism_toward_the_critics_disagreement_keeps_the_actor_near_its_data() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    let run = |critic_disagreement: f64, updates: usize| -> Vec<f32> {
        let ddpg = DdpgConfig { batch_size: 32, warmup_steps: 0, twin_critics: true, critic_disagreement, ..cfg.ddpg.clone() };
        probe_after_updates(agent(&ddpg, &cfg), 11, (512, 0.1), |a| a, updates)
    };
    let outside = |actions: &[f32]| actions.iter().map(|a| (a.abs() - 0.1).max(0.0)).sum::<f32>() / actions.len() as f32;
    // The critics' disagreement grows slowly outside their data (both
    // extrapolate the slope they fitted): here κ = 2 held the actor by
    // 1% after 400 updates, κ = 10 by 75%.
    let (free, held) = (outside(&run(0.0, 400)), outside(&run(10.0, 400)));
    assert!(free > 0.2, "the plain actor did not leave the data toward larger actions: {free}");
    assert!(held < 0.5 * free, "pessimism did not hold the actor near its data: {held} outside against {free}");
}

/// `actor_lr_warmup_updates`: the actor's rate climbs linearly from 0
/// over its first N steps (counted after the critic's head start and
/// under `policy_delay`), so its first step is 1/N of the full-rate
/// one (Adam's first step is lr · sign(g), to its ε), and from step N
/// on it is `actor_lr`.
#[test]
fn the_actors_learning_rate_ramps_up_over_its_first_steps() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    let first_step = |actor_lr_warmup_updates| -> (Vec<f32>, Ddpg) {
        let ddpg = DdpgConfig { batch_size: 8, warmup_steps: 0, policy_delay: 2, critic_warmup_updates: 2, actor_lr_warmup_updates, ..cfg.ddpg.clone() };
        let mut agent = agent(&ddpg, &cfg);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for _ in 0..64 {
            let s = [rng.random_range(-1.0f32..1.0), rng.random_range(-1.0f32..1.0)];
            agent.replay.push(&s, &[rng.random_range(-1.0..1.0)], -(s[0] * s[0]), &s, true).unwrap();
        }
        let before = actor_weights(&agent);
        // Updates 1–2: the critic's head start; 3 is odd; 4 is the actor's first step.
        for _ in 0..4 {
            agent.update();
        }
        let delta = actor_weights(&agent).iter().zip(&before).map(|(a, b)| a - b).collect();
        (delta, agent)
    };
    let (full, _) = first_step(0);
    let (ramped, mut agent) = first_step(4);
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for (r, f) in ramped.iter().zip(&full) {
        num += f64::from(*r) * f64::from(*f);
        den += f64::from(*f) * f64::from(*f);
    }
    assert!(den > 0.0, "the actor did not move at full rate");
    assert!((num / den - 0.25).abs() < 1e-3, "the first step of 4 is not a quarter of the full one: {}", num / den);
    // Actor steps 2, 3, 4 and after: 2/4, 3/4, 1, 1 of the rate.
    for expected in [0.5, 0.75, 1.0, 1.0] {
        agent.update();
        agent.update();
        assert!((agent.actor_lr() - expected * cfg.ddpg.actor_lr).abs() < 1e-12, "{} against {expected}", agent.actor_lr() / cfg.ddpg.actor_lr);
    }
}

/// `warmup_actions`: uniform warm-up actions spread over the box; with
/// "policy" they are the initial policy's action (≈ 0, the base) plus
/// noise of std `noise_start`, and the actor tells actors so too
/// (`exploration`). After the warm-up both act the same way.
#[test]
fn warm_up_acts_uniformly_or_around_the_initial_policy() {
    tch::set_num_threads(1);
    let cfg = small_nets();
    let spread = |warmup_actions| {
        let ddpg = DdpgConfig { warmup_steps: 10, noise_start: 0.1, warmup_actions, ..cfg.ddpg.clone() };
        let mut agent = agent(&ddpg, &cfg);
        let uniform = agent.exploration(0).map(|(u, _)| u);
        let mean = agent.act(&[0.3, -0.2])[0];
        let draws: Vec<f32> = (0..2000).map(|_| agent.explore(&[0.3, -0.2], 0)[0] - mean).collect();
        let rms = (draws.iter().map(|d| d * d).sum::<f32>() / draws.len() as f32).sqrt();
        (uniform, mean, rms)
    };
    let (uniform, _, rms) = spread(WarmupActions::Uniform);
    assert_eq!(uniform, Some(true));
    assert!(rms > 0.5, "uniform over [-1, 1] has an rms of about 0.58, got {rms}");
    let (uniform, mean, rms) = spread(WarmupActions::Policy);
    assert_eq!(uniform, Some(false));
    assert!(mean.abs() < 0.05, "the initial policy's residual is near 0, got {mean}");
    assert!((rms - 0.1).abs() < 0.01, "noise_start 0.1 around the policy, got an rms of {rms}");
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
        let mut agent = Ddpg::new(&ddpg, &cfg.network, Connection::Global, &[vec![1]], 1, 1, 3, Device::Cpu);
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
