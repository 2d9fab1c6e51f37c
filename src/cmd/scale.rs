//! `lcrl scale`: how the distributed system's throughput grows with actor
//! processes on this machine. For each point (actors × environments per
//! actor) it starts a learner and the actors from a preset, lets them warm
//! up, and measures over a window: env steps/s, updates/s, the replay ratio
//! achieved, policy lag, `Policy.Act` latency (p50) and the CPU each
//! process used. The single-process `lcrl train` loop is measured too, as
//! the baseline. Writes scale.json, scale.csv and scale.png.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::policy_client::PolicyClient;
use lcrl_proto::v1::{ActRequest, GetStatusRequest, LearnerStatus};
use plotters::prelude::*;
use serde::Serialize;

use lcrl::binaries::sibling;
use lcrl::preset::Preset;
use lcrl::local_run::TransportArg;
use lcrl::supervise::{stop_with_parent, wait_healthy, Managed};

/// Measure throughput against the number of actor processes.
#[derive(Debug, clap::Args)]
pub struct ScaleArgs {
    /// Preset (configs/*.toml) whose environment, algorithm and settings
    /// every point runs.
    #[arg(long)]
    pub config: PathBuf,
    /// Actor process counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
    pub actors: Vec<usize>,
    /// Environments per actor process, each combined with every --actors.
    #[arg(long, value_delimiter = ',', default_value = "1")]
    pub envs_per_actor: Vec<usize>,
    /// Length of each point's measurement window, seconds (after warm-up).
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Warm-up before the window, seconds (processes start, replay fills).
    #[arg(long, default_value_t = 3.0)]
    pub warmup: f64,
    #[arg(long, value_enum, default_value_t = TransportArg::Shm)]
    pub transport: TransportArg,
    /// Also measure the wall time until the mean return of the last 10
    /// episodes reaches this (each point then runs until it does, or for
    /// --threshold-timeout seconds).
    #[arg(long, allow_hyphen_values = true, value_name = "RETURN")]
    pub to_threshold: Option<f64>,
    #[arg(long, default_value_t = 300.0)]
    pub threshold_timeout: f64,
    /// Replay ratio for every point (samples per insert, or `unlimited`);
    /// default: the preset's (Algorithm 2's).
    #[arg(long)]
    pub replay_ratio: Option<String>,
    /// PPO: policy versions a batch may lag and still be trained on
    /// (asynchronous PPO, docs/method.md §5); default: the preset's.
    #[arg(long)]
    pub max_staleness: Option<u64>,
    #[command(flatten)]
    pub compute: lcrl::preset::LearnerCompute,
    /// Where scale.json, scale.csv, scale.png and per-point logs go.
    #[arg(long, default_value = "runs/scale")]
    pub out: PathBuf,
}

/// One measured point (a row of scale.csv).
#[derive(Debug, Clone, Serialize)]
pub struct ScalePoint {
    /// "distributed" or "train (single process)".
    pub kind: String,
    pub actors: usize,
    pub envs_per_actor: usize,
    /// Learner + actors (1 for the single-process loop).
    pub processes: usize,
    pub transport: String,
    /// The learner's device and libtorch threads.
    pub learner_device: String,
    pub learner_threads: usize,
    pub seconds: f64,
    pub env_steps_per_s: f64,
    pub updates_per_s: f64,
    /// Δ sampled / Δ inserted over the window (0 for PPO or unlimited).
    pub replay_ratio: f64,
    pub policy_lag_mean: f64,
    pub policy_lag_max: u64,
    /// Median `Policy.Act` latency over the window, milliseconds.
    pub act_p50_ms: Option<f64>,
    /// CPU used over the window, in cores (1.0 = one core busy).
    pub learner_cpu: f64,
    pub actors_cpu: f64,
    /// Seconds the limiter held actors back / made the learner wait.
    pub actors_waited_s: f64,
    pub learner_waited_s: f64,
    /// Steps the actors simulated over the window that the learner did not
    /// train on, being more policy versions behind than PPO's lag bound
    /// allows (`stale`), and their share of those simulated (stored +
    /// discarded).
    pub discarded_steps: u64,
    pub discarded_share: f64,
    /// The share of the actors' wall time over the window their
    /// environment threads spent waiting to hand a batch over (the learner
    /// held them back), from each actor's `send_wait_seconds`; None where
    /// an actor's metrics could not be read.
    pub actor_idle_share: Option<f64>,
    /// Wall time to reach --to-threshold, when asked and reached.
    pub seconds_to_threshold: Option<f64>,
}

