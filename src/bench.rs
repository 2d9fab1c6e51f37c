//! `lcrl bench`: performance figures, measured as ratios within one run
//! because machine noise is large.

use std::time::Instant;

use clap::Subcommand;
use lcrl_graph_builder::{build_graph, Cs3Config, GraphOptions, Rule};
use lcrl_sim::lti::{LtiConfig, LtiEnv};
use lcrl_sim::Env;

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// CS3 graph-build time for lti-paper and a random sparse 12-state,
    /// 6-action linear system, with 1 thread and with every core.
    Graph {
        /// ST, CS3 samples per action.
        #[arg(long, default_value_t = 256)]
        samples: usize,
        /// Timed repetitions per case (the median is reported).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// DDPG update and PPO update time, local vs global actor.
    Learner {
        /// DDPG updates to time per actor.
        #[arg(long, default_value_t = 300)]
        updates: usize,
    },
    /// gRPC ingestion rate, Policy.Act latency, and end-to-end environment
    /// steps/s with 1 and 2 actors (real lcrl-learner / lcrl-actor processes).
    Transport {
        /// Seconds per measurement.
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
    },
    /// A Gymnasium environment stepped in plain Python, against the same
    /// environment stepped through `python -m lcrl_env serve` (one
    /// instance, and K instances batched in one call).
    Env {
        /// The Gymnasium id.
        #[arg(long, default_value = "HalfCheetah-v5")]
        gym: String,
        /// Batch sizes K to measure through the service.
        #[arg(long, value_delimiter = ',', default_value = "1,8,32")]
        instances: Vec<usize>,
        /// Environment steps per measurement.
        #[arg(long, default_value_t = 4000)]
        steps: usize,
    },
    /// Control steps per second of peg-group1 on one core.
    Sim {
        /// Episodes per setting.
        #[arg(long, default_value_t = 100)]
        episodes: usize,
    },
}

pub fn run(command: BenchCommand) -> anyhow::Result<()> {
    match command {
        BenchCommand::Graph { samples, repeats } => bench_graph(samples, repeats.max(1)),
        BenchCommand::Sim { episodes } => bench_sim(episodes.max(1)),
        BenchCommand::Learner { updates } => bench_learner(updates.max(1)),
        BenchCommand::Transport { seconds } => crate::bench_transport::run(seconds.max(1.0)),
        BenchCommand::Env { gym, instances, steps } => crate::bench_env::run(&gym, &instances, steps.max(1)),
    }
}

/// One DDPG update (batch 256, default sizes) and one PPO update (a 2048-step
/// rollout: 10 epochs of 64-transition minibatches), local vs global actor,
/// at the peg task's size with its CS3 graph, one libtorch thread.
fn bench_learner(updates: usize) -> anyhow::Result<()> {
    use lcrl_learner::agent::Transition;
    use lcrl_learner::trainer::make_agent;
    use lcrl_learner::{Algo, Connection, TrainConfig};
    use rand::{Rng, SeedableRng};

    tch::set_num_threads(1);
    let env = lcrl_sim::make_env("peg-group1")?;
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    let options = GraphOptions { cs3: Cs3Config { samples: 32, seed: 0, threads: 0, start: None }, rule: Rule::Threshold(0.1), bootstrap: 0 };
    let mask = build_graph(env.as_ref(), &options, &|| {})?.g;
    let edges: usize = mask.iter().flatten().map(|&v| usize::from(v)).sum();
    println!("peg-group1 ({m} states, {n} actions, {edges} of {} edges in G), one libtorch thread", m * n);
    let mut cfg = TrainConfig::default();
    cfg.ddpg.warmup_steps = 0;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut random = |len: usize| -> Vec<f32> { (0..len).map(|_| rng.random_range(-1.0..1.0)).collect() };
    let mut results = Vec::new();
    for connection in [Connection::Global, Connection::Local, Connection::FullSubnets] {
        let mut ddpg = make_agent(Algo::Ddpg, connection, &cfg, &mask, m, n)?;
        let mut ddpg_seconds = 0.0;
        for k in 0..(updates + cfg.ddpg.batch_size) {
            let (obs, action, next) = (random(m), random(n), random(m));
            let t = Transition { obs: &obs, action: &action, reward: -1.0, next_obs: &next, terminated: false, truncated: false };
            let spent = ddpg.observe(t);
            if k >= cfg.ddpg.batch_size {
                ddpg_seconds += spent;
            }
        }
        let mut ppo = make_agent(Algo::Ppo, connection, &cfg, &mask, m, n)?;
        let mut ppo_seconds = 0.0;
        for _ in 0..cfg.ppo.rollout_steps {
            let obs = random(m);
            let action = ppo.explore(&obs, 0);
            let next = random(m);
            ppo_seconds += ppo.observe(Transition { obs: &obs, action: &action, reward: -1.0, next_obs: &next, terminated: false, truncated: false });
        }
        let params = ddpg.param_counts().0;
        results.push((connection, params, ddpg_seconds / updates as f64, ppo_seconds));
    }
    println!("{:<14} {:>13} {:>16} {:>12} {:>18}", "actor", "actor params", "DDPG update ms", "updates/s", "PPO update (10 ep) s");
    for (connection, params, ddpg, ppo) in &results {
        println!("{:<14} {params:>13} {:>16.3} {:>12.0} {ppo:>18.3}", format!("{connection:?}"), ddpg * 1e3, 1.0 / ddpg);
    }
    let (global, local) = (&results[0], &results[1]);
    println!("local / global: DDPG update {:.2}×, PPO update {:.2}× (target ≤ 1.3×)", local.2 / global.2, local.3 / global.3);
    Ok(())
}

