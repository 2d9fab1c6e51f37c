//! The study's figures: curves.png (the publication's Fig. 6: mean return
//! over seeds with its min–max band, one colour per connection) and
//! traces.png (Fig. 7: force and moment over one insertion from the initial
//! error [0.2 mm ×3, 0.5° ×3] for a = 0, the best constant and the median
//! GCRL and LCRL agents).

use std::path::Path;

use anyhow::Context;
use lcrl_learner::policy::trained::Policy;
use lcrl_sim::peg::{PegConfig, PegEnv};
use lcrl_sim::Env;

use super::config::algo_name;
use super::report::{CellRuns, Study};
use super::stats::AVERAGE_WINDOW;
use crate::plots::{line_panels, Panel};

/// One panel per environment × algorithm.
fn groups(study: &Study) -> Vec<Vec<&CellRuns>> {
    let mut out: Vec<Vec<&CellRuns>> = Vec::new();
    for c in &study.cells {
        match out.iter_mut().find(|g| g[0].cell.env == c.cell.env && g[0].cell.algo == c.cell.algo) {
            Some(group) => group.push(c),
            None => out.push(vec![c]),
        }
    }
    out
}

/// The 10-episode moving average of one run's returns.
fn moving_average(returns: &[f64]) -> Vec<f64> {
    (0..returns.len())
        .map(|k| {
            let window = &returns[k.saturating_sub(AVERAGE_WINDOW - 1)..=k];
            window.iter().sum::<f64>() / window.len() as f64
        })
        .collect()
}

pub fn curves(study: &Study, path: &Path) -> anyhow::Result<()> {
    let mut panels = Vec::new();
    for group in groups(study) {
        let (env, algo) = (&group[0].cell.env, group[0].cell.algo);
        let episodes = study.experiment.episodes(algo);
        let mut series = Vec::new();
        let mut bands = Vec::new();
        for cell in &group {
            let smoothed: Vec<Vec<f64>> = cell.runs.iter().map(|r| moving_average(&r.returns)).collect();
            if smoothed.is_empty() {
                continue;
            }
            let at = |k: usize| smoothed.iter().filter_map(move |s| s.get(k).copied());
            let mean: Vec<f64> = (0..episodes).map(|k| at(k).sum::<f64>() / at(k).count().max(1) as f64).collect();
            let low: Vec<f64> = (0..episodes).map(|k| at(k).fold(f64::INFINITY, f64::min)).collect();
            let high: Vec<f64> = (0..episodes).map(|k| at(k).fold(f64::NEG_INFINITY, f64::max)).collect();
            bands.push((series.len(), low, high));
            series.push((format!("{} ({} seeds)", cell.label(), cell.runs.len()), mean));
        }
        let mut references = Vec::new();
        if let Some(b) = study.best_constant.get(env) {
            references.push(("best constant".to_string(), b.mean_return));
            references.push(("a = 0".to_string(), b.zero_action_return));
        }
        if let Some(p) = study.best_policy.get(env) {
            references.push(("headroom (best feedback policy)".to_string(), p.mean_return));
        }
        let mut panel = Panel::rewards(format!("{env}, {}: return (avg 10)", algo_name(algo).to_uppercase()), series, references);
        panel.bands = bands;
        panel.x = Some((1..=episodes).map(|k| k as f64).collect());
        panels.push(panel);
    }
    let title = format!("experiment {}: mean over seeds, band min–max", study.experiment.file.name);
    line_panels(path, &title, &[0.0, 1.0], "episode", &panels).with_context(|| format!("drawing {}", path.display()))
}

/// The publication's testing start: 0.2 mm along x, y and z, 0.5° about
/// each axis (peg presets). Other environments start from episode seed 0.
fn testing_env(env: &str) -> anyhow::Result<(Box<dyn Env>, String)> {
    match PegConfig::preset(env) {
        Some(mut cfg) => {
            let e = &mut cfg.episode;
            e.position_error_mm = 0.0;
            e.angle_error_deg = 0.0;
            e.position_offset_mm = [0.2, 0.2];
            e.angle_offset_deg = [0.5; 3];
            e.start_height_mm += 0.2;
            Ok((Box::new(PegEnv::new(env, cfg)?), "initial error 0.2 mm ×3, 0.5° ×3".into()))
        }
        None => Ok((lcrl_sim::make_env(env)?, "episode seed 0".into())),
    }
}