pub fn run(args: &ScaleArgs) -> anyhow::Result<()> {
    check_args(args)?;
    let mut preset = Preset::load(&args.config)?;
    preset.set_compute(&args.compute)?;
    lcrl_learner::device::torch::resolve_device(&preset.train.run.device)?;
    if args.replay_ratio.is_some() {
        preset.job.replay_ratio = args.replay_ratio.clone();
    }
    if args.max_staleness.is_some() {
        preset.job.max_staleness = args.max_staleness;
    }
    // Far more episodes than any window reaches: the budget never ends a point.
    preset.job.episodes = u64::MAX / 4;
    fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let transport = match args.transport {
        TransportArg::Grpc => "grpc",
        TransportArg::Shm => "shm",
    };
    // One graph for every point.
    let graph = args.out.join("graph.json");
    if preset.job.connection == lcrl_learner::Connection::Local && !graph.is_file() {
        let env = lcrl_sim::make_env(&preset.job.env)?;
        let options = lcrl_graph_builder::GraphOptions::paper(preset.train.run.graph_samples, preset.train.run.seed, 0);
        lcrl_graph_builder::build_graph(env.as_ref(), &options, &|| {})?.write_json(&graph)?;
    }
    let mut points = vec![baseline(&preset, args, &graph)?];
    eprintln!("baseline (lcrl train loop, 1 process): {:.0} env steps/s, {:.0} updates/s", points[0].env_steps_per_s, points[0].updates_per_s);
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    for &envs in &args.envs_per_actor {
        for &actors in &args.actors {
            let point = runtime.block_on(measure(&preset, args, &graph, actors, envs, transport))?;
            eprintln!(
                "{actors} actor(s) × {envs} env(s): {:.0} env steps/s, {:.0} updates/s, ratio {:.1}, lag {:.1}, CPU learner {:.2} actors {:.2}",
                point.env_steps_per_s, point.updates_per_s, point.replay_ratio, point.policy_lag_mean, point.learner_cpu, point.actors_cpu
            );
            points.push(point);
        }
    }
    let json = args.out.join("scale.json");
    lcrl::output::write_atomic(&json, &(serde_json::to_string_pretty(&points)? + "\n"))?;
    let csv_path = args.out.join("scale.csv");
    let mut csv = csv::Writer::from_path(&csv_path).with_context(|| format!("writing {}", csv_path.display()))?;
    for p in &points {
        csv.serialize(p)?;
    }
    csv.flush()?;
    plot(&points, &args.out.join("scale.png"), &preset.job.env)?;
    print_table(&points);
    println!("wrote {}, {}, {}", json.display(), csv_path.display(), args.out.join("scale.png").display());
    Ok(())
}

/// The counts and durations asked for, each within its range.
fn check_args(args: &ScaleArgs) -> anyhow::Result<()> {
    use lcrl::preset::{MAX_ACTORS, MAX_ENVS_PER_ACTOR};
    if args.actors.is_empty() || args.actors.iter().any(|a| !(1..=MAX_ACTORS).contains(a)) {
        bail!("--actors takes counts from 1 to {MAX_ACTORS}");
    }
    if args.envs_per_actor.iter().any(|e| !(1..=MAX_ENVS_PER_ACTOR).contains(e)) {
        bail!("--envs-per-actor takes counts from 1 to {MAX_ENVS_PER_ACTOR}");
    }
    // A day at most: longer would overflow the clock's arithmetic.
    const DAY: f64 = 86_400.0;
    for (flag, value, least) in [("--seconds", args.seconds, f64::MIN_POSITIVE), ("--warmup", args.warmup, 0.0), ("--threshold-timeout", args.threshold_timeout, 0.0)] {
        if !(value.is_finite() && value >= least && value <= DAY) {
            let lower = if least > 0.0 { "above 0" } else { "from 0" };
            bail!("{flag} must be a number of seconds {lower} and at most {DAY}, got {value}");
        }
    }
    Ok(())
}