/// Control steps per second of the constant controller on peg-group1 on
/// one thread, at the default physics substeps and at half and double, to
/// show how much of a control step is the physics.
fn bench_sim(episodes: usize) -> anyhow::Result<()> {
    use lcrl_sim::evaluate::evaluate;
    use lcrl_sim::peg::{PegConfig, PegEnv};
    let default = PegConfig::group1().physics.substeps;
    println!("peg-group1, constant controller, {episodes} episodes, one thread");
    println!("{:>9} {:>16} {:>14}", "substeps", "control steps/s", "µs per step");
    for substeps in [default / 2, default, default * 2] {
        let mut cfg = PegConfig::group1();
        cfg.physics.substeps = substeps;
        let mut env = PegEnv::new("peg-group1", cfg)?;
        let (summary, _) = evaluate(&mut env, "constant", episodes, 0, &mut |_| vec![0.0; 6], &mut |_| {})?;
        let per_step = 1e6 / summary.control_steps_per_sec;
        println!("{substeps:>9} {:>16.0} {per_step:>14.1}", summary.control_steps_per_sec);
    }
    Ok(())
}

fn bench_graph(samples: usize, repeats: usize) -> anyhow::Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let systems = [
        ("lti-paper (3×3)", LtiEnv::new("lti-paper", &LtiConfig::paper_example())?),
        ("random 12×6", LtiEnv::new("random-12x6", &LtiConfig::random_sparse(12, 6, 0.25, 42))?),
    ];
    println!("CS3 graph build, ST = {samples}, eq. 7, 200 bootstrap resamples; median of {repeats}");
    println!("{:<18} {:>12} {:>12} {:>14}", "system", "1 thread", format!("{cores} threads"), "speed-up");
    for (label, env) in &systems {
        let time = |threads: usize| -> anyhow::Result<f64> {
            let options = GraphOptions {
                cs3: Cs3Config { samples, seed: 0, threads, start: None },
                rule: Rule::Threshold(0.1),
                bootstrap: 200,
            };
            let mut runs = Vec::with_capacity(repeats);
            for _ in 0..repeats {
                let started = Instant::now();
                build_graph(env as &dyn Env, &options, &|| {})?;
                runs.push(started.elapsed().as_secs_f64());
            }
            runs.sort_by(f64::total_cmp);
            Ok(runs[runs.len() / 2])
        };
        let one = time(1)?;
        let all = time(cores)?;
        println!("{label:<18} {:>10.2}ms {:>10.2}ms {:>13.2}×", one * 1e3, all * 1e3, one / all);
    }
    Ok(())
}
