//! `lcrl bench sim`: control steps per second of the peg simulator on one
//! thread at the default physics substeps and at half and double, the
//! instructions a control step costs (callgrind, when valgrind is on the
//! PATH: a count that machine noise does not move), and an evaluation's
//! episodes on 1 thread against every core; `lcrl bench tune`, the
//! best-constant search on 1 thread against every core.

use std::process::Command;
use std::time::Instant;

use anyhow::Context;
use lcrl_learner::policy::trained::evaluate_snapshot;
use lcrl_sim::evaluate::{evaluate, evaluate_parallel};
use lcrl_sim::peg::{PegConfig, PegEnv};
use lcrl_sim::tune::TuneOptions;
use lcrl_sim::Env;

/// Episodes of the two counted runs: their difference cancels what every
/// run pays once (start-up, libtorch's initializers, the first reset).
const COUNTED_EPISODES: [usize; 2] = [2, 6];

pub fn run(episodes: usize) -> anyhow::Result<()> {
    let default = PegConfig::group1().physics.substeps;
    println!("peg-group1, constant controller, {episodes} episodes, one thread");
    println!("{:>9} {:>16} {:>14}", "substeps", "control steps/s", "µs per step");
    for substeps in [default / 2, default, default * 2] {
        let mut env = env_with(substeps)?;
        let (summary, _) = evaluate(&mut env, "constant", episodes, 0, &mut |_| vec![0.0; 6], &mut |_| {})?;
        let per_step = 1e6 / summary.control_steps_per_sec;
        println!("{substeps:>9} {:>16.0} {per_step:>14.1}", summary.control_steps_per_sec);
    }
    match instructions_per_step(default) {
        Ok(Some(count)) => println!("instructions per control step at {default} substeps (callgrind): {count:.0}"),
        Ok(None) => println!("instructions per control step: skipped (valgrind is not on the PATH)"),
        Err(e) => println!("instructions per control step: failed ({e:#})"),
    }
    // An evaluation's independent episodes on every core, against one
    // thread, same episodes: the constant controller (evaluate_parallel),
    // then a DDPG policy at the peg presets' network sizes, whose libtorch
    // network each thread copies (evaluate_snapshot).
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let env = env_with(default)?;
    let constant = |_: &[f64]| vec![0.0; 6];
    let policy = untrained_policy(&env)?;
    let wall = |threads: usize, trained: bool| -> anyhow::Result<(f64, f64)> {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
        let started = Instant::now();
        let (summary, _) = if trained {
            pool.install(|| evaluate_snapshot(&env, "policy", &policy, episodes, 0, &|_| {}))?
        } else {
            pool.install(|| evaluate_parallel(&env, "constant", episodes, 0, &constant))?
        };
        Ok((started.elapsed().as_secs_f64(), summary.mean_return))
    };
    for (trained, label) in [(false, "constant controller"), (true, "DDPG policy (libtorch, a copy per thread)")] {
        let ((one, one_return), (all, all_return)) = (wall(1, trained)?, wall(cores, trained)?);
        let same = if one_return == all_return { "identical returns" } else { "RETURNS DIFFER" };
        println!("evaluation of {episodes} episodes, {label}: {one:.2} s on 1 thread, {all:.2} s on {cores}: {:.2}× ({same})", one / all);
    }
    Ok(())
}

/// A DDPG actor at the peg presets' sizes (configs/peg.toml's network,
/// global connection), its initial weights: what a trained policy costs per
/// step, whatever it has learned.
fn untrained_policy(env: &PegEnv) -> anyhow::Result<lcrl_proto::v1::PolicySnapshot> {
    use lcrl_learner::{Algo, Connection};
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    let (cfg, _) = lcrl_learner::TrainConfig::for_env("peg-group1");
    let mask = vec![vec![1; m]; n];
    let agent = lcrl_learner::algo::algorithms::make_agent(Algo::Ddpg, Connection::Global, &cfg, &mask, m, n)?;
    let meta = lcrl_learner::policy::checkpoint::CheckpointMeta::start("peg-group1", Algo::Ddpg, Connection::Global, m, n, mask, cfg);
    Ok(lcrl_learner::policy::snapshot::snapshot(agent.as_ref(), &meta.architecture(), 0)?)
}

