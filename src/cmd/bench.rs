//! `lcrl bench`: performance figures, measured as ratios within one run
//! because machine noise is large.

use std::time::Instant;

use clap::Subcommand;
use lcrl_graph_builder::{build_graph, Cs3Config, GraphOptions};
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
    /// DDPG update time and a PPO rollout's learner time (storing 2,048
    /// steps and the update), local vs global actor, per device and
    /// libtorch thread count; with the PyTorch-eager equivalent when a
    /// Python with torch is at hand (ratios within one run).
    Learner {
        /// DDPG updates to time per setting.
        #[arg(long, default_value_t = 300)]
        updates: usize,
        /// Where the networks compute.
        #[arg(long, default_value = "cpu", value_parser = ["cpu", "cuda"])]
        device: String,
        /// libtorch intra-op thread counts to measure.
        #[arg(long, value_delimiter = ',', default_value = "1")]
        threads: Vec<usize>,
        /// Rounds per thread count: each round times every actor once, in
        /// turn, and the medians are printed (a busy machine's noise falls
        /// on all of them alike).
        #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=50))]
        rounds: u32,
        /// The training settings timed: `presets`, the peg presets' own
        /// (configs/peg.toml with peg-group1.toml: ELU, twin critics, policy
        /// delay 2, the trust region toward the target actor), what
        /// configs/peg-group1-*.toml train; or `table1`,
        /// docs/method.md Table I's (ReLU, one critic), the settings the
        /// PyTorch-eager reference repeats.
        #[arg(long, default_value = "presets", value_parser = ["presets", "table1"])]
        settings: String,
        /// The Python whose torch times the same DDPG update eagerly
        /// (scripts/bench_torch_ddpg.py, with `--settings table1`)
        /// [default: this project's .venv]; `none` skips it.
        #[arg(long)]
        python: Option<String>,
    },
    /// gRPC ingestion rate, Policy.Act latency, and end-to-end environment
    /// steps/s with 1 and 2 actors (real lcrl-learner / lcrl-actor processes).
    Transport {
        /// Seconds per measurement.
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
    },
    /// The learner's updates/s with `--threads 1` against
    /// `OMP_NUM_THREADS=1` exported, each beside N processes busy at nice
    /// 10 (one actor, `lcrl scale`'s distributed and single-process
    /// points), in turn over a few rounds: threads that obey keep at least
    /// 0.9 of what OpenMP's own setting gives.
    Busy {
        /// The preset measured.
        #[arg(long, default_value = "configs/peg-group1-ddpg-local.toml")]
        config: std::path::PathBuf,
        /// Busy processes beside the learner.
        #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(0..=64))]
        busy: u32,
        /// Seconds per measurement window.
        #[arg(long, default_value_t = 8.0)]
        seconds: f64,
        /// Rounds (each runs both settings once).
        #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=20))]
        rounds: u32,
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
    /// Control steps per second of peg-group1 on one core (and, with
    /// valgrind on the PATH, instructions per step, which machine noise
    /// does not move), and a 100-episode evaluation on 1 thread against all.
    Sim {
        /// Episodes per setting.
        #[arg(long, default_value_t = 100)]
        episodes: usize,
    },
    /// `lcrl tune`'s best-constant search on peg-group1 (a short one) on 1
    /// thread against every core, and whether both found the same constant.
    Tune {
        /// Candidates CMA-ES evaluates.
        #[arg(long, default_value_t = 60)]
        evaluations: usize,
        /// Tuning starts per candidate.
        #[arg(long, default_value_t = 16)]
        episodes: usize,
    },
    /// The episodes `bench sim` counts instructions of, run under valgrind
    /// by `bench sim` itself.
    #[command(hide = true)]
    SimEpisodes {
        #[arg(long)]
        episodes: usize,
        #[arg(long)]
        substeps: usize,
    },
}

