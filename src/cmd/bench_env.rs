//! `lcrl bench env`: what serving an environment costs. One Gymnasium
//! environment stepped in plain Python (the floor), then through a real
//! `python -m lcrl_env serve` process from this one: one instance per call,
//! and K instances batched in one call, as an actor with K environments
//! steps them. All in one run, so the ratios hold whatever the machine.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{bail, Context};
use lcrl_sim::Env;
use rand::SeedableRng;

use lcrl::supervise::Managed;

pub fn run(gym: &str, instances: &[usize], steps: usize) -> anyhow::Result<()> {
    let python = lcrl::binaries::lcrl_python()?;
    let plain = Command::new(&python).args(["-m", "lcrl_env", "bench", "--env", gym, "--steps", &steps.to_string()]).stderr(Stdio::null()).output()?;
    if !plain.status.success() {
        bail!("python -m lcrl_env bench --env {gym} failed (exit {:?})", plain.status.code());
    }
    let figures: serde_json::Value = serde_json::from_slice(&plain.stdout).context("reading python -m lcrl_env bench's output")?;
    let python_us = figures["us_per_step"].as_f64().context("us_per_step missing")?;

    let logs = tempfile::tempdir()?;
    let most = instances.iter().copied().max().unwrap_or(1).max(1);
    let server = lcrl::preset::EnvServer { gym: Some(gym.to_string()), ..Default::default() };
    let mut cmd = server.command("127.0.0.1:0", most, Path::new("."))?;
    lcrl::supervise::die_with_parent(&mut cmd);
    let (_server, address) = Managed::spawn("env-server", cmd, logs.path(), true)?;
    let url = format!("{}{}", lcrl_sim::remote::SCHEME, address.context("the environment server did not start")?);

    println!("{gym}: {steps} environment steps per measurement, random actions");
    println!("{:<34} {:>12} {:>12} {:>10}", "", "µs/env step", "env steps/s", "× Python");
    println!("{:<34} {:>12.1} {:>12.0} {:>10.2}", "plain Python (env.step)", python_us, 1e6 / python_us, 1.0);
    for &k in instances.iter().filter(|&&k| k > 0) {
        let us = through_service(&url, k, steps)?;
        let label = if k == 1 { "service, 1 instance per call".to_string() } else { format!("service, {k} instances per call") };
        println!("{label:<34} {us:>12.1} {:>12.0} {:>10.2}", 1e6 / us, us / python_us);
    }
    Ok(())
}

/// µs per environment step through the service with K sessions stepped per call.
fn through_service(url: &str, k: usize, steps: usize) -> anyhow::Result<f64> {
    let mut envs: Vec<Box<dyn Env>> = (0..k).map(|_| lcrl_sim::make_env(url)).collect::<Result<_, _>>()?;
    for (i, env) in envs.iter_mut().enumerate() {
        env.reset(i as u64)?;
    }
    let spec = envs[0].spec().clone();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let calls = steps.div_ceil(k);
    let started = Instant::now();
    for _ in 0..calls {
        let actions: Vec<Vec<f64>> = (0..k)
            .map(|_| spec.action_low.iter().zip(&spec.action_high).map(|(lo, hi)| rand::Rng::random_range(&mut rng, *lo..=*hi)).collect())
            .collect();
        let results = lcrl_sim::step_all(&mut envs, &actions)?;
        for (i, step) in results.iter().enumerate() {
            if step.terminated || step.truncated {
                envs[i].reset(rand::Rng::random(&mut rng))?;
            }
        }
    }
    Ok(started.elapsed().as_secs_f64() * 1e6 / (calls * k) as f64)
}


