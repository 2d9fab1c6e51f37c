//! `lcrl graph --explain ACTION,STATE`: where one entry of phi comes from.
//!
//! phi(i, j) (eq. 5) averages Algorithm 1's paired rollouts over start
//! states. On the peg task those starts lie along an a = 0 insertion, so an
//! edge can come from one stretch of it only: a lateral compliance factor
//! moves the tilt only once the peg touches the hole. This splits the same
//! samples CS3 draws by the phase of their start state, and shows, per
//! phase, how much of phi(i, j) it holds, the effect step by step, and the
//! states that move first (the physical path from action i to state j).

use std::fmt::Write as _;

use lcrl_sim::Env;
use rayon::prelude::*;

use crate::cs3::{paired_trace, sample_seed, PairedTrace, Start};
use crate::{Cs3Config, GraphError};

/// Where along an insertion a CS3 sample starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Phase {
    /// Above the hole entrance, no contact force.
    FreeMotion,
    /// At or above the entrance (within 2 mm below it), touching the hole.
    FirstContact,
    /// In the hole, with more than a tenth of the depth left.
    Sliding,
    /// The last tenth of the depth.
    Inserted,
    /// Tasks without an insertion depth: every start.
    Any,
}

impl Phase {
    pub fn name(&self) -> &'static str {
        match self {
            Phase::FreeMotion => "free motion",
            Phase::FirstContact => "first contact",
            Phase::Sliding => "sliding",
            Phase::Inserted => "inserted",
            Phase::Any => "every start",
        }
    }

    /// The phase of state `s` of `env`: by the remaining depth (state 2,
    /// against the hole entrance's) and the contact force (states named
    /// Fx, Fy, Fz), where the task has them.
    pub fn of(env: &dyn Env, s: &[f64]) -> Phase {
        let Some(entrance) = env.depth_reference_mm() else { return Phase::Any };
        let names = &env.spec().state_names;
        let force: f64 = ["Fx", "Fy", "Fz"]
            .iter()
            .filter_map(|f| names.iter().position(|n| n == f))
            .map(|j| s[j] * s[j])
            .sum::<f64>()
            .sqrt();
        let z = s[2];
        if z >= entrance - 2.0 {
            if force > 0.01 { Phase::FirstContact } else { Phase::FreeMotion }
        } else if z > 0.1 * entrance {
            Phase::Sliding
        } else {
            Phase::Inserted
        }
    }
}

/// One phase's share of phi(i, j).
#[derive(Debug, Clone, PartialEq)]
pub struct PhaseEffect {
    pub phase: Phase,
    pub samples: usize,
    /// This phase's part of phi(i, j): the sum of its samples' eq. 5
    /// brackets over ST, so the parts add up to phi(i, j).
    pub phi_part: f64,
    /// Mean |s'_{t+1,j} − s_{t+1,j}| at each step t of its samples.
    pub per_step: Vec<f64>,
    /// Mean normalized |Δ| of every state at each step (the path).
    pub all_states_per_step: Vec<Vec<f64>>,
}

/// phi(i, j) split by phase.
#[derive(Debug, Clone, PartialEq)]
pub struct Explanation {
    pub env: String,
    pub action: usize,
    pub state: usize,
    pub action_name: String,
    pub state_names: Vec<String>,
    pub samples: usize,
    pub start: Start,
    pub phi: f64,
    pub phases: Vec<PhaseEffect>,
}

/// Looks up "ACTION,STATE" by name (e.g. "dx,alpha") or by 1-based index.
pub fn parse_pair(env: &dyn Env, text: &str) -> Result<(usize, usize), String> {
    let spec = env.spec();
    let (a, s) = text.split_once(',').ok_or_else(|| format!("--explain wants ACTION,STATE such as dx,alpha; got \"{text}\""))?;
    let find = |names: &[String], key: &str, what: &str| {
        let key = key.trim();
        names
            .iter()
            .position(|n| n == key)
            .or_else(|| key.parse::<usize>().ok().filter(|k| (1..=names.len()).contains(k)).map(|k| k - 1))
            .ok_or_else(|| format!("--explain: no {what} \"{key}\" in {}; its {what}s are {}", spec.name, names.join(", ")))
    };
    Ok((find(&spec.action_names, a, "action")?, find(&spec.state_names, s, "state")?))
}

