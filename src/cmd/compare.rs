//! `lcrl compare`: runs side by side, as the publication's Table II and
//! reward-curve figures show LCRL against GCRL, with the best constant
//! controller as the bar.

use std::path::PathBuf;

use anyhow::Context;
use lcrl_learner::run::files::EpisodeRow;
use lcrl_learner::run::summary::RunSummary;
use serde::Deserialize;

use lcrl::plots::{line_panels, Panel};
use lcrl::run_summary::references;

/// Compare training runs: time split (graph, optimization, total), final
/// and evaluation returns, and their reward curves in one plot, beside the
/// reference controllers (LQR on linear systems, a = 0, the best constant).
#[derive(Debug, clap::Args)]
pub struct CompareArgs {
    /// Run directories written by `lcrl train` (or `lcrl run`).
    #[arg(required = true, num_args = 1..)]
    pub runs: Vec<PathBuf>,
    /// Moving-average window of the plotted returns, in episodes.
    #[arg(long, default_value_t = 10)]
    pub window: usize,
    /// The bar: a best_constant.json written by `lcrl tune`, shown as a row
    /// of the table and a line in the plot.
    #[arg(long, value_name = "best_constant.json")]
    pub best_constant: Option<PathBuf>,
    /// The headroom: a best_policy.json of `lcrl tune --policy affine` (or
    /// depth-switched), the best state-feedback controller of that family,
    /// shown as a row and a line beside the best constant.
    #[arg(long, value_name = "best_policy.json")]
    pub best_policy: Option<PathBuf>,
    /// The environment to evaluate a run on again (on the common starts),
    /// where the name it was trained on is a served environment's address
    /// or a TOML file outside the run: a file never chooses where lcrl
    /// connects (docs/security.md).
    #[arg(long)]
    pub env: Option<String>,
    /// Where to draw the reward curves (a .png file).
    #[arg(long, value_name = "FILE.png", default_value = "compare.png", value_parser = lcrl_graph_builder::plot::png_path)]
    pub out: PathBuf,
}

/// The parts of best_constant.json (and of best_policy.json, which has
/// the same fields) that compare shows.
#[derive(Debug, Deserialize)]
struct BestConstant {
    env: String,
    action: Vec<f64>,
    mean_return: f64,
    success_rate: Option<f64>,
    eval_episodes: usize,
    #[serde(default)]
    eval_seed: u64,
    zero_action: ZeroAction,
}

/// The evaluation starts every row of the table is measured on: episodes
/// from `seed` on (lcrl_sim::seeds), `episodes` of them.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Starts {
    seed: u64,
    episodes: usize,
}

#[derive(Debug, Deserialize)]
struct ZeroAction {
    eval: lcrl_sim::evaluate::SummaryReturn,
}

pub fn run(args: &CompareArgs) -> anyhow::Result<()> {
    let bar = read_reference(&args.best_constant, "best_constant.json")?;
    let headroom = read_reference(&args.best_policy, "best_policy.json")?;
    if let (Some(b), Some(h)) = (&bar, &headroom) {
        if (b.eval_seed, b.eval_episodes) != (h.eval_seed, h.eval_episodes) {
            anyhow::bail!(
                "the best constant and the best policy were evaluated on different starts (seeds {}.. × {} and {}.. × {}); evaluate them again with one `lcrl tune ... --eval-episodes N` run each",
                b.eval_seed, b.eval_episodes, h.eval_seed, h.eval_episodes
            );
        }
    }
    // Every row on one set of starts: the references' (lcrl tune's), or the
    // first run's own; a run evaluated elsewhere is evaluated again here.
    let starts = bar.as_ref().or(headroom.as_ref()).map(|r| Starts { seed: r.eval_seed, episodes: r.eval_episodes });
    println!("{}", match starts {
        Some(s) => format!("every row evaluated on the same {} starts (seeds {} on, those of `lcrl tune`)", s.episodes, s.seed),
        None => "every row evaluated on the first run's evaluation starts".to_string(),
    });
    let mut starts = starts;
    let mut series = Vec::new();
    let mut longest: Vec<f64> = Vec::new();
    let mut lines = Vec::new();
    println!("{:<34} {:>8} {:>10} {:>14} {:>10} {:>13} {:>11} {:>8}", "run", "episodes", "graph s", "optimization s", "total s", "final return", "eval return", "success");
    for dir in &args.runs {
        let (label, s, rows) = read_run(dir, [(&bar, "best constant"), (&headroom, "best policy")], &mut starts, args.env.as_deref())?;
        for line in references(&s) {
            if !lines.iter().any(|(name, _): &(String, f64)| *name == line.0) {
                lines.push(line);
            }
        }
        let smooth = moving_average(&rows, args.window.max(1));
        if smooth.len() > longest.len() {
            longest = (1..=smooth.len()).map(|e| e as f64).collect();
        }
        series.push((label, smooth));
    }
    lines.extend(print_references(bar.as_ref(), headroom.as_ref()));
    // Shorter runs are padded with NaN, which the plot leaves out.
    for (_, values) in series.iter_mut() {
        values.resize(longest.len(), f64::NAN);
    }
    let panel = Panel::rewards(format!("return, moving average ({})", args.window), series, lines);
    line_panels(&args.out, "reward curves", &longest, "episode", &[panel])?;
    println!("wrote {}", args.out.display());
    Ok(())
}

/// A reference `lcrl tune` wrote (`what` names the file), if given.
fn read_reference(path: &Option<PathBuf>, what: &str) -> anyhow::Result<Option<BestConstant>> {
    match path {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            Ok(Some(serde_json::from_str(&text).with_context(|| format!("{} is not a {what} written by `lcrl tune`", path.display()))?))
        }
        None => Ok(None),
    }
}

