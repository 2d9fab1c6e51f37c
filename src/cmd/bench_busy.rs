//! `lcrl bench busy`: the learner's update rate on a busy machine, with
//! its thread count set by `--threads` against the same count exported as
//! `OMP_NUM_THREADS` (OpenMP's own setting, which every thread obeys).
//! Each setting runs `lcrl scale` (one actor, the single-process loop as
//! well) beside N processes that keep a core busy at nice 10, in turn, for
//! a few rounds, so the ratio holds whatever else the machine does.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context};

use lcrl::supervise::Managed;

/// What one `lcrl scale` run measured: distributed and single-process
/// updates per second.
#[derive(Debug, Clone, Copy)]
struct Rates {
    distributed: f64,
    train: f64,
}

pub fn run(config: &Path, busy: usize, seconds: f64, rounds: usize) -> anyhow::Result<()> {
    if !(1.0..=600.0).contains(&seconds) {
        bail!("--seconds takes 1 to 600, got {seconds}");
    }
    // The default preset is named from the repository's root: found from
    // elsewhere too.
    let config = if config.is_file() { config.to_path_buf() } else { lcrl::binaries::project_file(&config.to_string_lossy())? };
    let config = config.as_path();
    let lcrl = std::env::current_exe().context("finding this lcrl binary")?;
    let work = tempfile::tempdir()?;
    // The busy processes, stopped (and killed with this one) when dropped.
    let mut spinners = Vec::new();
    for k in 0..busy {
        let mut cmd = Command::new("nice");
        cmd.args(["-n", "10", "sh", "-c", "while :; do :; done"]);
        lcrl::supervise::die_with_parent(&mut cmd);
        spinners.push(Managed::spawn(&format!("busy-{k}"), cmd, work.path(), false)?.0);
    }
    println!("{}: learner updates/s with --threads 1, beside {busy} process(es) busy at nice 10, {seconds} s windows", config.display());
    println!("{:>5} {:<28} {:>16} {:>16}", "round", "threads set by", "lcrl run upd/s", "lcrl train upd/s");
    let (mut flag, mut omp) = (Vec::new(), Vec::new());
    for round in 0..rounds {
        // In turn, the first setting alternating between rounds.
        for exported in if round % 2 == 0 { [false, true] } else { [true, false] } {
            let out = work.path().join(format!("r{round}-{}", if exported { "omp" } else { "flag" }));
            let rates = scale(&lcrl, config, seconds, exported, &out)?;
            let label = if exported { "OMP_NUM_THREADS=1 exported" } else { "--threads 1" };
            println!("{round:>5} {label:<28} {:>16.1} {:>16.1}", rates.distributed, rates.train);
            if exported { omp.push(rates) } else { flag.push(rates) }
        }
    }
    let total = |rates: &[Rates], pick: fn(&Rates) -> f64| rates.iter().map(pick).sum::<f64>();
    println!(
        "--threads 1 keeps {:.2} of OMP_NUM_THREADS=1's distributed updates ({:.2} of its single-process ones); the goal: at least 0.90",
        total(&flag, |r| r.distributed) / total(&omp, |r| r.distributed).max(1e-9),
        total(&flag, |r| r.train) / total(&omp, |r| r.train).max(1e-9)
    );
    drop(spinners);
    Ok(())
}

/// One `lcrl scale --actors 1 --threads 1` run; with `exported`, under
/// OMP_NUM_THREADS=1 (otherwise with it removed from the environment).
fn scale(lcrl: &Path, config: &Path, seconds: f64, exported: bool, out: &PathBuf) -> anyhow::Result<Rates> {
    let mut cmd = Command::new(lcrl);
    cmd.args(["scale", "--actors", "1", "--threads", "1", "--seconds", &seconds.to_string(), "--config"]).arg(config).arg("--out").arg(out);
    if exported {
        cmd.env("OMP_NUM_THREADS", "1");
    } else {
        cmd.env_remove("OMP_NUM_THREADS");
    }
    let ran = cmd.output().context("starting lcrl scale")?;
    if !ran.status.success() {
        bail!("lcrl scale failed: {}", String::from_utf8_lossy(&ran.stderr).lines().last().unwrap_or("no message"));
    }
    let points: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("scale.json"))?)?;
    let rate = |kind: &str| points.as_array().and_then(|p| p.iter().find(|p| p["kind"].as_str().is_some_and(|k| k.starts_with(kind)))).and_then(|p| p["updates_per_s"].as_f64());
    Ok(Rates { distributed: rate("distributed").context("no distributed point in scale.json")?, train: rate("train").context("no single-process point in scale.json")? })
}