/// The points as a table on stdout.
fn print_table(points: &[ScalePoint]) {
    println!(
        "{:<24} {:>6} {:>5} {:>8} {:>12} {:>10} {:>7} {:>6} {:>10} {:>6} {:>8} {:>9} {:>9} {:>10}",
        "kind", "actors", "envs", "learner", "env steps/s", "updates/s", "ratio", "lag", "discarded", "idle", "act p50", "cpu lrn", "cpu act", "to thr. s"
    );
    for p in points {
        println!(
            "{:<24} {:>6} {:>5} {:>8} {:>12.0} {:>10.0} {:>7.1} {:>6.1} {:>9.0}% {:>6} {:>8} {:>9.2} {:>9.2} {:>10}",
            p.kind,
            p.actors,
            p.envs_per_actor,
            format!("{}×{}", p.learner_device, p.learner_threads),
            p.env_steps_per_s,
            p.updates_per_s,
            p.replay_ratio,
            p.policy_lag_mean,
            100.0 * p.discarded_share,
            p.actor_idle_share.map_or("-".into(), |v| format!("{:.0}%", 100.0 * v)),
            p.act_p50_ms.map_or("-".into(), |v| format!("{v:.2}ms")),
            p.learner_cpu,
            p.actors_cpu,
            p.seconds_to_threshold.map_or("-".into(), |v| format!("{v:.0}"))
        );
    }
}

/// The single-process `lcrl train` loop on the same settings: env steps and
/// updates per second after its warm-up (as many episodes as fit in the
/// window, at least enough to pass the warm-up).
fn baseline(preset: &Preset, args: &ScaleArgs, graph: &Path) -> anyhow::Result<ScalePoint> {
    let env = lcrl_sim::make_env(&preset.job.env)?;
    // Episode length from one a = 0 episode.
    let mut probe = env.fresh();
    let n = probe.spec().action_dim();
    let length = lcrl_sim::evaluate::run_episode(probe.as_mut(), 0, &mut |_| vec![0.0; n], false)?.steps.max(1);
    let warm = preset.train.ddpg.warmup_steps.div_ceil(length) + 1;
    let mut config = preset.train.clone();
    config.run.episodes = warm + 20;
    config.run.eval_episodes = 1;
    config.run.checkpoint_every = usize::MAX / 2;
    let dir = args.out.join("baseline");
    let _ = fs::remove_dir_all(&dir);
    let request = lcrl_learner::run::trainer::TrainRequest {
        env: preset.job.env.clone(),
        algo: preset.job.algo,
        connection: preset.job.connection,
        graph: (preset.job.connection == lcrl_learner::Connection::Local).then(|| graph.to_path_buf()),
        config,
        settings_source: args.config.display().to_string(),
        run_dir: dir,
        resume: false,
        stop_after: None,
    };
    let outcome = lcrl_learner::run::trainer::train(&request, &mut |_| {})?;
    let after_warmup = &outcome.rows[warm.min(outcome.rows.len().saturating_sub(1))..];
    let wall: f64 = after_warmup.iter().filter_map(|r| r.wall_s).sum();
    let steps: usize = after_warmup.iter().map(|r| r.length).sum();
    let rate = steps as f64 / wall.max(1e-9);
    let ddpg = &preset.train.ddpg;
    Ok(ScalePoint {
        kind: "train (single process)".into(),
        actors: 0,
        envs_per_actor: 1,
        processes: 1,
        transport: "-".into(),
        learner_device: preset.train.run.device.clone(),
        learner_threads: lcrl_learner::device::torch::resolve_threads(preset.train.run.threads, 0),
        seconds: wall,
        env_steps_per_s: rate,
        // Algorithm 2 in one process: one update per step once warm, or
        // gradient_steps every update_every steps (PPO: one PPO update per
        // rollout).
        updates_per_s: match preset.job.algo {
            // Actor updates, as the distributed rows count them: one per
            // policy_delay critic updates.
            lcrl_learner::Algo::Ddpg => rate * ddpg.gradient_steps as f64 / ddpg.update_every as f64 / ddpg.policy_delay as f64,
            lcrl_learner::Algo::Ppo => rate / preset.train.ppo.rollout_steps as f64,
        },
        replay_ratio: if preset.job.algo == lcrl_learner::Algo::Ddpg { ddpg.samples_per_insert() } else { 0.0 },
        policy_lag_mean: 0.0,
        policy_lag_max: 0,
        act_p50_ms: None,
        learner_cpu: 1.0,
        actors_cpu: 0.0,
        actors_waited_s: 0.0,
        learner_waited_s: 0.0,
        discarded_steps: 0,
        discarded_share: 0.0,
        actor_idle_share: None,
        seconds_to_threshold: None,
    })
}