pub fn run(command: BenchCommand) -> anyhow::Result<()> {
    match command {
        BenchCommand::Graph { samples, repeats } => bench_graph(samples, repeats.max(1)),
        BenchCommand::Sim { episodes } => crate::cmd::bench_sim::run(episodes.max(1)),
        BenchCommand::Tune { evaluations, episodes } => crate::cmd::bench_sim::tune(evaluations.max(2), episodes.max(1)),
        BenchCommand::SimEpisodes { episodes, substeps } => crate::cmd::bench_sim::episodes(episodes, substeps),
        BenchCommand::Learner { updates, device, threads, rounds, settings, python } => {
            bench_learner(updates.max(1), &device, &threads, rounds as usize, settings == "table1", python.as_deref())
        }
        BenchCommand::Transport { seconds } => {
            // At least 1 s per measurement; at most an hour (1e300 s would
            // overflow the deadline's clock arithmetic).
            if !(seconds.is_finite() && seconds <= 3600.0) {
                anyhow::bail!("--seconds must be a number of seconds up to 3600, got {seconds}");
            }
            crate::cmd::bench_transport::run(seconds.max(1.0))
        }
        BenchCommand::Env { gym, instances, steps } => crate::cmd::bench_env::run(&gym, &instances, steps.max(1)),
        BenchCommand::Busy { config, busy, seconds, rounds } => crate::cmd::bench_busy::run(&config, busy as usize, seconds, rounds as usize),
    }
}

/// One DDPG update (batch 256) and one PPO rollout's learner work (storing
/// 2048 steps, then the update: 10 epochs of 64-transition minibatches) on
/// the peg presets' settings (configs/peg.toml with peg-group1.toml, what
/// `configs/peg-group1-*.toml` train) or on Table I's, for the global
/// actor, the local one on the presets' graph (T_rule) and on the
/// publication's (T = 0.1), and full subnetworks, for each thread count on
/// `device`, the median of `rounds` interleaved rounds; then, on Table I's
/// settings, the same DDPG update in PyTorch eager (global actor).
fn bench_learner(updates: usize, device: &str, threads: &[usize], rounds: usize, table1: bool, python: Option<&str>) -> anyhow::Result<()> {
    use lcrl_graph_builder::choose_t::RULE_THRESHOLD;
    use lcrl_learner::Connection;
    if threads.is_empty() || threads.iter().any(|&t| t == 0 || t > lcrl_learner::device::torch::MAX_THREADS) {
        anyhow::bail!("--threads takes counts from 1 to {}", lcrl_learner::device::torch::MAX_THREADS);
    }
    let torch_device = lcrl_learner::device::torch::resolve_device(device)?;
    let env_name = "peg-group1";
    let env = lcrl_sim::make_env(env_name)?;
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    let (mut cfg, source) = if table1 { (lcrl_learner::TrainConfig::default(), "Table I's settings") } else { lcrl_learner::TrainConfig::for_env(env_name) };
    if !table1 && source == lcrl_learner::TrainConfig::TABLE1_SOURCE {
        anyhow::bail!("the peg presets' embedded settings did not load (a build defect): `--settings table1` times Table I's");
    }
    cfg.ddpg.warmup_steps = 0;
    cfg.run.device = device.to_string();
    // The presets' graph: CS3 with their graph_samples, cut at T_rule and
    // at the publication's T (one measurement, two cuts).
    let options = GraphOptions { rule: lcrl_graph_builder::Rule::Threshold(RULE_THRESHOLD), ..GraphOptions::paper(cfg.run.graph_samples, cfg.run.seed, 0) };
    let report = build_graph(env.as_ref(), &options, &|| {})?;
    let rule_mask = report.g.clone();
    let paper_mask = lcrl_graph_builder::graph::connection_graph(&report.phi, lcrl_graph_builder::Rule::Threshold(lcrl_graph_builder::PAPER_THRESHOLD)).g;
    let edges = |g: &[Vec<u8>]| -> usize { g.iter().flatten().map(|&v| usize::from(v)).sum() };
    let rule_label = format!("Local@{RULE_THRESHOLD}");
    let paper_label = format!("Local@{}", lcrl_graph_builder::PAPER_THRESHOLD);
    println!(
        "{env_name} ({m} states, {n} actions) on {source}: {:?} activations, DDPG batch {}, twin critics {}, policy delay {}, proximal_l2 {}, {updates} updates per setting, on {device} ({} cores here)",
        cfg.network.activation,
        cfg.ddpg.batch_size,
        cfg.ddpg.twin_critics,
        cfg.ddpg.policy_delay,
        cfg.ddpg.proximal_l2,
        lcrl_learner::device::torch::available_cores()
    );
    println!(
        "G from {} CS3 samples: {} of {} edges at T_rule = {RULE_THRESHOLD} (the presets' graph), {} at T = {} (the publication's)",
        cfg.run.graph_samples,
        edges(&rule_mask),
        m * n,
        edges(&paper_mask),
        lcrl_graph_builder::PAPER_THRESHOLD
    );
    println!("{:>7} {:<16} {:>13} {:>16} {:>12} {:>20}", "threads", "actor", "actor params", "DDPG update ms", "updates/s", "PPO rollout s");
    let settings_of_actor: [(String, Connection, &[Vec<u8>]); 4] = [
        ("Global".to_string(), Connection::Global, &rule_mask),
        (rule_label.clone(), Connection::Local, &rule_mask),
        (paper_label.clone(), Connection::Local, &paper_mask),
        ("FullSubnets".to_string(), Connection::FullSubnets, &rule_mask),
    ];
    let mut globals: Vec<(usize, f64)> = Vec::new();
    for &t in threads {
        tch::set_num_threads(t as i32);
        let timed = time_rounds(&cfg, &settings_of_actor, rounds, updates, torch_device)?;
        print_rows(t, &timed, &[&rule_label, &paper_label], torch_device.is_cuda());
        // The first row is the global actor's, eager.
        let global = median(&timed[0].ddpg);
        if let Some(&(first, seconds)) = globals.first() {
            println!("{t:>7} global DDPG update: {:.2}× the speed of {first} thread(s)", seconds / global);
        }
        globals.push((t, global));
    }
    if !table1 {
        println!("PyTorch eager: its reference repeats Table I's update; `--settings table1` times both");
        return Ok(());
    }
    torch_eager(python, device, threads, updates, (m, n, cfg.ddpg.batch_size), &globals)
}

