//! CS3 and the LCRL connection graph (docs/method.md §2–4).
//!
//! - [`choose_t`]: eq. 7's T chosen from CS3 reproducibility alone.
//! - [`cs3`]: Algorithm 1's paired rollouts, in parallel and deterministic.
//! - [`given`]: graphs given, not measured (a file, or K random edges).
//! - [`explain`]: one action's paired-rollout effect on one state, by phase.
//! - [`graph`]: eq. 7 / eq. 6 thresholding and per-entry stability.
//! - [`lemma1`]: the closed-form graph of a linear system.
//! - [`report`]: `graph.json`, the printed table, the gRPC message.
//! - [`plot`]: the normalized-CS3 heatmap.
//! - [`cli`]: the arguments shared by `lcrl graph` and `lcrl-graph-builder`.
//! - [`service`]: the `lcrl.v1.Graph` gRPC service.

pub mod choose_t;
pub mod cli;
pub mod cs3;
pub mod explain;
pub mod given;
pub mod graph;
pub mod lemma1;
pub mod plot;
pub mod progress;
pub mod report;
pub mod rows;
pub mod service;

use std::path::PathBuf;
use std::time::Instant;

use lcrl_sim::{Env, EnvError};

pub use cs3::{Cs3Config, Cs3Error, Cs3Samples, Start};
pub use graph::{ConnectionGraph, Rule, DEFAULT_BOOTSTRAP, EXACT_TOLERANCE, PAPER_THRESHOLD};
pub use report::{GraphReport, SweepEntry};
pub use rows::RowRule;

/// How to build a graph: CS3 sampling, the rule, and the bootstrap size.
#[derive(Debug, Clone, PartialEq)]
pub struct GraphOptions {
    pub cs3: Cs3Config,
    pub rule: Rule,
    /// Bootstrap resamples for the stability of each entry (0: skip).
    pub bootstrap: usize,
}

impl GraphOptions {
    /// The publication's graph (T of eq. 7, [`PAPER_THRESHOLD`]) from
    /// `samples` CS3 samples per action with `seed`, on every core, with
    /// `bootstrap` stability resamples.
    pub fn paper(samples: usize, seed: u64, bootstrap: usize) -> Self {
        GraphOptions { cs3: Cs3Config { samples, seed, threads: 0, start: None }, rule: Rule::Threshold(PAPER_THRESHOLD), bootstrap }
    }

    /// Rejects settings that cannot give a meaningful graph.
    pub fn validate(&self) -> Result<(), GraphError> {
        if self.cs3.samples == 0 {
            return Err(GraphError::Cs3(Cs3Error::NoSamples));
        }
        match self.rule {
            Rule::Threshold(t) if !(t.is_finite() && t > 0.0) => Err(GraphError::Threshold(t)),
            Rule::Exact { tolerance } if !(tolerance.is_finite() && tolerance >= 0.0) => {
                Err(GraphError::Tolerance(tolerance))
            }
            _ => Ok(()),
        }
    }
}

/// Algorithm 1 end to end: CS3 rollouts, the rule, normalized phi, stability.
pub fn build_graph(env: &dyn Env, opts: &GraphOptions, on_sample: &(dyn Fn() + Sync)) -> Result<GraphReport, GraphError> {
    opts.validate()?;
    let started = Instant::now();
    let pool = cs3::thread_pool(opts.cs3.threads)?;
    let (samples, phi, graph, stability) = pool.install(|| -> Result<_, GraphError> {
        let samples = cs3::measure(env, &opts.cs3, on_sample)?;
        let phi = samples.phi();
        let graph = graph::connection_graph(&phi, opts.rule);
        let stability = graph::stability(&samples, opts.rule, &graph, opts.bootstrap, opts.cs3.seed);
        Ok((samples, phi, graph, stability))
    })?;
    drop(samples);
    let spec = env.spec();
    let (threshold, exact, tolerance) = match opts.rule {
        Rule::Threshold(t) => (Some(t), false, None),
        Rule::Exact { tolerance } => (None, true, Some(tolerance)),
    };
    let margin = match opts.rule {
        Rule::Threshold(t) => graph::margins(&phi, t),
        Rule::Exact { .. } => Vec::new(),
    };
    Ok(GraphReport {
        env: spec.name.clone(),
        state_names: spec.state_names.clone(),
        action_names: spec.action_names.clone(),
        samples: opts.cs3.samples,
        threshold,
        exact,
        tolerance,
        seed: opts.cs3.seed,
        threads: pool.current_num_threads(),
        bootstrap_resamples: opts.bootstrap,
        phi_normalized: graph::normalized(&phi),
        phi,
        g: graph.g,
        stability,
        unmoved_states: graph.unmoved_states,
        start: Some(opts.cs3.start.unwrap_or_else(|| cs3::Start::default_for(env)).name().to_string()),
        margin,
        sweep: Vec::new(),
        elapsed_s: started.elapsed().as_secs_f64(),
        origin: None,
        rows: Vec::new(),
    })
}

/// Everything that can stop a graph from being built or saved.
#[derive(Debug, thiserror::Error)]
pub enum GraphError {
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Cs3(#[from] Cs3Error),
    #[error("--threshold must be a finite number above 0 (the publication uses 0.1), got {0}")]
    Threshold(f64),
    #[error("--tolerance must be a finite number ≥ 0, got {0}")]
    Tolerance(f64),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("cannot write {path}: {message}")]
    Output { path: PathBuf, message: String },
    #[error("graph file {path} is not a valid graph.json: {message}")]
    BadGraphFile { path: PathBuf, message: String },
    #[error("random@{edges}: K must be between {actions} and {entries} (at least one edge for each of the {actions} actions, at most every entry)")]
    RandomEdges { edges: usize, actions: usize, entries: usize },
    #[error("{0}")]
    Explain(String),
    #[error("{0}")]
    Row(String),
    #[error("cannot encode the graph as JSON: {0}")]
    Json(String),
    #[error("cannot draw {path}: {message}")]
    Plot { path: PathBuf, message: String },
}

#[cfg(test)]
mod tests;
