//! The policy room's tests on real agents: a checkpoint loads back to the
//! same actions (as an agent and as a served [`Policy`]), and a snapshot
//! evaluates alike on any number of threads.

use lcrl_sim::make_env;

use crate::algo::algorithms::make_agent;
use crate::config::test_config::tiny;
use crate::config::{Algo, Connection};
use crate::policy::checkpoint::{write_checkpoint, CheckpointMeta};
use crate::policy::trained::Policy;

#[test]
fn checkpoint_round_trip_gives_identical_actions() {
    for algo in [Algo::Ddpg, Algo::Ppo] {
        let dir = tempfile::tempdir().unwrap();
        let cfg = tiny();
        let mask = vec![vec![1, 0, 0], vec![1, 1, 0], vec![0, 0, 1]];
        let mut agent = make_agent(algo, Connection::Local, &cfg, &mask, 3, 3).unwrap();
        // Some training so the weights are not the initial ones.
        let obs = [0.3f32, -0.2, 0.5];
        for k in 0..80 {
            let u = agent.explore(&obs, k);
            let next = [obs[0] * 0.9, obs[1] + 0.01 * k as f32, -obs[2]];
            agent.observe(crate::algo::agent::Transition { obs: &obs, action: &u, reward: -1.0, next_obs: &next, terminated: false, truncated: k % 50 == 49, log_prob: None, ..Default::default() });
        }
        let meta = CheckpointMeta { episode: 1, ..CheckpointMeta::start("lti-paper", algo, Connection::Local, 3, 3, mask.clone(), cfg.clone()) };
        let saved = write_checkpoint(dir.path(), agent.as_ref(), &meta).unwrap();
        let policy = Policy::load(&saved).unwrap();
        let mut restored = make_agent(algo, Connection::Local, &cfg, &mask, 3, 3).unwrap();
        restored.load(&saved).unwrap();
        let env = make_env("lti-paper").unwrap();
        for probe in [[0.1f32, 0.2, 0.3], [-1.0, 0.5, 0.0]] {
            assert_eq!(agent.act(&probe), restored.act(&probe), "{algo:?}");
            let state: Vec<f64> = probe.iter().map(|&v| f64::from(v)).collect();
            let expected: Vec<f64> = agent.act(&probe).iter().map(|&u| f64::from(u)).collect();
            assert_eq!(policy.act(env.as_ref(), &state), expected, "{algo:?}");
        }
        assert_eq!(agent.counters(), restored.counters());
    }
}

/// The evaluation of a trained policy on every core (each thread with its
/// own copy of the network, built from the snapshot's bytes) gives the
/// records of one thread, and those of the agent itself stepping the
/// episodes in order: on the real peg simulator, with a base controller,
/// for the global actor and for LCRL's local one (a sparse graph).
#[test]
fn parallel_policy_evaluation_equals_one_thread() {
    let env = make_env("peg-group1").unwrap();
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    let mut cfg = tiny();
    cfg.base.action = crate::config::BaseController::Action(vec![1.0; n]);
    for connection in [Connection::Global, Connection::Local] {
        let mask: Vec<Vec<u8>> = match connection {
            Connection::Global => vec![vec![1; m]; n],
            _ => (0..n).map(|i| (0..m).map(|j| u8::from(j % n == i || j == 0)).collect()).collect(),
        };
        let mut agent = make_agent(Algo::Ddpg, connection, &cfg, &mask, m, n).unwrap();
        // Some training so the weights are not the initial ones.
        let obs = vec![0.1f32; m];
        for k in 0..80 {
            let u = agent.explore(&obs, k);
            agent.observe(crate::algo::agent::Transition { obs: &obs, action: &u, reward: -1.0, next_obs: &obs, terminated: false, truncated: k % 40 == 39, log_prob: None, ..Default::default() });
        }
        let meta = CheckpointMeta::start("peg-group1", Algo::Ddpg, connection, m, n, mask, cfg.clone());
        let snapshot = crate::policy::snapshot::snapshot(agent.as_ref(), &meta.architecture(), 0).unwrap();
        let actions = crate::policy::action::ActionMap::new(env.spec(), meta.architecture().base.as_deref()).unwrap();
        let (episodes, first) = (6, 40);
        let mut stepped = env.fresh();
        let probe = env.fresh();
        let mut own = |s: &[f64]| actions.to_env(&agent.act(&crate::algo::agent::observe(probe.as_ref(), s)));
        let (_, in_order) = lcrl_sim::evaluate::evaluate(stepped.as_mut(), "policy", episodes, first, &mut own, &mut |_| {}).unwrap();
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let (summary, records) = pool.install(|| crate::policy::trained::evaluate_snapshot(env.as_ref(), "policy", &snapshot, episodes, first, &|_| {})).unwrap();
            assert_eq!(records, in_order, "{connection:?}, {threads} threads");
            assert_eq!(summary.mean_return, in_order.iter().map(|r| r.episode_return).sum::<f64>() / episodes as f64);
        }
        assert!(in_order.windows(2).any(|w| w[0].episode_return != w[1].episode_return), "the starts must differ");
    }
}
