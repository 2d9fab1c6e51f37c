//! `lcrl tune`: the best constant action of an environment (CMA-ES), the
//! bar a learned agent must beat to be worth training.

use std::path::PathBuf;

use indicatif::{ProgressBar, ProgressStyle};
use lcrl_sim::tune::{tune, TuneOptions};

use crate::sim_cmd::{prepare_out_dir, print_terms};

/// Search constant actions on a fixed set of starts and write
/// best_constant.json (the bar beside trained runs in `lcrl compare`).
#[derive(Debug, clap::Args)]
pub struct TuneArgs {
    /// Environment: a registered name, a path to a .toml file, or
    /// grpc://HOST:PORT for a served one (`python -m lcrl_env serve`).
    #[arg(long)]
    pub env: String,
    /// Episodes per candidate action (the fixed tuning starts).
    #[arg(long, default_value_t = TuneOptions::default().episodes)]
    pub episodes: usize,
    /// Seed of the first tuning start (kept apart from the evaluation starts).
    #[arg(long, default_value_t = TuneOptions::default().seed)]
    pub seed: u64,
    /// Candidate actions CMA-ES may evaluate.
    #[arg(long, default_value_t = TuneOptions::default().evaluations)]
    pub evaluations: usize,
    /// Initial CMA-ES step size, in units of the action box mapped to [−1, 1].
    #[arg(long, default_value_t = TuneOptions::default().sigma)]
    pub sigma: f64,
    /// Episodes of the final evaluation (a = 0 and the winner, same starts).
    #[arg(long, default_value_t = TuneOptions::default().eval_episodes)]
    pub eval_episodes: usize,
    /// Seed of the first evaluation start; `lcrl sim --seed S --episodes N`
    /// runs the same starts.
    #[arg(long, default_value_t = TuneOptions::default().eval_seed)]
    pub eval_seed: u64,
    /// Directory for best_constant.json.
    #[arg(long, default_value = "runs/tune")]
    pub out: PathBuf,
}

pub fn run(args: &TuneArgs) -> anyhow::Result<()> {
    let env = lcrl_sim::make_env(&args.env)?;
    prepare_out_dir(&args.out)?;
    let opts = TuneOptions {
        episodes: args.episodes,
        seed: args.seed,
        evaluations: args.evaluations,
        sigma: args.sigma,
        eval_episodes: args.eval_episodes,
        eval_seed: args.eval_seed,
    };
    let bar = ProgressBar::new(args.evaluations as u64);
    if let Ok(style) = ProgressStyle::with_template("candidates [{bar:30}] {pos}/{len} {msg} ({elapsed}, eta {eta})") {
        bar.set_style(style.progress_chars("=> "));
    }
    let report = tune(env.as_ref(), &opts, &|best| {
        bar.set_message(format!("best mean return {best:.3}"));
        bar.inc(1);
    });
    bar.finish_and_clear();
    let report = report?;
    let path = args.out.join("best_constant.json");
    // Atomic: `lcrl experiment` takes an existing file as a finished tune.
    crate::output::write_atomic(&path, &(serde_json::to_string_pretty(&report)? + "\n"))?;

    let pct = |r: Option<f64>| r.map_or("n/a".into(), |r| format!("{:.0}%", 100.0 * r));
    let force = |f: Option<f64>| f.map_or("n/a".into(), |f| format!("{f:.2} N"));
    println!("best constant action of {} ({} candidates, {:.1} s):", report.env, report.evaluations, report.elapsed_s);
    for (name, a) in report.action_names.iter().zip(&report.action) {
        println!("  {name:<8} {a:>8.4}");
    }
    println!("on {} evaluation episodes from seed {}:", report.eval_episodes, report.eval_seed);
    println!("  {:<16} {:>12} {:>9} {:>12}", "controller", "mean return", "success", "peak force");
    for (label, r) in [("a = 0", &report.zero_action), ("best constant", &report.best)] {
        println!("  {label:<16} {:>12.3} {:>9} {:>12}", r.eval.mean_return, pct(r.eval.success_rate), force(r.eval.mean_peak_force_n));
    }
    print_terms(&report.terms);
    println!("  run it: lcrl sim --env {} --action {}", args.env, report.action.iter().map(|a| format!("{a:.4}")).collect::<Vec<_>>().join(","));
    println!("wrote {}", path.display());
    Ok(())
}
