//! The built graph as users and other processes see it: `graph.json`, the
//! terminal table, and the gRPC message.

use std::fmt::Write as _;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::GraphError;

/// Everything `lcrl graph` writes to its JSON file. The learner reads the
/// same file back (`--graph graph.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraphReport {
    pub env: String,
    pub state_names: Vec<String>,
    pub action_names: Vec<String>,
    /// ST, CS3 samples per action.
    pub samples: usize,
    /// T of eq. 7; null when the exact rule (eq. 6) was used.
    pub threshold: Option<f64>,
    /// True for eq. 6 with a relative tolerance.
    pub exact: bool,
    /// Relative tolerance of eq. 6 (null for eq. 7).
    pub tolerance: Option<f64>,
    pub seed: u64,
    /// Rollout threads used (does not change the result).
    pub threads: usize,
    /// Bootstrap resamples behind `stability`.
    pub bootstrap_resamples: usize,
    /// phi(i, j) of eq. 5, n × m.
    pub phi: Vec<Vec<f64>>,
    /// phi divided by its column sum, n × m.
    pub phi_normalized: Vec<Vec<f64>>,
    /// G, n × m of 0/1 (action × state).
    pub g: Vec<Vec<u8>>,
    /// Share of bootstrap resamples that reproduce each G_ij, n × m; null
    /// (NaN) entries when the bootstrap was skipped.
    #[serde(deserialize_with = "nullable_matrix")]
    pub stability: Vec<Vec<f64>>,
    /// State columns no action moves (all zeros in G).
    pub unmoved_states: Vec<usize>,
    /// Where CS3's start states came from: "reset" or "trajectory".
    #[serde(default)]
    pub start: Option<String>,
    /// Each entry's margin under eq. 7: phi divided by its cut (T times the
    /// column mean), n × m; G_ij = 1 iff ≥ 1. Empty for eq. 6.
    #[serde(default)]
    pub margin: Vec<Vec<f64>>,
    /// G at other thresholds, when a sweep was asked for (`--thresholds`).
    #[serde(default)]
    pub sweep: Vec<SweepEntry>,
    /// Wall time of CS3 and thresholding, seconds.
    pub elapsed_s: f64,
    /// Where G came from when it was given, not measured: "random@23,
    /// draw seed 0" or "graph:PATH" (crate::given). Absent for CS3 graphs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<String>,
    /// Rows rebuilt under their own rule (`--row dz=0.1`, crate::rows);
    /// absent when every row follows `threshold`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rows: Vec<crate::rows::RowRule>,
}

/// G at one threshold of a sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepEntry {
    pub threshold: f64,
    /// G (n × m) under eq. 7 at this threshold.
    pub g: Vec<Vec<u8>>,
    /// Edges kept (ones in G).
    pub edges: usize,
    /// phi over this threshold's cut, n × m.
    pub margin: Vec<Vec<f64>>,
}

impl GraphReport {
    /// Adds G at each of `thresholds` (eq. 7, from the same phi).
    pub fn with_sweep(mut self, thresholds: &[f64]) -> Self {
        self.sweep = thresholds
            .iter()
            .map(|&t| {
                let g = crate::graph::connection_graph(&self.phi, crate::Rule::Threshold(t)).g;
                let edges = g.iter().flatten().filter(|&&v| v == 1).count();
                SweepEntry { threshold: t, g, edges, margin: crate::graph::margins(&self.phi, t) }
            })
            .collect();
        self
    }

    /// One line for a given graph: where it came from and its edge count.
    pub fn origin_line(&self) -> String {
        format!("graph: {} ({} of {} edges)", self.origin.as_deref().unwrap_or("given"), self.edges(), self.actions() * self.states())
    }

    /// Edges kept in G.
    pub fn edges(&self) -> usize {
        self.g.iter().flatten().filter(|&&v| v == 1).count()
    }

    /// The sweep as text: G and its edge count per T, and which edges flip
    /// between consecutive thresholds.
    pub fn sweep_table(&self) -> String {
        let mut out = String::new();
        if self.sweep.is_empty() {
            return out;
        }
        let label = self.action_names.iter().map(|s| s.len()).max().unwrap_or(0);
        let _ = writeln!(out, "\nthreshold sweep (eq. 7), columns {}:", self.state_names.join(" "));
        for (k, entry) in self.sweep.iter().enumerate() {
            let _ = writeln!(out, "T = {}: {} of {} edges", entry.threshold, entry.edges, self.actions() * self.states());
            for (i, name) in self.action_names.iter().enumerate() {
                let row: Vec<String> = entry.g[i].iter().map(u8::to_string).collect();
                let _ = writeln!(out, "  {name:<label$} [{}]", row.join(", "));
            }
            if let Some(next) = self.sweep.get(k + 1) {
                let flips: Vec<String> = (0..self.actions())
                    .flat_map(|i| (0..self.states()).map(move |j| (i, j)))
                    .filter(|&(i, j)| entry.g[i][j] != next.g[i][j])
                    .map(|(i, j)| {
                        let sign = if next.g[i][j] == 1 { '+' } else { '-' };
                        format!("{sign}{}→{}", self.action_names[i], self.state_names[j])
                    })
                    .collect();
                let listed = if flips.is_empty() { "none".to_string() } else { flips.join(", ") };
                let _ = writeln!(out, "  flips from T = {} to T = {}: {listed}", entry.threshold, next.threshold);
            }
        }
        out
    }

