//! `lcrl compare`: runs side by side, as the publication's Table II and
//! reward-curve figures show LCRL against GCRL.

use std::path::PathBuf;

use anyhow::Context;
use lcrl_learner::trainer::{EpisodeRow, TrainSummary};

use crate::plots::{line_panels, Panel};

/// Compare training runs: time split (graph, optimization, total), final
/// returns, and their reward curves in one plot.
#[derive(Debug, clap::Args)]
pub struct CompareArgs {
    /// Run directories written by `lcrl train` (or `lcrl run`).
    #[arg(required = true, num_args = 1..)]
    pub runs: Vec<PathBuf>,
    /// Moving-average window of the plotted returns, in episodes.
    #[arg(long, default_value_t = 10)]
    pub window: usize,
    /// Where to draw the reward curves (a .png file).
    #[arg(long, value_name = "FILE.png", default_value = "compare.png", value_parser = lcrl_graph_builder::plot::png_path)]
    pub out: PathBuf,
}

pub fn run(args: &CompareArgs) -> anyhow::Result<()> {
    let mut series = Vec::new();
    let mut longest: Vec<f64> = Vec::new();
    println!("{:<34} {:>8} {:>10} {:>14} {:>10} {:>13} {:>11}", "run", "episodes", "graph s", "optimization s", "total s", "final return", "eval return");
    for dir in &args.runs {
        let path = dir.join("summary.json");
        let text = std::fs::read_to_string(&path).with_context(|| format!("{} is not a finished run (no summary.json)", dir.display()))?;
        let s: TrainSummary = serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
        let metrics = dir.join("metrics.csv");
        let rows: Vec<EpisodeRow> = csv::Reader::from_path(&metrics)
            .with_context(|| format!("reading {}", metrics.display()))?
            .deserialize()
            .collect::<Result<_, _>>()
            .with_context(|| format!("reading {}", metrics.display()))?;
        let label = format!("{:?}/{:?}", s.algo, s.connection).to_lowercase();
        println!(
            "{:<34} {:>8} {:>10.2} {:>14.2} {:>10.2} {:>13.3} {:>11.3}",
            format!("{label} ({})", dir.display()),
            s.episodes,
            s.graph_seconds,
            s.optimization_seconds,
            s.total_seconds,
            s.final_return,
            s.eval_return
        );
        let returns: Vec<f64> = rows.iter().map(|r| r.episode_return).collect();
        let window = args.window.max(1);
        let smooth: Vec<f64> = (0..returns.len())
            .map(|k| {
                let w = &returns[k.saturating_sub(window - 1)..=k];
                w.iter().sum::<f64>() / w.len() as f64
            })
            .collect();
        if smooth.len() > longest.len() {
            longest = (1..=smooth.len()).map(|e| e as f64).collect();
        }
        series.push((label, smooth));
    }
    // Shorter runs are padded with NaN, which the plot leaves out.
    for (_, values) in series.iter_mut() {
        values.resize(longest.len(), f64::NAN);
    }
    let panel = Panel { y_label: format!("return, moving average ({})", args.window), series, band: None };
    line_panels(&args.out, "reward curves", &longest, "episode", &[panel])?;
    println!("wrote {}", args.out.display());
    Ok(())
}