/// The point's actors, each serving its metrics (read for its idle share)
/// on a port of its own choosing; their processes and metrics addresses.
fn start_actors(preset: &Preset, url: &str, run_id: &str, transport: &str, actors: usize, logs: &Path) -> anyhow::Result<(Vec<Managed>, Vec<Option<String>>)> {
    let mut workers = Vec::new();
    let mut metrics = Vec::new();
    for k in 0..actors {
        let mut cmd = Command::new(sibling("lcrl-actor")?);
        cmd.args(preset.actor_args(url, run_id, transport, Some(&format!("actor-{k}")), k as u64));
        cmd.args(["--metrics-listen", "127.0.0.1:0"]);
        stop_with_parent(&mut cmd);
        let (worker, address) = Managed::spawn_announcing(&format!("actor-{k}"), cmd, logs, Some("metrics on "))?;
        workers.push(worker);
        metrics.push(address);
    }
    Ok((workers, metrics))
}

/// The actors' seconds waiting to hand batches over until now, summed,
/// from each one's metrics; None (said why) when any actor's cannot be
/// read.
fn send_wait_seconds(addresses: &[Option<String>]) -> Option<f64> {
    addresses
        .iter()
        .enumerate()
        .map(|(k, address)| {
            let waited = address.as_deref().and_then(scrape_send_wait);
            if waited.is_none() {
                tracing::warn!("actor-{k}'s metrics could not be read ({address:?}): no idle share for this point");
            }
            waited
        })
        .sum()
}

/// One actor's seconds waiting until now: its finished waits
/// (`lcrl_actor_send_wait_seconds_total`) and the part of a wait going on
/// (`lcrl_actor_send_waiting_since_ms`), so a long wait counts in the
/// window it falls in. Over plain HTTP.
fn scrape_send_wait(address: &str) -> Option<f64> {
    use std::io::{Read, Write};
    let mut stream = std::net::TcpStream::connect_timeout(&address.parse().ok()?, Duration::from_secs(2)).ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(stream, "GET /metrics HTTP/1.1\r\nHost: {address}\r\nConnection: close\r\n\r\n").ok()?;
    let mut body = String::new();
    stream.read_to_string(&mut body).ok()?;
    let now_ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).ok()?.as_millis() as f64;
    let value = |name: &str| body.lines().find_map(|line| line.strip_prefix(name)).and_then(|v| v.trim().parse::<f64>().ok());
    let finished = value("lcrl_actor_send_wait_seconds_total ")?;
    let since = value("lcrl_actor_send_waiting_since_ms ").unwrap_or(0.0);
    Some(finished + if since > 0.0 { ((now_ms - since) / 1e3).max(0.0) } else { 0.0 })
}

/// CPU seconds (user + system) a process has used so far.
fn cpu_seconds(pid: u32) -> f64 {
    let Ok(stat) = fs::read_to_string(format!("/proc/{pid}/stat")) else { return 0.0 };
    // Fields after the command name, which is in parentheses.
    let Some(rest) = stat.rsplit(')').next() else { return 0.0 };
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |k: usize| fields.get(k).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // utime and stime are fields 14 and 15 of stat (11 and 12 after the name).
    (ticks(11) + ticks(12)) / 100.0
}

