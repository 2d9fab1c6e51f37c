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
    }
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
                cs3: Cs3Config { samples, seed: 0, threads },
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