    pub fn actions(&self) -> usize {
        self.action_names.len()
    }

    pub fn states(&self) -> usize {
        self.state_names.len()
    }

    /// Reads a `graph.json`, checking that its matrices have the shapes its
    /// names announce and that G holds only 0 and 1.
    pub fn load(path: &Path) -> Result<Self, GraphError> {
        let text = std::fs::read_to_string(path).map_err(|source| GraphError::Io { path: path.into(), source })?;
        Self::from_json(&text, path)
    }

    /// [`GraphReport::load`] on a file's text; `path` names it in errors.
    pub fn from_json(text: &str, path: &Path) -> Result<Self, GraphError> {
        let report: GraphReport = serde_json::from_str(text)
            .map_err(|e| GraphError::BadGraphFile { path: path.into(), message: e.to_string() })?;
        let (n, m) = (report.actions(), report.states());
        let bad = |message: String| GraphError::BadGraphFile { path: path.into(), message };
        for (name, rows) in [("phi", report.phi.len()), ("g", report.g.len())] {
            if rows != n {
                return Err(bad(format!("`{name}` has {rows} rows, expected {n} (one per action name)")));
            }
        }
        if let Some(i) = report.g.iter().position(|row| row.len() != m || row.iter().any(|&v| v > 1)) {
            return Err(bad(format!("`g` row {} must hold {m} entries, each 0 or 1", i + 1)));
        }
        Ok(report)
    }

    /// Writes pretty JSON, atomically (a learner may be reading it).
    pub fn write_json(&self, path: &Path) -> Result<(), GraphError> {
        let text = serde_json::to_string_pretty(self).map_err(|e| GraphError::Json(e.to_string()))?;
        lcrl_runtime::files::write_atomically(path, (text + "\n").as_bytes()).map_err(|source| GraphError::Io { path: path.into(), source })
    }

    /// The rule, in words, for headings.
    pub fn rule_text(&self) -> String {
        match (self.exact, self.threshold) {
            (true, _) => format!("eq. 6, exact (tolerance {:e} × max phi)", self.tolerance.unwrap_or(0.0)),
            (false, Some(t)) => format!("eq. 7, T = {t}"),
            (false, None) => "eq. 7".into(),
        }
    }

    /// A labelled table: action rows, state columns, phi in every cell and
    /// `*` where G = 1; then borderline edges and unmoved states.
    pub fn table(&self) -> String {
        let mut out = String::new();
        if let Some(origin) = &self.origin {
            let _ = writeln!(out, "connection graph of {} given, not measured: {origin}", self.env);
            return out + &self.g_rows();
        }
        let _ = writeln!(
            out,
            "CS3 connection graph of {} — ST = {}, {}, starts: {}, seed {}, {:.3} s",
            self.env,
            self.samples,
            self.rule_text(),
            self.start.as_deref().unwrap_or("reset"),
            self.seed,
            self.elapsed_s
        );
        let _ = writeln!(out, "phi(i, j) (eq. 5); * marks G_ij = 1 (action i sees state j)");
        out.push_str(&self.matrix(|i, j| format!("{}{}", format_phi(self.phi[i][j]), if self.g[i][j] == 1 { '*' } else { ' ' })));
        if !self.margin.is_empty() {
            let _ = writeln!(out, "\nmargin of each kept edge, phi / (T × column mean) (≥ 1 kept; the edge survives up to margin × T):");
            out.push_str(&self.matrix(|i, j| if self.g[i][j] == 1 { format!("{:.2}", self.margin[i][j]) } else { ".".to_string() }));
        }
        out.push('\n');
        out.push_str(&self.g_rows());
        let borderline: Vec<String> = (0..self.actions())
            .flat_map(|i| (0..self.states()).map(move |j| (i, j)))
            .filter(|&(i, j)| self.stability[i][j] < 0.95)
            .map(|(i, j)| format!("{}→{} ({:.0}%)", self.action_names[i], self.state_names[j], 100.0 * self.stability[i][j]))
            .collect();
        if !borderline.is_empty() {
            let _ = writeln!(out, "\nborderline entries (share of {} bootstrap resamples that agree): {}", self.bootstrap_resamples, borderline.join(", "));
        }
        if !self.unmoved_states.is_empty() {
            let names: Vec<&str> = self.unmoved_states.iter().map(|&j| self.state_names[j].as_str()).collect();
            let _ = writeln!(out, "\nno action moves: {} (their columns are all 0)", names.join(", "));
        }
        if let (false, Some(t)) = (self.exact, self.threshold) {
            let _ = writeln!(out, "\nT = {t}: {}.", crate::choose_t::threshold_reason(t));
        }
        out
    }
}

