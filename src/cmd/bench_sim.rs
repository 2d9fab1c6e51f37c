//! `lcrl bench sim`: control steps per second of the peg simulator on one
//! thread at the default physics substeps and at half and double, the
//! instructions a control step costs (callgrind, when valgrind is on the
//! PATH: a count that machine noise does not move), and an evaluation's
//! episodes on 1 thread against every core.

use std::process::Command;
use std::time::Instant;

use anyhow::Context;
use lcrl_sim::evaluate::{evaluate, evaluate_parallel};
use lcrl_sim::peg::{PegConfig, PegEnv};

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
    // An evaluation's independent episodes on every core
    // (evaluate_parallel), against one thread, same episodes.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let env = env_with(default)?;
    let constant = |_: &[f64]| vec![0.0; 6];
    let wall = |threads: usize| -> anyhow::Result<f64> {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
        let started = Instant::now();
        pool.install(|| evaluate_parallel(&env, "constant", episodes, 0, &constant))?;
        Ok(started.elapsed().as_secs_f64())
    };
    let (one, all) = (wall(1)?, wall(cores)?);
    println!("evaluation of {episodes} episodes (default substeps): {one:.2} s on 1 thread, {all:.2} s on {cores}: {:.2}×", one / all);
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