/// Each actor's medians at `t` threads, then each local actor of `locals`
/// against the global one (the first row): the median of the rounds'
/// ratios (the same machine state within a round), eager against eager and,
/// on a GPU, CUDA graphs against CUDA graphs.
fn print_rows(t: usize, timed: &[Timed], locals: &[&str], cuda: bool) {
    for actor in timed {
        let (ddpg, ppo) = (median(&actor.ddpg), median(&actor.ppo));
        println!("{t:>7} {:<16} {:>13} {:>16.3} {:>12.0} {ppo:>20.3}", actor.label, actor.params, ddpg * 1e3, 1.0 / ddpg);
    }
    let find = |name: &str| timed.iter().find(|a| a.label == name).expect("every actor was timed");
    let ratio = |a: &[f64], b: &[f64]| median(&a.iter().zip(b).map(|(x, y)| x / y).collect::<Vec<_>>());
    let global = find("Global");
    for name in locals {
        let local = find(name);
        println!(
            "{t:>7} {name} / global: DDPG update {:.2}×, PPO rollout {:.2}× (medians of the rounds' ratios; the goal: at most 1.00×)",
            ratio(&local.ddpg, &global.ddpg),
            ratio(&local.ppo, &global.ppo)
        );
        // On a GPU the DDPG updates train as CUDA graphs by default.
        if cuda {
            let (local, global) = (find(&format!("{name}+graphs")), find("Global+graphs"));
            println!("{t:>7} {name} / global, as CUDA graphs: DDPG update {:.2}×", ratio(&local.ddpg, &global.ddpg));
        }
    }
}

