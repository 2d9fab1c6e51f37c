//! The algorithms on a GPU: CUDA updates against CPU ones, CUDA graphs
//! against eager updates. Skipped, with the reason printed, where no CUDA
//! device is (`lcrl doctor` says what libtorch sees).

use crate::algo::agent::AgentSetup;
use crate::config::{Algo, Connection, TrainConfig};

/// One GPU test at a time: graph captures of two tests at once would
/// share the device's stream synchronization (cuda_graph.rs).
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn gpu_turn() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner())
}

/// The GPU's turn for a test of CUDA graphs, or None (the reason printed)
/// where there is no CUDA device or no graph shim.
fn graphs_turn(checks: &str) -> Option<std::sync::MutexGuard<'static, ()>> {
    if !crate::device::torch::cuda_available() {
        eprintln!("skipped: no CUDA device here; run on a GPU machine to check {checks}");
        return None;
    }
    if let Err(why) = crate::device::cuda_graph::availability() {
        eprintln!("skipped: {why}");
        return None;
    }
    let turn = gpu_turn();
    tch::set_num_threads(1);
    Some(turn)
}

/// The DDPG agent of the graph tests: 3 states, 3 actions, a local mask.
fn small_ddpg(cfg: &TrainConfig, device: tch::Device) -> crate::algo::ddpg::Ddpg {
    let mask = vec![vec![1, 0, 0], vec![1, 1, 0], vec![0, 0, 1]];
    crate::algo::ddpg::Ddpg::new(&cfg.ddpg, &cfg.network, AgentSetup { connection: Connection::Local, mask: &mask, state_dim: 3, action_dim: 3, seed: 7, device })
}

/// The actor's weights, on the host.
fn actor_weights(agent: &dyn crate::algo::agent::Agent) -> Vec<(String, Vec<f32>)> {
    agent.actor_variables().into_iter().map(|(name, t)| (name, Vec::<f32>::try_from(t.to_device(tch::Device::Cpu).flatten(0, -1)).unwrap())).collect()
}

/// Feeds `agent` 160 steps of a fixed 3-state system (the run's progress
/// moving with them) and returns its actor's weights.
fn fed_actor_weights(agent: &mut dyn crate::algo::agent::Agent) -> Vec<(String, Vec<f32>)> {
    for k in 0..160 {
        agent.set_progress(k as f64 / 160.0);
        let obs: Vec<f32> = (0..3).map(|j| ((k * 3 + j) as f32 * 0.37).sin()).collect();
        let action = agent.explore(&obs, 0);
        let next: Vec<f32> = obs.iter().zip(action.iter().cycle()).map(|(s, a)| 0.9 * s + 0.1 * a).collect();
        let reward = -obs.iter().map(|v| v * v).sum::<f32>();
        agent.observe(crate::algo::agent::Transition { obs: &obs, action: &action, reward, next_obs: &next, terminated: false, truncated: k % 40 == 39, log_prob: None, ..Default::default() });
    }
    actor_weights(agent)
}

fn assert_close(what: &str, a: &[(String, Vec<f32>)], b: &[(String, Vec<f32>)]) {
    assert_eq!(a.len(), b.len());
    for ((name, a), (_, b)) in a.iter().zip(b) {
        let worst = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
        assert!(worst < 1e-3, "{what} {name}: weights differ by {worst}");
    }
}

/// The same updates on CUDA as on the CPU: DDPG and PPO agents built with
/// one seed, fed the same transitions, end with the same actor weights
/// within float tolerance (DDPG as `make_agent` builds it, so with CUDA
/// graphs where the build has them). Needs a GPU: skipped with a printed
/// reason otherwise (`lcrl doctor` says what libtorch sees).
#[test]
fn cuda_updates_equal_cpu_updates() {
    if !crate::device::torch::cuda_available() {
        eprintln!("skipped: no CUDA device here (libtorch_cuda: {}); run on a GPU machine to check CUDA updates", crate::device::torch::load_cuda());
        return;
    }
    let _turn = gpu_turn();
    tch::set_num_threads(1);
    let mask = vec![vec![1, 0, 0], vec![1, 1, 0], vec![0, 0, 1]];
    for algo in [Algo::Ddpg, Algo::Ppo] {
        let weights = |device: &str| {
            let mut cfg = TrainConfig::default();
            cfg.run.device = device.into();
            (cfg.ddpg.warmup_steps, cfg.ddpg.batch_size) = (32, 32);
            (cfg.ppo.rollout_steps, cfg.ppo.minibatch_size, cfg.ppo.epochs) = (64, 16, 2);
            fed_actor_weights(crate::algo::algorithms::make_agent(algo, Connection::Local, &cfg, &mask, 3, 3).unwrap().as_mut())
        };
        assert_close(&format!("{algo:?} CUDA against CPU"), &weights("cpu"), &weights("cuda"));
    }
}

