//! `lcrl tune`: the best constant action of an environment (CMA-ES), the
//! bar a learned agent must beat to be worth training; with `--policy`, the
//! best state-feedback controller of a simple family (the headroom above
//! that bar, docs/peg.md).

use std::path::PathBuf;

use lcrl_sim::tune::feedback::{tune_policy, Family};
use lcrl_sim::tune::{tune, TuneOptions};

use crate::cmd::sim::prepare_out_dir;
use lcrl::output::print_terms;

/// What `--policy` searches.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PolicyFamily {
    /// A constant action (best_constant.json).
    Constant,
    /// a = clip(a0 + K·ŝ) on the normalized state (best_policy.json).
    Affine,
    /// Two gain matrices, switched 2 mm below the hole entrance (best_policy.json).
    DepthSwitched,
}

/// Search constant actions on a fixed set of starts and write
/// best_constant.json (the bar beside trained runs in `lcrl compare`), or
/// with --policy a state-feedback family and write best_policy.json (how
/// much a controller that looks at the state can gain over that bar).
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
    /// Candidates CMA-ES may evaluate [default: 300 for constants, 1500
    /// for feedback policies (78 or 150 parameters on peg tasks)].
    #[arg(long)]
    pub evaluations: Option<usize>,
    /// The controller family to search.
    #[arg(long, value_enum, default_value = "constant")]
    pub policy: PolicyFamily,
    /// Feedback policies start at this constant (a best_constant.json)
    /// [default: the best constant recorded for a registered peg preset,
    /// else a = 0].
    #[arg(long, value_name = "best_constant.json")]
    pub start: Option<PathBuf>,
    /// Initial CMA-ES step size, in units of the action box mapped to
    /// [−1, 1] [default: 0.3 for constants, 0.1 for feedback policies].
    #[arg(long)]
    pub sigma: Option<f64>,
    /// Episodes of the final evaluation (a = 0 and the winner, same starts).
    #[arg(long, default_value_t = TuneOptions::default().eval_episodes)]
    pub eval_episodes: usize,
    /// Seed of the first evaluation start; `lcrl sim --seed S --episodes N`
    /// runs the same starts.
    #[arg(long, default_value_t = TuneOptions::default().eval_seed)]
    pub eval_seed: u64,
    /// Directory for best_constant.json or best_policy.json.
    #[arg(long, default_value = "runs/tune")]
    pub out: PathBuf,
}

pub fn run(args: &TuneArgs) -> anyhow::Result<()> {
    let env = lcrl_sim::make_env(&args.env)?;
    prepare_out_dir(&args.out)?;
    let pct = |r: Option<f64>| r.map_or("n/a".into(), |r| format!("{:.0}%", 100.0 * r));
    let force = |f: Option<f64>| f.map_or("n/a".into(), |f| format!("{f:.2} N"));
    let constant = args.policy == PolicyFamily::Constant;
    let opts = TuneOptions {
        episodes: args.episodes,
        seed: args.seed,
        evaluations: args.evaluations.unwrap_or(if constant { TuneOptions::default().evaluations } else { 1500 }),
        sigma: args.sigma.unwrap_or(if constant { TuneOptions::default().sigma } else { 0.1 }),
        eval_episodes: args.eval_episodes,
        eval_seed: args.eval_seed,
    };
    let bar = lcrl_graph_builder::progress::bar(opts.evaluations as u64, "candidates [{bar:30}] {pos}/{len} {msg} ({elapsed}, eta {eta})");
    let family = match args.policy {
        PolicyFamily::Constant => None,
        PolicyFamily::Affine => Some(Family::Affine),
        PolicyFamily::DepthSwitched => Some(Family::DepthSwitched),
    };
    if let Some(family) = family {
        let n = env.spec().action_dim();
        let start = match &args.start {
            Some(path) => lcrl_learner::policy::action::read_best_constant(path)?,
            None => lcrl_sim::peg::measured_best_constant(&env.spec().name).map_or(vec![0.0; n], |a| a.to_vec()),
        };
        let report = tune_policy(env.as_ref(), family, &start, &opts, &|best| {
            bar.set_message(format!("best mean return {best:.3}"));
            bar.inc(1);
        });
        bar.finish_and_clear();
        let mut report = report?;
        // On a linear system the optimum is known: LQR on the same starts.
        report.lqr_return = lcrl_sim::lti::LtiEnv::of(env.as_ref()).and_then(|lti| lcrl_learner::algo::lqr::lqr_return(lti, report.record.eval_episodes, report.record.eval_seed));
        let path = args.out.join("best_policy.json");
        lcrl::output::write_atomic(&path, &(serde_json::to_string_pretty(&report)? + "\n"))?;
        println!("best {:?} policy of {} ({} candidates, {:.1} s):", family, report.record.env, report.record.evaluations, report.record.elapsed_s);
        println!("on {} evaluation episodes from seed {}:", report.record.eval_episodes, report.record.eval_seed);
        println!("  {:<22} {:>12} {:>9} {:>12}", "controller", "mean return", "success", "peak force");
        for (label, r) in [("a = 0", &report.record.zero_action), ("start constant", &report.start_constant), ("feedback policy", &report.record.best)] {
            println!("  {label:<22} {:>12.3} {:>9} {:>12}", r.eval.mean_return, pct(r.eval.success_rate), force(r.eval.mean_peak_force_n));
        }
        if let Some(lqr) = report.lqr_return {
            println!("  {:<22} {lqr:>12.3}", "LQR (the optimum)");
        }
        print_terms(&report.record.terms);
        println!("wrote {}", path.display());
        return Ok(());
    }
    let report = tune(env.as_ref(), &opts, &|best| {
        bar.set_message(format!("best mean return {best:.3}"));
        bar.inc(1);
    });
    bar.finish_and_clear();
    let report = report?;
    let path = args.out.join("best_constant.json");
    // Atomic: `lcrl experiment` takes an existing file as a finished tune.
    lcrl::output::write_atomic(&path, &(serde_json::to_string_pretty(&report)? + "\n"))?;

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