/// One actor's times, one per round.
struct Timed {
    label: String,
    ddpg: Vec<f64>,
    ppo: Vec<f64>,
    params: usize,
}

/// Every actor of `actors` (label, connection, graph) timed once per round,
/// in turn, each round starting with another (no setting is always timed
/// first, on a warmer or colder machine); on a GPU eager updates first,
/// then the same replayed from CUDA graphs (`run.cuda_graphs`; ignored on
/// the CPU). In the order of `actors`.
fn time_rounds(cfg: &lcrl_learner::TrainConfig, actors: &[(String, lcrl_learner::Connection, &[Vec<u8>])], rounds: usize, updates: usize, device: tch::Device) -> anyhow::Result<Vec<Timed>> {
    let graph_settings: &[bool] = if device.is_cuda() { &[false, true] } else { &[false] };
    // One row per (actor, graphs), in the order of `actors`, eager first.
    let mut timed: Vec<Timed> = actors
        .iter()
        .flat_map(|(name, ..)| graph_settings.iter().map(move |&graphs| if graphs { format!("{name}+graphs") } else { name.clone() }))
        .map(|label| Timed { label, ddpg: Vec::new(), ppo: Vec::new(), params: 0 })
        .collect();
    for round in 0..rounds {
        for k in 0..actors.len() {
            let index = (k + round) % actors.len();
            let (_, connection, mask) = &actors[index];
            for (g, &graphs) in graph_settings.iter().enumerate() {
                let cfg = lcrl_learner::TrainConfig { run: lcrl_learner::config::RunConfig { cuda_graphs: graphs, ..cfg.run.clone() }, ..cfg.clone() };
                let (ddpg, ppo, params) = time_updates(&cfg, *connection, mask, updates, device)?;
                let row = &mut timed[index * graph_settings.len() + g];
                row.ddpg.push(ddpg);
                row.ppo.push(ppo);
                row.params = params;
            }
        }
    }
    Ok(timed)
}

/// The median of `values` (not empty).
fn median(values: &[f64]) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let k = sorted.len() / 2;
    if sorted.len() % 2 == 1 { sorted[k] } else { (sorted[k - 1] + sorted[k]) / 2.0 }
}

/// Seconds per DDPG update and per PPO rollout (stored and trained on),
/// and the actor's parameters, for the graph `mask` (n × m: a row per
/// action, a column per state).
/// Updates are timed as a whole after a synchronizing read, so a GPU's
/// asynchronous launches are counted when they finish, not when queued.
fn time_updates(cfg: &lcrl_learner::TrainConfig, connection: lcrl_learner::Connection, mask: &[Vec<u8>], updates: usize, device: tch::Device) -> anyhow::Result<(f64, f64, usize)> {
    use lcrl_learner::algo::agent::Transition;
    use lcrl_learner::algo::algorithms::make_agent;
    use lcrl_learner::Algo;
    use rand::{Rng, SeedableRng};

    let (n, m) = (mask.len(), mask[0].len());
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut random = |len: usize| -> Vec<f32> { (0..len).map(|_| rng.random_range(-1.0..1.0)).collect() };
    let sync = || {
        if let tch::Device::Cuda(k) = device {
            tch::Cuda::synchronize(k as i64);
        }
    };
    let mut ddpg = make_agent(Algo::Ddpg, connection, cfg, mask, m, n)?;
    for _ in 0..cfg.ddpg.batch_size {
        let (obs, action, next) = (random(m), random(n), random(m));
        ddpg.store(Transition { obs: &obs, action: &action, reward: -1.0, next_obs: &next, terminated: false, truncated: false, log_prob: None, ..Default::default() });
    }
    // Warm-up updates (allocator, kernels' first launches) are not timed.
    for _ in 0..10 {
        ddpg.train_step();
    }
    sync();
    let started = Instant::now();
    for _ in 0..updates {
        ddpg.train_step();
    }
    sync();
    let ddpg_seconds = started.elapsed().as_secs_f64() / updates as f64;

    // The learner's whole work on one rollout: storing its steps (each
    // with the log-probability an actor sends) and the update. The steps
    // are drawn first, so acting is not timed.
    let mut ppo = make_agent(Algo::Ppo, connection, cfg, mask, m, n)?;
    let steps: Vec<(Vec<f32>, Vec<f32>, Vec<f32>)> = (0..cfg.ppo.rollout_steps).map(|_| (random(m), random(n), random(m))).collect();
    let started = Instant::now();
    for (obs, action, next) in &steps {
        ppo.observe(Transition { obs, action, reward: -1.0, next_obs: next, terminated: false, truncated: false, log_prob: Some(-1.0), ..Default::default() });
    }
    sync();
    let ppo_seconds = started.elapsed().as_secs_f64();
    Ok((ddpg_seconds, ppo_seconds, ddpg.param_counts().0))
}