/// `lcrl bench tune`: the best-constant search on 1 thread against every
/// core (candidates and their episodes in parallel; the report must be the
/// same).
pub fn tune(evaluations: usize, episodes: usize) -> anyhow::Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let env = env_with(PegConfig::group1().physics.substeps)?;
    let opts = TuneOptions { episodes, evaluations, eval_episodes: 100, ..TuneOptions::default() };
    println!("lcrl tune on peg-group1: {evaluations} candidates × {episodes} starts, then 2 × 100 evaluation episodes");
    let run = |threads: usize| -> anyhow::Result<(f64, Vec<f64>, f64)> {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
        let started = Instant::now();
        let report = pool.install(|| lcrl_sim::tune::tune(&env, &opts, &|_| {}))?;
        Ok((started.elapsed().as_secs_f64(), report.action, report.mean_return))
    };
    let (one, one_action, one_return) = run(1)?;
    let (all, all_action, all_return) = run(cores)?;
    let same = if (one_action.as_slice(), one_return) == (all_action.as_slice(), all_return) { "identical reports" } else { "REPORTS DIFFER" };
    println!("{one:.2} s on 1 thread, {all:.2} s on {cores}: {:.2}× ({same}; best constant {one_action:.3?}, eval return {one_return:.3})", one / all);
    Ok(())
}

/// `lcrl bench sim-episodes`: the counted run, its step count on stdout.
pub fn episodes(episodes: usize, substeps: usize) -> anyhow::Result<()> {
    let mut env = env_with(substeps)?;
    let (_, records) = evaluate(&mut env, "constant", episodes, 0, &mut |_| vec![0.0; 6], &mut |_| {})?;
    println!("steps {}", records.iter().map(|r| r.steps).sum::<usize>());
    Ok(())
}

fn env_with(substeps: usize) -> anyhow::Result<PegEnv> {
    let mut cfg = PegConfig::group1();
    cfg.physics.substeps = substeps;
    Ok(PegEnv::new("peg-group1", cfg)?)
}

/// Instructions per control step: this binary's `bench sim-episodes` under
/// callgrind twice, the difference of the counts over the difference of
/// the steps. None when valgrind is not installed.
fn instructions_per_step(substeps: usize) -> anyhow::Result<Option<f64>> {
    if Command::new("valgrind").arg("--version").output().is_err() {
        return Ok(None);
    }
    let exe = std::env::current_exe().context("finding this binary to run under valgrind")?;
    let counted = |episodes: usize| -> anyhow::Result<(f64, f64)> {
        let out = Command::new("valgrind")
            .args(["--tool=callgrind", "--callgrind-out-file=/dev/null"])
            .arg(&exe)
            .args(["bench", "sim-episodes", "--episodes", &episodes.to_string(), "--substeps", &substeps.to_string()])
            .output()
            .context("running valgrind")?;
        let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        anyhow::ensure!(out.status.success(), "valgrind exited with {}: {}", out.status, stderr.lines().last().unwrap_or(""));
        let steps = stdout.lines().find_map(|l| l.strip_prefix("steps ")).and_then(|v| v.trim().parse::<f64>().ok());
        // callgrind's summary line: "==PID== Collected : 1536589918".
        let collected = stderr.lines().find_map(|l| l.split_once("Collected :")).and_then(|(_, v)| v.trim().parse::<f64>().ok());
        match (collected, steps) {
            (Some(c), Some(s)) => Ok((c, s)),
            _ => anyhow::bail!("no instruction or step count in valgrind's output"),
        }
    };
    let [few, many] = COUNTED_EPISODES;
    let ((ir_few, steps_few), (ir_many, steps_many)) = (counted(few)?, counted(many)?);
    anyhow::ensure!(steps_many > steps_few, "the longer run took no more steps");
    Ok(Some((ir_many - ir_few) / (steps_many - steps_few)))
}