/// A finished run's label, summary and episodes, checked against the
/// references' environment; its row of the table is printed.
fn read_run(dir: &std::path::Path, references: [(&Option<BestConstant>, &str); 2], starts: &mut Option<Starts>, env: Option<&str>) -> anyhow::Result<(String, RunSummary, Vec<EpisodeRow>)> {
    let path = dir.join("summary.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("{} is not a finished run (no summary.json)", dir.display()))?;
    let mut s: RunSummary = serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
    let own = s.evaluation.eval_episodes.zip(s.evaluation.eval_seed).map(|(episodes, seed)| Starts { seed, episodes });
    let starts = match *starts {
        Some(s) => s,
        None => *starts.insert(own.with_context(|| format!("{} does not record its evaluation starts; give --best-constant (its starts are then every row's) or evaluate it with `lcrl sim --checkpoint {}`", dir.display(), dir.display()))?),
    };
    if own != Some(starts) {
        s.evaluation.eval_return = evaluate_on(dir, &s.env, env, starts)?;
        s.evaluation.eval_success_rate = None;
    }
    for (reference, what) in references {
        if let Some(r) = reference {
            if r.env != s.env {
                anyhow::bail!("{} was trained on {} but the {what} is for {}; compare runs of one environment", dir.display(), s.env, r.env);
            }
        }
    }
    let metrics = dir.join("metrics.csv");
    let rows: Vec<EpisodeRow> = csv::Reader::from_path(&metrics)
        .with_context(|| format!("reading {}", metrics.display()))?
        .deserialize()
        .collect::<Result<_, _>>()
        .with_context(|| format!("reading {}", metrics.display()))?;
    let label = format!("{:?}/{:?}", s.algo, s.connection).to_lowercase();
    println!(
        "{:<34} {:>8} {:>10.2} {:>14.2} {:>10.2} {:>13.3} {:>11.3} {:>8}",
        format!("{label} ({})", dir.display()),
        s.episodes,
        s.graph_seconds,
        s.optimization_seconds,
        s.total_seconds,
        s.final_return,
        s.evaluation.eval_return,
        s.evaluation.eval_success_rate.map_or("n/a".into(), |r| format!("{:.0}%", 100.0 * r)),
    );
    Ok((label, s, rows))
}

/// The run's handed-over policy (RUN/selected, else its newest checkpoint;
/// RUN/learner/ for `lcrl run`) evaluated deterministically on `starts`.
fn evaluate_on(dir: &std::path::Path, env_name: &str, given: Option<&str>, starts: Starts) -> anyhow::Result<f64> {
    let folder = if dir.join("learner").is_dir() { dir.join("learner") } else { dir.to_path_buf() };
    let policy = lcrl_learner::policy::trained::Policy::load(&folder)
        .with_context(|| format!("{} has no policy to evaluate on the common starts; compare runs evaluated on them (`lcrl train --eval-seed {} --eval-episodes {}`)", dir.display(), starts.seed, starts.episodes))?;
    let env_name = lcrl::recorded_env::environment_to_build(env_name, given, &folder)?;
    let mut env = lcrl_sim::make_env(&env_name)?;
    let probe = env.fresh();
    let (summary, _) = lcrl_sim::evaluate::evaluate(env.as_mut(), "run", starts.episodes, starts.seed, &mut |state| policy.act(probe.as_ref(), state), &mut |_| {})?;
    eprintln!("{}: evaluated again on the common starts (its own were others)", dir.display());
    Ok(summary.mean_return)
}

/// Returns averaged over the last `window` episodes (fewer at the start).
fn moving_average(rows: &[EpisodeRow], window: usize) -> Vec<f64> {
    let returns: Vec<f64> = rows.iter().map(|r| r.episode_return).collect();
    (0..returns.len())
        .map(|k| {
            let w = &returns[k.saturating_sub(window - 1)..=k];
            w.iter().sum::<f64>() / w.len() as f64
        })
        .collect()
}

/// The best constant, a = 0 and the best feedback policy as rows of the
/// table; the plot's lines for them.
fn print_references(bar: Option<&BestConstant>, headroom: Option<&BestConstant>) -> Vec<(String, f64)> {
    let mut lines = Vec::new();
    if let Some(bar) = bar {
        let pct = bar.success_rate.map_or("n/a".into(), |r| format!("{:.0}%", 100.0 * r));
        println!(
            "{:<34} {:>8} {:>10} {:>14} {:>10} {:>13} {:>11.3} {:>8}",
            "best constant (lcrl tune)", "-", "-", "-", "-", "-", bar.mean_return, pct
        );
        println!(
            "{:<34} {:>8} {:>10} {:>14} {:>10} {:>13} {:>11.3}",
            "a = 0", "-", "-", "-", "-", "-", bar.zero_action.eval.mean_return
        );
        println!(
            "(constants: mean of {} evaluation episodes of `lcrl tune`; best a = {:?}. A trained agent is worth its training only above the best constant.)",
            bar.eval_episodes,
            bar.action.iter().map(|a| (a * 1e4).round() / 1e4).collect::<Vec<_>>()
        );
        lines.push(("best constant".to_string(), bar.mean_return));
    }
    if let Some(policy) = headroom {
        let pct = policy.success_rate.map_or("n/a".into(), |r| format!("{:.0}%", 100.0 * r));
        println!(
            "{:<34} {:>8} {:>10} {:>14} {:>10} {:>13} {:>11.3} {:>8}",
            "best feedback policy (lcrl tune)", "-", "-", "-", "-", "-", policy.mean_return, pct
        );
        println!("(the headroom: the best state-feedback controller `lcrl tune --policy` found, mean of {} evaluation episodes.)", policy.eval_episodes);
        lines.push(("best feedback policy".to_string(), policy.mean_return));
    }
    lines
}