/// The same DDPG update (global actor, Table I sizes) in PyTorch eager, per
/// thread count, and lcrl's speed against it.
fn torch_eager(python: Option<&str>, device: &str, threads: &[usize], updates: usize, (m, n, batch): (usize, usize, usize), lcrl: &[(usize, f64)]) -> anyhow::Result<()> {
    let python = match python {
        Some("none") => return Ok(()),
        Some(path) => std::path::PathBuf::from(path),
        None => match lcrl::binaries::lcrl_python() {
            Ok(path) => path,
            Err(_) => {
                println!("PyTorch eager: skipped (no .venv Python; pass --python)");
                return Ok(());
            }
        },
    };
    let script = match lcrl::binaries::project_file("scripts/bench_torch_ddpg.py") {
        Ok(script) => script,
        Err(e) => {
            println!("PyTorch eager: skipped ({e})");
            return Ok(());
        }
    };
    let threads_arg = threads.iter().map(ToString::to_string).collect::<Vec<_>>().join(",");
    let out = std::process::Command::new(&python)
        .arg(&script)
        .args(["--device", device, "--threads", &threads_arg, "--updates", &updates.to_string()])
        .args(["--states", &m.to_string(), "--actions", &n.to_string(), "--batch", &batch.to_string()])
        .output()
        .map_err(|e| anyhow::anyhow!("starting {}: {e}", python.display()))?;
    if !out.status.success() {
        println!("PyTorch eager: skipped ({} failed: {})", script.display(), String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or("no message"));
        return Ok(());
    }
    // Lines "THREADS MS_PER_UPDATE VERSION".
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let fields: Vec<&str> = line.split_whitespace().collect();
        let (Some(t), Some(ms), Some(version)) = (fields.first(), fields.get(1).and_then(|v| v.parse::<f64>().ok()), fields.get(2)) else { continue };
        let against = match lcrl.iter().find(|(lt, _)| lt.to_string() == *t) {
            Some((_, seconds)) => format!(", lcrl's global update {:.2}× its time", seconds * 1e3 / ms),
            None => String::new(),
        };
        println!("{t:>7} PyTorch {version} eager DDPG update (global): {ms:.3} ms{against}");
    }
    Ok(())
}

fn bench_graph(samples: usize, repeats: usize) -> anyhow::Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let systems = [
        ("lti-paper (3×3)", LtiEnv::new("lti-paper", &LtiConfig::paper_example())?),
        ("random 12×6", LtiEnv::new("random-12x6", &LtiConfig::random_sparse(12, 6, 0.25, 42))?),
    ];
    println!("CS3 graph build, ST = {samples}, eq. 7, {} bootstrap resamples; median of {repeats}", lcrl_graph_builder::DEFAULT_BOOTSTRAP);
    println!("{:<18} {:>12} {:>12} {:>14}", "system", "1 thread", format!("{cores} threads"), "speed-up");
    for (label, env) in &systems {
        let time = |threads: usize| -> anyhow::Result<f64> {
            let options = GraphOptions { cs3: Cs3Config { samples, seed: 0, threads, start: None }, ..GraphOptions::paper(samples, 0, lcrl_graph_builder::DEFAULT_BOOTSTRAP) };
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