impl GraphReport {
    /// G's rows under a heading with the edge count, columns in state order.
    fn g_rows(&self) -> String {
        let mut out = String::new();
        let label = self.action_names.iter().map(|s| s.len()).max().unwrap_or(0);
        let _ = writeln!(out, "G (action × state; columns {}), {} of {} edges:", self.state_names.join(" "), self.edges(), self.actions() * self.states());
        for (i, name) in self.action_names.iter().enumerate() {
            let row: Vec<String> = self.g[i].iter().map(u8::to_string).collect();
            let rule = self.rows.iter().find(|r| r.action == *name).map(|r| format!("  (its own rule: {})", r.text())).unwrap_or_default();
            let _ = writeln!(out, "{name:<label$} [{}]{rule}", row.join(", "));
        }
        out
    }

    /// An action × state table of `cell(i, j)` with labelled rows and columns.
    fn matrix(&self, cell: impl Fn(usize, usize) -> String) -> String {
        let mut out = String::new();
        let width = self.state_names.iter().map(|s| s.len()).max().unwrap_or(0).max(10) + 1;
        let label = self.action_names.iter().map(|s| s.len()).max().unwrap_or(0);
        let _ = write!(out, "{:<label$}", "");
        for name in &self.state_names {
            let _ = write!(out, " {name:>width$}");
        }
        out.push('\n');
        for (i, name) in self.action_names.iter().enumerate() {
            let _ = write!(out, "{name:<label$}");
            for j in 0..self.states() {
                let _ = write!(out, " {:>width$}", cell(i, j));
            }
            out.push('\n');
        }
        out
    }
}

/// JSON has no NaN: serde_json writes it as null; read null back as NaN.
fn nullable_matrix<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<Vec<f64>>, D::Error> {
    let rows: Vec<Vec<Option<f64>>> = Deserialize::deserialize(d)?;
    Ok(rows.into_iter().map(|row| row.into_iter().map(|v| v.unwrap_or(f64::NAN)).collect()).collect())
}

fn format_phi(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if (1e-3..1e4).contains(&v.abs()) {
        format!("{v:.4}")
    } else {
        format!("{v:.3e}")
    }
}

/// G (n rows of m 0/1 entries) from a graph builder's message, checked
/// against the environment that will use it: a peer's malformed graph is
/// refused here with what is wrong, never reshaped into a network.
pub fn mask_from_message(graph: &lcrl_proto::v1::ConnectionGraph, n: usize, m: usize) -> Result<Vec<Vec<u8>>, String> {
    if (graph.actions as usize, graph.states as usize) != (n, m) {
        return Err(format!("the graph builder's graph is {}×{} but this environment needs {n}×{m}", graph.actions, graph.states));
    }
    if n == 0 || m == 0 {
        return Err(format!("the graph builder's graph is {n}×{m}: it has no rows or no columns"));
    }
    if graph.g.len() != n * m {
        return Err(format!("the graph builder's G has {} entries but a {n}×{m} graph needs {}", graph.g.len(), n * m));
    }
    if let Some(k) = graph.g.iter().position(|&v| v > 1) {
        return Err(format!("the graph builder's G[{}][{}] = {}: entries must be 0 or 1", k / m, k % m, graph.g[k]));
    }
    Ok(graph.g.chunks(m).map(|row| row.iter().map(|&v| v as u8).collect()).collect())
}

impl From<&GraphReport> for lcrl_proto::v1::ConnectionGraph {
    fn from(r: &GraphReport) -> Self {
        let flat_f32 = |rows: &[Vec<f64>]| rows.iter().flatten().map(|&v| v as f32).collect();
        lcrl_proto::v1::ConnectionGraph {
            env: r.env.clone(),
            state_names: r.state_names.clone(),
            action_names: r.action_names.clone(),
            actions: r.actions() as u32,
            states: r.states() as u32,
            g: r.g.iter().flatten().map(|&v| u32::from(v)).collect(),
            phi: flat_f32(&r.phi),
            phi_normalized: flat_f32(&r.phi_normalized),
            stability: flat_f32(&r.stability),
            samples: r.samples as u32,
            threshold: r.threshold.unwrap_or(0.0),
            exact: r.exact,
            seed: r.seed,
            unmoved_states: r.unmoved_states.iter().map(|&j| j as u32).collect(),
            elapsed_s: r.elapsed_s,
        }
    }
}
