//! `lcrl sim`: runs a controller on an environment and writes
//! summary.json, episodes.csv (one row per episode: which starts failed,
//! how hard each pushed), trace.csv and trace.png.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use lcrl_learner::policy::trained::evaluate_snapshot;
use lcrl_sim::evaluate::{evaluate_parallel_with, EpisodeRecord, Summary};
use lcrl_sim::Env;

use lcrl::plots::{line_panels, Panel};

/// Run a controller on an environment and report what it achieved.
#[derive(Debug, clap::Args)]
pub struct SimArgs {
    /// Environment: a registered name (peg-group1, peg-group2, peg-experiment,
    /// lti-paper), a path to a .toml file, or grpc://HOST:PORT for a served
    /// environment (python -m lcrl_env serve). With --checkpoint it defaults
    /// to the environment the policy was trained on.
    #[arg(long, required_unless_present = "checkpoint")]
    pub env: Option<String>,
    /// Evaluate a trained policy instead: a checkpoint folder
    /// (RUN/checkpoints/epNNNNNN) or a run directory (its newest checkpoint).
    #[arg(long, value_name = "DIR", conflicts_with = "controller")]
    pub checkpoint: Option<PathBuf>,
    /// The controller: `constant` is the constant compliance controller
    /// (a = 0, docs/method.md §6), the non-learning baseline.
    #[arg(long, value_enum, default_value_t = Controller::Constant)]
    pub controller: Controller,
    /// Run this constant action instead of a = 0: n comma-separated
    /// revision factors (peg: dx,dy,dz,dalpha,dbeta,dgamma within
    /// [−1,2]³×[−1,4]³), e.g. the `action` of a best_constant.json.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, conflicts_with = "checkpoint", value_name = "A1,…,An")]
    pub action: Option<Vec<f64>>,
    /// Episodes to run; seeds are seed, seed+1, …
    #[arg(long, default_value_t = 10)]
    pub episodes: usize,
    /// Seed of the first episode's initial pose error.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Directory for summary.json, episodes.csv (one row per start),
    /// trace.csv (first episode) and trace.png. To trace another start,
    /// run it alone: --seed S --episodes 1.
    #[arg(long, default_value = "runs/sim")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum Controller {
    Constant,
}

pub fn run(args: &SimArgs) -> anyhow::Result<()> {
    if args.episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    let policy = args.checkpoint.as_deref().map(lcrl_learner::policy::trained::Policy::load).transpose()?;
    // What every evaluation thread builds its own copy of the network from.
    let snapshot = args
        .checkpoint
        .as_deref()
        .map(|dir| lcrl_learner::policy::trained::policy_dir(dir).and_then(|dir| lcrl_learner::policy::snapshot::read_snapshot(&dir)))
        .transpose()?;
    let env_name = match (&args.env, &policy, &args.checkpoint) {
        (Some(name), _, _) => name.clone(),
        (None, Some(policy), Some(dir)) => lcrl::recorded_env::environment_to_build(&policy.architecture.shape.env, None, dir)?,
        _ => bail!("--env is required without --checkpoint"),
    };
    let env = lcrl_sim::make_env(&env_name)?;
    if let Some(policy) = &policy {
        policy.check_env(env.as_ref())?;
    }
    prepare_out_dir(&args.out)?;
    let n = env.spec().action_dim();
    let constant = match &args.action {
        Some(action) => {
            env.spec().check_action(action).with_context(|| format!("--action for {env_name}"))?;
            let clipped = env.spec().clip_action(action);
            if clipped != *action {
                bail!(
                    "--action {action:?} lies outside the action box [{:?}, {:?}] of {env_name}",
                    env.spec().action_low,
                    env.spec().action_high
                );
            }
            action.clone()
        }
        None => vec![0.0; n],
    };
    let label = match &policy {
        Some(policy) => format!("{:?}/{:?} policy (episode {})", policy.architecture.shape.algo, policy.architecture.shape.connection, policy.episode.unwrap_or(0)).to_lowercase(),
        None if args.action.is_some() => format!("constant a = {constant:?}"),
        None => "constant".to_string(),
    };
    let bar = lcrl_graph_builder::progress::bar(args.episodes as u64, "episodes [{bar:30}] {pos}/{len} {msg} ({elapsed})");
    let on_episode = |r: &EpisodeRecord| {
        bar.set_message(format!("return {:.2}", r.episode_return));
        bar.inc(1);
    };
    // The episodes run on every core (RAYON_NUM_THREADS=1: one), with the
    // records of one thread.
    let result = match &snapshot {
        Some(snapshot) => evaluate_snapshot(env.as_ref(), &label, snapshot, args.episodes, args.seed, &on_episode).map_err(anyhow::Error::from),
        None => evaluate_parallel_with(env.as_ref(), &label, args.episodes, args.seed, &|| Ok(|_: &[f64]| constant.clone()), &on_episode).map_err(anyhow::Error::from),
    };
    bar.finish_and_clear();
    let (summary, records) = result?;
    write_outputs(env.as_ref(), &summary, &records, &args.out)?;
    print_summary(&summary, &args.out);
    Ok(())
}

/// Creates the directory and proves it writable before any episode runs.
pub fn prepare_out_dir(dir: &Path) -> anyhow::Result<()> {
    fs::create_dir_all(dir).with_context(|| format!("cannot create output directory {}", dir.display()))?;
    tempfile::tempfile_in(dir).with_context(|| format!("output directory {} is not writable", dir.display()))?;
    Ok(())
}