/// Runs the ST samples of action `i` exactly as CS3 does (same seeds, so
/// the parts add up to the graph's phi(i, j)) and splits them by phase.
pub fn explain(env: &dyn Env, cfg: &Cs3Config, i: usize, j: usize, on_sample: &(dyn Fn() + Sync)) -> Result<Explanation, GraphError> {
    env.check_snapshot()?;
    let spec = env.spec();
    let m = spec.state_dim();
    let start = cfg.start.unwrap_or_else(|| Start::default_for(env));
    let traces: Vec<PairedTrace> = crate::cs3::thread_pool(cfg.threads)?.install(|| {
        (0..cfg.samples)
            .into_par_iter()
            .map(|k| {
                let trace = paired_trace(env, start, i, sample_seed(cfg.seed, i, k));
                on_sample();
                trace
            })
            .collect::<Result<Vec<_>, _>>()
    })?;
    // |Δ| in the agent's units, so states of different units compare.
    let zero = env.normalize_state(&vec![0.0; m]);
    let scale: Vec<f64> = (0..m)
        .map(|j| {
            let mut unit = vec![0.0; m];
            unit[j] = 1.0;
            (env.normalize_state(&unit)[j] - zero[j]).abs()
        })
        .collect();
    let mut phases: Vec<PhaseEffect> = Vec::new();
    let mut sorted: Vec<(Phase, &PairedTrace)> = traces.iter().map(|t| (Phase::of(env, &t.start_state), t)).collect();
    sorted.sort_by_key(|(p, _)| *p);
    for (phase, trace) in sorted {
        if phases.last().map(|p| p.phase) != Some(phase) {
            phases.push(PhaseEffect { phase, samples: 0, phi_part: 0.0, per_step: vec![0.0; m], all_states_per_step: vec![vec![0.0; m]; m] });
        }
        let Some(part) = phases.last_mut() else { continue };
        part.samples += 1;
        for (t, effect) in trace.effects.iter().enumerate() {
            part.phi_part += effect[j];
            part.per_step[t] += effect[j];
            for (acc, (d, s)) in part.all_states_per_step[t].iter_mut().zip(effect.iter().zip(&scale)) {
                *acc += d * s;
            }
        }
    }
    for part in &mut phases {
        let k = part.samples as f64;
        part.phi_part /= cfg.samples as f64;
        part.per_step.iter_mut().for_each(|v| *v /= k);
        part.all_states_per_step.iter_mut().flatten().for_each(|v| *v /= k);
    }
    Ok(Explanation {
        env: spec.name.clone(),
        action: i,
        state: j,
        action_name: spec.action_names[i].clone(),
        state_names: spec.state_names.clone(),
        samples: cfg.samples,
        start,
        phi: phases.iter().map(|p| p.phi_part).sum(),
        phases,
    })
}