/// One episode's (time, ‖F‖, ‖M‖) or, without forces, (time, ‖s‖).
struct Trace {
    time: Vec<f64>,
    panels: Vec<Vec<f64>>,
}

fn rollout(env: &mut dyn Env, act: &mut dyn FnMut(&[f64]) -> Vec<f64>) -> anyhow::Result<Trace> {
    let names = env.spec().state_names.clone();
    let find = |labels: [&str; 3]| labels.iter().map(|l| names.iter().position(|n| n == l)).collect::<Option<Vec<usize>>>();
    let groups: Vec<Vec<usize>> = match (find(["Fx", "Fy", "Fz"]), find(["Mx", "My", "Mz"])) {
        (Some(f), Some(m)) => vec![f, m],
        _ => vec![(0..names.len()).collect()],
    };
    let norm = |s: &[f64], idx: &[usize]| idx.iter().map(|&j| s[j] * s[j]).sum::<f64>().sqrt();
    let mut state = env.reset(0)?;
    let mut trace = Trace { time: vec![0.0], panels: groups.iter().map(|g| vec![norm(&state, g)]).collect() };
    for k in 1.. {
        let step = env.step(&act(&state))?;
        state = step.state;
        trace.time.push(k as f64 * env.control_period_s());
        for (values, g) in trace.panels.iter_mut().zip(&groups) {
            values.push(norm(&state, g));
        }
        if step.terminated || step.truncated {
            break;
        }
    }
    Ok(trace)
}

pub fn traces(study: &Study, path: &Path) -> anyhow::Result<()> {
    let mut panels = Vec::new();
    let mut start_note = String::new();
    for group in groups(study) {
        let (env_name, algo) = (&group[0].cell.env, group[0].cell.algo);
        let (mut env, note) = testing_env(env_name)?;
        start_note = note;
        let n = env.spec().action_dim();
        let mut runs: Vec<(String, Trace)> = vec![("a = 0".into(), rollout(env.as_mut(), &mut |_| vec![0.0; n])?)];
        if let Some(b) = study.best_constant.get(env_name) {
            let action = b.action.clone();
            runs.push(("best constant".into(), rollout(env.as_mut(), &mut |_| action.clone())?));
        }
        for cell in &group {
            let Some(run) = cell.median_run() else { continue };
            let label = format!("{} (seed {}, median)", cell.label(), run.seed);
            // An archived study (scripts/archive-study.sh) keeps summaries,
            // not policies: its report is still written, without this trace.
            let policy = match Policy::load(&run.dir) {
                Ok(policy) => policy,
                Err(err) => {
                    eprintln!("traces.png: leaving out {env_name} {} {label}: {err}", algo_name(algo));
                    continue;
                }
            };
            let scales = env.fresh();
            runs.push((label, rollout(env.as_mut(), &mut |s| policy.act(scales.as_ref(), s))?));
        }
        let longest = runs.iter().map(|(_, t)| t.time.len()).max().unwrap_or(0);
        let x = runs.iter().find(|(_, t)| t.time.len() == longest).map(|(_, t)| t.time.clone()).unwrap_or_default();
        let labels = if runs[0].1.panels.len() == 2 { vec!["‖F‖ [N]", "‖M‖ [N·m]"] } else { vec!["‖s‖"] };
        for (k, label) in labels.iter().enumerate() {
            let series = runs.iter().map(|(name, t)| (name.clone(), t.panels[k].clone())).collect();
            let mut panel = Panel::lines(format!("{env_name}, {}: {label}", algo_name(algo).to_uppercase()), series);
            panel.x = Some(x.clone());
            panels.push(panel);
        }
    }
    let title = format!("experiment {}: one episode from {start_note}", study.experiment.file.name);
    line_panels(path, &title, &[0.0, 1.0], "time [s]", &panels).with_context(|| format!("drawing {}", path.display()))
}