/// summary.json, episodes.csv, and the first episode's trace.csv and trace.png.
fn write_outputs(env: &dyn Env, summary: &Summary, records: &[EpisodeRecord], dir: &Path) -> anyhow::Result<()> {
    let path = dir.join("summary.json");
    lcrl::output::write_atomic(&path, &(serde_json::to_string_pretty(summary)? + "\n"))?;
    write_episodes_csv(records, &dir.join("episodes.csv"))?;
    let first = records.first().context("no episode ran")?;
    write_trace_csv(env, first, &dir.join("trace.csv"))?;
    plot_trace(env, summary, first, &dir.join("trace.png"))
}

fn write_trace_csv(env: &dyn Env, record: &EpisodeRecord, path: &Path) -> anyhow::Result<()> {
    let spec = env.spec();
    let mut out = csv::Writer::from_path(path).with_context(|| format!("writing {}", path.display()))?;
    let mut header = vec!["step".to_string(), "time_s".to_string()];
    header.extend(spec.state_names.iter().cloned());
    header.extend(spec.action_names.iter().map(|a| format!("action_{a}")));
    header.push("reward".into());
    out.write_record(&header)?;
    let mut first = vec!["0".to_string(), "0".to_string()];
    first.extend(record.initial_state.iter().map(f64::to_string));
    first.extend(std::iter::repeat_n(String::new(), spec.action_dim() + 1));
    out.write_record(&first)?;
    for row in &record.trace {
        let mut fields = vec![row.step.to_string(), row.time_s.to_string()];
        fields.extend(row.state.iter().map(f64::to_string));
        fields.extend(row.action.iter().map(f64::to_string));
        fields.push(row.reward.to_string());
        out.write_record(&fields)?;
    }
    out.flush().with_context(|| format!("writing {}", path.display()))
}

/// One row per episode, in seed order: a start that failed, or came near a
/// limit, can be found and traced on its own (`--seed S --episodes 1`).
/// Columns a task does not measure are left empty.
fn write_episodes_csv(records: &[EpisodeRecord], path: &Path) -> anyhow::Result<()> {
    let mut out = csv::Writer::from_path(path).with_context(|| format!("writing {}", path.display()))?;
    out.write_record(["seed", "steps", "return", "terminated", "success", "failed", "peak_force_n", "peak_moment_nm", "max_penetration_mm", "max_action_jump"])?;
    let opt = |v: Option<f64>| v.map_or(String::new(), |v| v.to_string());
    let flag = |v: Option<bool>| v.map_or(String::new(), |v| v.to_string());
    for r in records {
        let m = &r.metrics;
        // The failure charge is paid exactly when a limit was exceeded (docs/peg.md).
        let failed = m.return_terms.map(|t| t.failure != 0.0);
        out.write_record([
            r.seed.to_string(),
            r.steps.to_string(),
            r.episode_return.to_string(),
            r.terminated.to_string(),
            flag(m.success),
            flag(failed),
            opt(m.peak_force_n),
            opt(m.peak_moment_nm),
            opt(m.max_penetration_mm),
            r.max_action_jump.to_string(),
        ])?;
    }
    out.flush().with_context(|| format!("writing {}", path.display()))
}

/// Force and moment over the insertion (depth, force, moment panels), as a
/// robotics paper shows them; other environments get their states over time.
fn plot_trace(env: &dyn Env, summary: &Summary, record: &EpisodeRecord, path: &Path) -> anyhow::Result<()> {
    let names = &env.spec().state_names;
    let column = |name: &str| names.iter().position(|n| n == name);
    let series = |j: usize| -> Vec<f64> {
        std::iter::once(record.initial_state[j]).chain(record.trace.iter().map(|r| r.state[j])).collect()
    };
    let time: Vec<f64> = std::iter::once(0.0).chain(record.trace.iter().map(|r| r.time_s)).collect();
    let named = |labels: &[&str]| -> Option<Vec<(String, Vec<f64>)>> {
        labels.iter().map(|l| column(l).map(|j| (l.to_string(), series(j)))).collect()
    };
    let title = format!("{} — {} controller, episode seed {}", summary.env, summary.controller, record.seed);
    let panels = match (named(&["z"]), named(&["Fx", "Fy", "Fz"]), named(&["Mx", "My", "Mz"])) {
        (Some(z), Some(f), Some(m)) => vec![
            Panel::lines("remaining depth z [mm]", z),
            Panel::lines("contact force [N]", f),
            Panel::lines("contact moment [N·m]", m),
        ],
        _ => vec![Panel::lines("state", names.iter().enumerate().map(|(j, n)| (n.clone(), series(j))).collect())],
    };
    line_panels(path, &title, &time, "time [s]", &panels)
}

fn print_summary(s: &Summary, dir: &Path) {
    let opt = |v: Option<f64>, unit: &str| v.map_or("n/a".to_string(), |v| format!("{v:.3}{unit}"));
    println!("{} episodes of {} with the {} controller:", s.episodes, s.env, s.controller);
    println!("  success rate          {}", s.success_rate.map_or("n/a".into(), |r| format!("{:.0}%", r * 100.0)));
    println!("  mean steps to insert  {}", opt(s.mean_steps_to_insert, ""));
    println!("  mean peak force       {}", opt(s.mean_peak_force_n, " N"));
    println!("  mean peak moment      {}", opt(s.mean_peak_moment_nm, " N·m"));
    println!("  max penetration       {}", opt(s.max_penetration_mm, " mm"));
    println!("  mean return           {:.3} (min {:.3}, max {:.3})", s.mean_return, s.min_return, s.max_return);
    lcrl::output::print_terms(&s.terms);
    println!("  control steps/s       {:.0}", s.control_steps_per_sec);
    println!("wrote {}/summary.json, episodes.csv, trace.csv, trace.png", dir.display());
}