/// Seconds from `started` until the learner's recent return (over at
/// least 10 episodes) reaches `threshold`; None after `timeout` seconds.
async fn seconds_to(client: &mut LearnerClient<tonic::transport::Channel>, threshold: f64, started: Instant, timeout: f64) -> anyhow::Result<Option<f64>> {
    loop {
        let s = client.get_status(GetStatusRequest {}).await.map_err(|e| anyhow::anyhow!("lost the learner: {e}"))?.into_inner();
        if s.episodes >= 10 && s.recent_return >= threshold {
            return Ok(Some(started.elapsed().as_secs_f64()));
        }
        if started.elapsed().as_secs_f64() > timeout {
            return Ok(None);
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// `Policy.Act` latencies (ms) of one query every 20 ms until `seconds`
/// after `window` began.
async fn act_latencies(policy: &mut PolicyClient<tonic::transport::Channel>, m: usize, window: Instant, seconds: f64) -> Vec<f64> {
    let mut latencies = Vec::new();
    while window.elapsed().as_secs_f64() < seconds {
        let t = Instant::now();
        if policy.act(ActRequest { state: vec![0.0; m] }).await.is_ok() {
            latencies.push(t.elapsed().as_secs_f64() * 1e3);
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    latencies
}

async fn measure(preset: &Preset, args: &ScaleArgs, graph: &Path, actors: usize, envs: usize, transport: &str) -> anyhow::Result<ScalePoint> {
    let mut preset = preset.clone();
    preset.job.envs_per_actor = envs;
    preset.job.actors = actors;
    preset.pin_learner_threads();
    let dir = args.out.join(format!("a{actors}-e{envs}"));
    let _ = fs::remove_dir_all(&dir);
    let logs = dir.join("logs");
    fs::create_dir_all(&logs)?;
    let train = dir.join("train.toml");
    preset.write_train_config(&train)?;
    let run_id = format!("scale-{}-a{actors}-e{envs}", std::process::id());
    let mut cmd = Command::new(sibling("lcrl-learner")?);
    cmd.args(preset.learner_args_with_graph_file("127.0.0.1:0", &run_id, &train, &dir.join("learner"), graph));
    // Spawned from the main thread (this runs inside `block_on`), which
    // lives as long as `lcrl scale`: they stop when it dies.
    stop_with_parent(&mut cmd);
    let (mut learner, address) = Managed::spawn("learner", cmd, &logs, true)?;
    let url = format!("http://{}", address.context("the learner did not start; see its log")?);
    wait_healthy(&url, "lcrl.v1.Learner", "the learner", Duration::from_secs(120), &Default::default()).await?;
    let started = Instant::now();
    let (mut workers, actor_metrics) = start_actors(&preset, &url, &run_id, transport, actors, &logs)?;
    let mut client = LearnerClient::connect(url.clone()).await?;
    let mut policy = PolicyClient::connect(url.clone()).await?;
    let status = |s: Result<tonic::Response<LearnerStatus>, tonic::Status>| s.map(|r| r.into_inner()).map_err(|e| anyhow::anyhow!("lost the learner: {e}"));
    tokio::time::sleep(Duration::from_secs_f64(args.warmup)).await;
    let first = status(client.get_status(GetStatusRequest {}).await)?;
    let waited_before = (send_wait_seconds(&actor_metrics), Instant::now());
    let cpu = |pids: &[u32]| pids.iter().map(|&p| cpu_seconds(p)).sum::<f64>();
    let actor_pids: Vec<u32> = workers.iter().map(Managed::pid).collect();
    let (learner_cpu0, actors_cpu0) = (cpu(&[learner.pid()]), cpu(&actor_pids));
    let window = Instant::now();
    let m = lcrl_sim::make_env(&preset.job.env)?.spec().state_dim();
    let mut latencies = act_latencies(&mut policy, m, window, args.seconds).await;
    let seconds = window.elapsed().as_secs_f64();
    let last = status(client.get_status(GetStatusRequest {}).await)?;
    let waited_after = (send_wait_seconds(&actor_metrics), Instant::now());
    let (learner_cpu, actors_cpu) = ((cpu(&[learner.pid()]) - learner_cpu0) / seconds, (cpu(&actor_pids) - actors_cpu0) / seconds);
    let seconds_to_threshold = match args.to_threshold {
        Some(threshold) => seconds_to(&mut client, threshold, started, args.threshold_timeout).await?,
        None => None,
    };
    for worker in workers.iter_mut() {
        worker.stop(Duration::from_secs(10));
    }
    learner.stop(Duration::from_secs(30));
    latencies.sort_by(f64::total_cmp);
    let inserted = last.inserted.saturating_sub(first.inserted);
    let stale = |s: &LearnerStatus| lcrl_learner::service::ingest::discarded_stale(&s.rejected);
    let discarded_steps = stale(&last).saturating_sub(stale(&first));
    let stored = last.env_steps.saturating_sub(first.env_steps);
    Ok(ScalePoint {
        kind: "distributed".into(),
        actors,
        envs_per_actor: envs,
        processes: actors + 1,
        transport: transport.into(),
        learner_device: preset.train.run.device.clone(),
        learner_threads: preset.train.run.threads,
        seconds,
        env_steps_per_s: last.env_steps.saturating_sub(first.env_steps) as f64 / seconds,
        updates_per_s: last.updates.saturating_sub(first.updates) as f64 / seconds,
        replay_ratio: if inserted > 0 { last.sampled.saturating_sub(first.sampled) as f64 / inserted as f64 } else { 0.0 },
        policy_lag_mean: last.policy_lag_mean,
        policy_lag_max: last.policy_lag_max,
        act_p50_ms: latencies.get(latencies.len() / 2).copied(),
        learner_cpu,
        actors_cpu,
        actors_waited_s: last.actors_waited_s - first.actors_waited_s,
        learner_waited_s: last.learner_waited_s - first.learner_waited_s,
        discarded_steps,
        discarded_share: discarded_steps as f64 / (stored + discarded_steps).max(1) as f64,
        // Over the time between the two readings.
        actor_idle_share: waited_before.0.zip(waited_after.0).map(|(before, after)| (after - before) / (actors as f64 * waited_after.1.duration_since(waited_before.1).as_secs_f64().max(1e-9))),
        seconds_to_threshold,
    })
}

/// Env steps/s against total processes: the distributed points, the
/// single-process loop as a horizontal baseline, and the ideal linear line
/// through the first distributed point.
fn plot(points: &[ScalePoint], path: &Path, env: &str) -> anyhow::Result<()> {
    lcrl_graph_builder::plot::register_fonts();
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("cannot draw {}: {e}", path.display());
    let distributed: Vec<&ScalePoint> = points.iter().filter(|p| p.kind == "distributed").collect();
    let baseline = points.iter().find(|p| p.kind != "distributed").map_or(0.0, |p| p.env_steps_per_s);
    let max_x = distributed.iter().map(|p| p.processes).max().unwrap_or(2) as f64 + 0.5;
    let first = distributed.first().map_or((2.0, 1.0), |p| (p.processes as f64, p.env_steps_per_s));
    let ideal = |x: f64| first.1 * (x - 1.0) / (first.0 - 1.0).max(1.0);
    let max_y = distributed.iter().map(|p| p.env_steps_per_s).chain([baseline, ideal(max_x)]).fold(1.0, f64::max) * 1.1;
    let root = BitMapBackend::new(path, (800, 500)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(format!("{env}: env steps/s against processes (learner + actors)"), ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0.5..max_x, 0.0..max_y)
        .map_err(|e| err(&e))?;
    chart.configure_mesh().x_desc("processes").y_desc("env steps/s").label_style(("sans-serif", 13)).draw().map_err(|e| err(&e))?;
    let blue = RGBColor(31, 119, 180);
    for envs in distributed.iter().map(|p| p.envs_per_actor).collect::<std::collections::BTreeSet<_>>() {
        let series: Vec<(f64, f64)> = distributed.iter().filter(|p| p.envs_per_actor == envs).map(|p| (p.processes as f64, p.env_steps_per_s)).collect();
        let color = if envs == 1 { blue } else { RGBColor(214, 39, 40) };
        chart
            .draw_series(LineSeries::new(series.clone(), color.stroke_width(2)))
            .map_err(|e| err(&e))?
            .label(format!("distributed, {envs} env(s)/actor"))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
        chart.draw_series(series.iter().map(|&p| Circle::new(p, 4, color.filled()))).map_err(|e| err(&e))?;
    }
    chart
        .draw_series(DashedLineSeries::new(vec![(0.5, baseline), (max_x, baseline)], 8, 5, BLACK.stroke_width(2)))
        .map_err(|e| err(&e))?
        .label(format!("lcrl train loop, 1 process ({baseline:.0})"))
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], BLACK.stroke_width(2)));
    let grey = RGBColor(140, 140, 140);
    chart
        .draw_series(DashedLineSeries::new(vec![(1.0, 0.0), (max_x, ideal(max_x))], 4, 4, grey.stroke_width(1)))
        .map_err(|e| err(&e))?
        .label("ideal linear (from the first point)")
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], grey.stroke_width(1)));
    chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).label_font(("sans-serif", 13)).draw().map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