/// DDPG updates replayed from CUDA graphs equal eager ones, on the CPU and
/// on the GPU, with every number that changes between updates in play:
/// twin critics and a policy delay (all three kinds of update, each its
/// own graph), target noise, the critic's head start, the actor's
/// learning-rate ramp, annealed learning rates and preactivation weight.
/// Needs a GPU and a build with the graph shim: skipped with the reason
/// otherwise.
#[test]
fn cuda_graph_updates_equal_eager_updates() {
    let Some(_turn) = graphs_turn("CUDA graphs") else { return };
    let mut cfg = TrainConfig::default();
    (cfg.ddpg.warmup_steps, cfg.ddpg.batch_size) = (32, 32);
    (cfg.ddpg.twin_critics, cfg.ddpg.policy_delay, cfg.ddpg.target_noise) = (true, 2, 0.2);
    cfg.ddpg.critic_warmup_updates = 10;
    (cfg.ddpg.anneal_lr, cfg.ddpg.preactivation_l2, cfg.ddpg.preactivation_anneal) = (true, 0.05, true);
    let ddpg = |device: tch::Device| small_ddpg(&cfg, device);
    let cpu = fed_actor_weights(&mut ddpg(tch::Device::Cpu));
    let eager = fed_actor_weights(&mut ddpg(tch::Device::Cuda(0)));
    let mut graphed = ddpg(tch::Device::Cuda(0));
    graphed.use_cuda_graphs().expect("CUDA graphs on a GPU with the shim");
    let replayed = fed_actor_weights(&mut graphed);
    assert_eq!(graphed.captured_graphs(), 3, "one graph per kind of update, none dropped");
    assert_close("graphs against eager CUDA", &eager, &replayed);
    assert_close("graphs against the CPU", &cpu, &replayed);
}

/// Issue 71: updates replayed from CUDA graphs are guarded as eager ones.
/// A replay buffer of states of 3e38 (finite, their squares not) makes
/// every update's numbers infinite; the check every 8 updates undoes them
/// all, on the CPU and from graphs alike: the same counts, no update
/// counted as run, the actor's weights those it started with, every buffer
/// finite, and the graphs still in use. Needs a GPU and the graph shim.
#[test]
fn cuda_graph_updates_that_leave_a_non_finite_number_are_undone() {
    let Some(_turn) = graphs_turn("the guard on CUDA graphs") else { return };
    use crate::algo::agent::Agent;
    let mut cfg = TrainConfig::default();
    (cfg.ddpg.warmup_steps, cfg.ddpg.batch_size, cfg.ddpg.policy_delay, cfg.ddpg.critic_warmup_updates) = (32, 32, 1, 0);
    // One update a step, so a check (every 8 updates) comes every 8 steps.
    (cfg.ddpg.update_every, cfg.ddpg.gradient_steps) = (1, 1);
    let ddpg = |device: tch::Device| small_ddpg(&cfg, device);
    let poisoned = |agent: &mut crate::algo::ddpg::Ddpg| {
        let start = actor_weights(agent);
        let obs = [3e38f32, -3e38, 3e38];
        // Until 16 updates are undone, stopping right after a check (every
        // update since the last one undone, none pending).
        for k in 0.. {
            let c = agent.counters();
            if c.skipped_updates >= 16 && c.critic_updates == 0 {
                break;
            }
            assert!(k < 1000, "no two checks in 1000 steps: {c:?}");
            agent.observe(crate::algo::agent::Transition { obs: &obs, action: &[0.5, -0.5, 0.1], reward: -1.0, next_obs: &obs, terminated: false, truncated: k % 40 == 39, log_prob: None, ..Default::default() });
        }
        let end = actor_weights(agent);
        assert_eq!(start, end, "the actor's weights are those it started with");
        assert!(end.iter().all(|(_, w)| w.iter().all(|v| v.is_finite())));
        assert!(agent.buffers_finite(), "every network, target copy and Adam moment finite");
        let c = agent.counters();
        (c.updates, c.critic_updates, c.skipped_updates)
    };
    let eager = poisoned(&mut ddpg(tch::Device::Cpu));
    let mut graphed = ddpg(tch::Device::Cuda(0));
    graphed.use_cuda_graphs().expect("CUDA graphs on a GPU with the shim");
    let replayed = poisoned(&mut graphed);
    assert_eq!((eager.0, eager.1), (0, 0), "eager updates all undone: {eager:?}");
    assert_eq!(replayed, eager, "(updates, critic updates, undone) from graphs against eager ones");
    assert!(graphed.captured_graphs() >= 1, "the graphs stay in use");
}