/// advantage.png for a study of `lti-blocks-N` environments (and only
/// then; returns false otherwise): LCRL's advantage against N, per
/// algorithm and per baseline the study has (global, full-subnets, each
/// matched global), as (local − baseline) eval return over |masked LQR|
/// (the gap's share of the optimum; above 0: LCRL better), with Welch's
/// 95% interval as an error bar. The local cells are those with a
/// measured graph. A companion study's cell of a baseline's connection
/// (`--with`, e.g. the global actor at another learning rate) is a second
/// series in that baseline's panel, at the N it ran.
pub fn advantage(study: &Study, path: &Path) -> anyhow::Result<bool> {
    use crate::connection::ConnectionSpec as C;
    let sizes: Option<Vec<usize>> = study.experiment.file.environments.iter().map(|e| lcrl_sim::lti::LtiConfig::blocks_size(e)).collect();
    let Some(sizes) = sizes else { return Ok(false) };
    // Every connection, the study's and its companions', has a cell.
    let mut baselines: Vec<&C> = Vec::new();
    for c in study.cells.iter().map(|c| &c.cell.connection).filter(|c| matches!(c, C::Global | C::FullSubnets | C::MatchedGlobal { .. })) {
        if !baselines.contains(&c) {
            baselines.push(c);
        }
    }
    let studies: Vec<Option<&str>> = std::iter::once(None).chain(study.companions.iter().map(|c| Some(c.name.as_str()))).collect();
    let mut panels = Vec::new();
    for &algo in &study.experiment.file.algorithms {
        for &baseline in &baselines {
            let (mut series, mut bands) = (Vec::new(), Vec::new());
            for &from in &studies {
                // Per N: the local cell (the study's own: the one a matched
                // global matches, else the first measured graph without
                // modifiers) against the baseline cell of `from`.
                let pairs: Vec<Option<(&CellRuns, &CellRuns)>> = study
                    .experiment
                    .file
                    .environments
                    .iter()
                    .map(|env| {
                        let find = |from: Option<&str>, pick: &dyn Fn(&C) -> bool| {
                            study.cells.iter().find(|c| &c.cell.env == env && c.cell.algo == algo && c.from.as_deref() == from && pick(&c.cell.connection))
                        };
                        let is_local = |c: &C| match baseline {
                            C::MatchedGlobal { to } => c == to.as_ref(),
                            _ => c.threshold().is_some() && !c.has_modifiers(),
                        };
                        find(None, &is_local).zip(find(from, &|c| c == baseline))
                    })
                    .collect();
                let differences: Vec<Option<super::stats::Welch>> = pairs
                    .iter()
                    .map(|pair| {
                        let (local, other) = (*pair)?;
                        let optimum = local.runs.iter().find_map(|r| r.summary.evaluation.masked_lqr_return).unwrap_or(1.0).abs().max(1e-9);
                        let eval = |c: &CellRuns| c.runs.iter().map(|r| r.summary.evaluation.eval_return / optimum).collect::<Vec<f64>>();
                        super::stats::welch(&eval(local), &eval(other))
                    })
                    .collect();
                let Some((local, other)) = pairs.iter().zip(&differences).find_map(|(pair, w)| w.as_ref().and(*pair)) else { continue };
                let column = |f: fn(&super::stats::Welch) -> f64| differences.iter().map(|w| w.as_ref().map_or(f64::NAN, f)).collect::<Vec<f64>>();
                bands.push((series.len(), column(|w| w.ci95[0]), column(|w| w.ci95[1])));
                series.push((format!("{} − {}", local.cell.connection.label(), other.label()), column(|w| w.difference)));
            }
            if series.is_empty() {
                continue;
            }
            let mut panel = Panel::lines(format!("{}: (local − {}) / |masked LQR|", algo_name(algo), baseline.label()), series);
            panel.bands = bands;
            panel.markers = true;
            panel.references.push(("no difference".into(), 0.0));
            panels.push(panel);
        }
    }
    if panels.is_empty() {
        return Ok(false);
    }
    let xs = sizes.iter().map(|&n| n as f64).collect::<Vec<f64>>();
    line_panels(path, "LCRL's advantage against N (lti-blocks-N, 95% interval)", &xs, "N (actions; 2N states)", &panels)
        .with_context(|| format!("drawing {}", path.display()))?;
    Ok(true)
}
