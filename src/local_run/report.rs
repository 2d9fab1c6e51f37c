//! The end of a local run: its summary.json and reward curve, and the
//! lines that say what the run did beside its references.

use std::path::Path;

use anyhow::Context;
use lcrl_learner::Connection;

use crate::preset::Preset;

/// Writes the run's summary and reward curve, and says what the run did
/// beside its reference.
// args: the run's preset, directory and id, and its end (the learner's last status, wall time, how it ended, whether interrupted), each from a different step of the local run
pub(super) fn report(preset: &Preset, run_dir: &Path, s: &lcrl_proto::v1::LearnerStatus, wall: f64, end: &crate::run_summary::RunEnd, run_id: &str, interrupted: bool) -> anyhow::Result<String> {
    let job = &preset.job;
    let summary = crate::run_summary::write_run_summary(preset, run_dir, s, wall, end)?;
    let evaluation = &summary.evaluation;
    let service = summary.service.as_ref().context("the run's summary has no service figures")?;
    let curve = run_dir.join("reward_curve.png");
    plot_curve(&run_dir.join("learner/metrics.csv"), &curve, &job.env, evaluation)?;
    let reference = match (evaluation.lqr_return, evaluation.masked_lqr_return, job.connection) {
        (_, Some(masked), Connection::Local) => format!("reference: masked LQR (the best controller with G) {masked:.3}"),
        (Some(lqr), _, _) => format!("reference: LQR {lqr:.3}"),
        _ => reference_table(job, evaluation),
    };
    let which = match (&summary.selection, evaluation.last_eval_return) {
        (Some(chosen), Some(last)) => format!("the selected policy (after {} episodes, {}; the last policy scores {last:.3})", chosen.episode, chosen.how_chosen()),
        _ => "the final policy".to_string(),
    };
    Ok(format!(
        "{}run {run_id}: {} episodes, {} env steps, {} updates ({}), policy lag mean {:.1}, policy v{}, recent average return {:.3}, {:.1} s\n\
         eval return {:.3} over {} episodes of {which}; {reference}\n\
         results in {}: summary.json, config.toml, graph.json/graph.png, learner/metrics.csv (and TensorBoard events), learner/checkpoints/, reward_curve.png, logs/",
        if interrupted { "interrupted: " } else { "" },
        s.episodes,
        s.env_steps,
        s.updates,
        match (job.algo, service.replay_ratio_target > 0.0) {
            (lcrl_learner::Algo::Ppo, _) => {
                let discarded = service.discarded_stale.unwrap_or(0);
                let share = discarded as f64 / (s.env_steps + discarded).max(1) as f64;
                match preset.max_staleness().unwrap_or(0) {
                    0 => format!("PPO, on-policy: {discarded} transitions discarded as stale, {:.0}% of those simulated", 100.0 * share),
                    lag => format!("PPO, asynchronous, lag at most {lag}: {discarded} transitions discarded as staler, {:.0}% of those simulated", 100.0 * share),
                }
            }
            (_, true) => format!("replay ratio {:.1} sampled per inserted, target {:.0}", service.replay_ratio, service.replay_ratio_target),
            (_, false) => format!("replay ratio {:.1} sampled per inserted, unlimited", service.replay_ratio),
        },
        service.policy_lag.mean,
        s.policy_version,
        s.recent_return,
        wall,
        evaluation.eval_return,
        evaluation.eval_episodes.unwrap_or(preset.train.run.eval_episodes),
        run_dir.display()
    ))
}

/// The trained policy beside every reference controller, on the same
/// evaluation starts (peg tasks: a = 0, the best constant, the headroom).
fn reference_table(job: &crate::preset::Job, evaluation: &lcrl_learner::run::summary::Evaluation) -> String {
    let pct = |r: Option<f64>| r.map_or("n/a".into(), |r| format!("{:.0}%", 100.0 * r));
    let force = |f: Option<f64>| f.map_or("n/a".into(), |f| format!("{f:.1} N"));
    let trained = format!("trained: {:?} {:?}", job.algo, job.connection).to_lowercase();
    let mut rows = vec![(trained, evaluation.eval_return, evaluation.eval_success_rate, evaluation.eval_peak_force_n)];
    rows.extend(evaluation.references.iter().map(|r| (r.controller.clone(), r.mean_return, r.success_rate, r.mean_peak_force_n)));
    let mut table = format!("beside the reference controllers on the same {} starts:\n  {:<34} {:>10} {:>8} {:>11}", evaluation.eval_episodes.unwrap_or(0), "controller", "return", "success", "peak force");
    for (name, ret, success, peak) in rows {
        table.push_str(&format!("\n  {name:<34} {ret:>10.3} {:>8} {:>11}", pct(success), force(peak)));
    }
    if let Some(bar) = evaluation.references.iter().find(|r| r.controller == crate::run_summary::BEST_CONSTANT) {
        table.push_str(&format!("\n  {}", verdict_against_best_constant(evaluation.eval_return, bar.mean_return)));
    }
    table
}

/// "beats the best constant by 0.2" or "trails the best constant by 0.013":
/// the gap as a positive number, in words that say its sign.
pub fn verdict_against_best_constant(eval_return: f64, best_constant: f64) -> String {
    let gap = eval_return - best_constant;
    if gap > 0.0 {
        format!("the trained policy beats the best constant by {gap:.3}")
    } else {
        format!("the trained policy trails the best constant by {:.3}", -gap)
    }
}

fn plot_curve(metrics: &Path, out: &Path, env: &str, evaluation: &lcrl_learner::run::summary::Evaluation) -> anyhow::Result<()> {
    let Ok(mut reader) = csv::Reader::from_path(metrics) else { return Ok(()) };
    let returns: Vec<f64> = reader.records().filter_map(|r| r.ok()?.get(1)?.parse().ok()).collect();
    if returns.is_empty() {
        return Ok(());
    }
    let x: Vec<f64> = (1..=returns.len()).map(|e| e as f64).collect();
    let average: Vec<f64> = (0..returns.len())
        .map(|k| {
            let w = &returns[k.saturating_sub(19)..=k];
            w.iter().sum::<f64>() / w.len() as f64
        })
        .collect();
    let mut references = crate::run_summary::reference_lines(evaluation.lqr_return, evaluation.masked_lqr_return, evaluation.zero_action_return);
    references.extend(evaluation.references.iter().filter(|r| r.controller != crate::run_summary::ZERO_ACTION).map(|r| (r.controller.clone(), r.mean_return)));
    let panel = crate::plots::Panel::rewards("episode return", vec![("return".into(), returns), ("moving average (20)".into(), average)], references);
    crate::plots::line_panels(out, &format!("{env} — distributed run"), &x, "episode (as reported by actors)", &[panel])
}