impl Explanation {
    /// The table `lcrl graph --explain` prints.
    pub fn text(&self) -> String {
        let (a, s) = (&self.action_name, &self.state_names[self.state]);
        let mut out = String::new();
        let _ = writeln!(
            out,
            "where phi({a}, {s}) = {:.4e} comes from ({}: ST = {} paired rollouts from {} starts, split by the phase of s_0)",
            self.phi,
            self.env,
            self.samples,
            self.start.name()
        );
        let _ = writeln!(out, "{:<14} {:>7} {:>13}  mean |Δ{s}| at steps t = 1, 2, …", "phase", "samples", "share of phi");
        for p in &self.phases {
            let share = if self.phi > 0.0 { 100.0 * p.phi_part / self.phi } else { 0.0 };
            let steps: Vec<String> = p.per_step.iter().map(|v| format!("{v:.2e}")).collect();
            let _ = writeln!(out, "{:<14} {:>7} {:>12.1}%  {}", p.phase.name(), p.samples, share, steps.join(" "));
        }
        if let Some(main) = self.phases.iter().max_by(|x, y| x.phi_part.total_cmp(&y.phi_part)) {
            let _ = writeln!(out, "\npath in {} (the largest share): the states {a} moves most at each step (normalized |Δ|):", main.phase.name());
            for (t, row) in main.all_states_per_step.iter().enumerate().take(4) {
                let mut order: Vec<usize> = (0..row.len()).collect();
                order.sort_by(|&x, &y| row[y].total_cmp(&row[x]));
                let top: Vec<String> = order.iter().take(4).filter(|&&k| row[k] > 0.0).map(|&k| format!("{} {:.3}", self.state_names[k], row[k])).collect();
                let rank = order.iter().position(|&k| k == self.state).map_or(0, |r| r + 1);
                let _ = writeln!(out, "  t = {}: {}  ({s}: rank {rank}, {:.3})", t + 1, if top.is_empty() { "nothing moves".into() } else { top.join(", ") }, row[self.state]);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cs3::measure;

    #[test]
    fn phase_parts_add_up_to_cs3_phi() {
        let env = lcrl_sim::make_env("lti-paper").unwrap();
        let cfg = Cs3Config { samples: 16, seed: 3, threads: 1, start: None };
        let phi = measure(env.as_ref(), &cfg, &|| {}).unwrap().phi();
        for (i, j) in [(1, 0), (0, 0), (0, 2)] {
            let e = explain(env.as_ref(), &cfg, i, j, &|| {}).unwrap();
            assert_eq!(e.phases.len(), 1, "a linear system has no insertion phases");
            assert_eq!(e.phases[0].phase, Phase::Any);
            assert!((e.phi - phi[i][j]).abs() <= 1e-12 * phi[i][j].max(1.0), "({i}, {j}): {} against {}", e.phi, phi[i][j]);
        }
        // a2 reaches s1 only through s2 (eq. 10): nothing at t = 1, then an effect.
        let e = explain(env.as_ref(), &cfg, 1, 0, &|| {}).unwrap();
        assert_eq!(e.phases[0].per_step[0], 0.0);
        assert!(e.phases[0].per_step[1] > 0.0);
        assert!(e.text().contains("t = 1: s2"), "{}", e.text());
    }

    #[test]
    fn peg_phases_split_the_samples_and_add_up() {
        let env = lcrl_sim::make_env("peg-group1").unwrap();
        let cfg = Cs3Config { samples: 24, seed: 0, threads: 0, start: None };
        let phi = measure(env.as_ref(), &cfg, &|| {}).unwrap().phi();
        let e = explain(env.as_ref(), &cfg, 0, 3, &|| {}).unwrap();
        assert_eq!(e.phases.iter().map(|p| p.samples).sum::<usize>(), 24);
        assert!(e.phases.iter().all(|p| p.phase != Phase::Any));
        assert!((e.phi - phi[0][3]).abs() <= 1e-9 * phi[0][3].max(1e-12), "{} against {}", e.phi, phi[0][3]);
    }

    #[test]
    fn pairs_parse_by_name_or_index_and_errors_list_the_names() {
        let env = lcrl_sim::make_env("peg-group1").unwrap();
        assert_eq!(parse_pair(env.as_ref(), "dx,alpha").unwrap(), (0, 3));
        assert_eq!(parse_pair(env.as_ref(), "2, 12").unwrap(), (1, 11));
        let err = parse_pair(env.as_ref(), "dq,alpha").unwrap_err();
        assert!(err.contains("no action \"dq\"") && err.contains("dx, dy"), "{err}");
        assert!(parse_pair(env.as_ref(), "dx").unwrap_err().contains("ACTION,STATE"));
    }
}
