//! Graphs given rather than measured (docs/lcrl-value.md): a graph file
//! written elsewhere (`graph:PATH`, e.g. the publication's own graph) and
//! K edges drawn at random (`random@K`), the control that asks whether a
//! graph's structure matters or only how many inputs each subnetwork gets.
//!
//! Both come back as a [`GraphReport`] with `origin` saying where G came
//! from and no CS3 values (phi is all zeros, `samples` is 0).

use std::path::Path;

use lcrl_sim::EnvSpec;
use rand::seq::index::sample;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::{GraphError, GraphReport};

/// Draws before [`random`] gives up: with K ≥ 2n edges in an n × m graph
/// a draw leaves some action without an edge rarely (e.g. 23 of 72 with
/// n = 6: about 1 draw in 20), so this is only reached for K close to n.
const MAX_DRAWS: usize = 100_000;

/// K edges drawn uniformly among the n × m entries of G, seeded, and drawn
/// again until every action has at least one (a subnetwork needs an
/// input): a uniform draw among the K-edge graphs with an edge per action.
pub fn random(spec: &EnvSpec, edges: usize, seed: u64) -> Result<GraphReport, GraphError> {
    let (n, m) = (spec.action_dim(), spec.state_dim());
    if edges < n || edges > n * m {
        return Err(GraphError::RandomEdges { edges, actions: n, entries: n * m });
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for _ in 0..MAX_DRAWS {
        let mut g = vec![vec![0u8; m]; n];
        for k in sample(&mut rng, n * m, edges) {
            g[k / m][k % m] = 1;
        }
        if g.iter().all(|row| row.contains(&1)) {
            return Ok(from_matrix(spec, g, format!("random@{edges}, draw seed {seed}"), seed));
        }
    }
    Err(GraphError::RandomEdges { edges, actions: n, entries: n * m })
}

/// The degree-matched random control of `random-rows@CONNECTION`: every
/// action row keeps as many inputs as `of` gives it (a row with none stays
/// empty), the states of the row drawn uniformly without replacement. So a
/// draw differs from `of` in which states each action sees, never in how
/// many: the control for "the measured edges matter, not only the count
/// per action" (docs/lcrl-value.md).
pub fn random_rows(spec: &EnvSpec, of: &GraphReport, seed: u64) -> Result<GraphReport, GraphError> {
    let (n, m) = (spec.action_dim(), spec.state_dim());
    if (of.actions(), of.states()) != (n, m) {
        return Err(GraphError::Row(format!("random rows: the graph is {}×{} but environment {} has {n} actions and {m} states", of.actions(), of.states(), spec.name)));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let g: Vec<Vec<u8>> = of
        .g
        .iter()
        .map(|row| {
            let degree = row.iter().filter(|&&e| e == 1).count();
            let mut drawn = vec![0u8; m];
            for j in sample(&mut rng, m, degree) {
                drawn[j] = 1;
            }
            drawn
        })
        .collect();
    let degrees: Vec<String> = of.g.iter().map(|row| row.iter().filter(|&&e| e == 1).count().to_string()).collect();
    Ok(from_matrix(spec, g, format!("random rows of degrees [{}], draw seed {seed}", degrees.join(", ")), seed))
}

/// The draw seed of draw `draw` of a `random-rows` cell on environment
/// `env`: FNV-1a of both, so draws are independent per environment and
/// never the run's seed (runs of one draw share it; docs/experiment.md).
pub fn draw_seed(env: &str, draw: u64) -> u64 {
    let mut hash: u64 = 0xcbf2_9ce4_8422_2325;
    for byte in format!("random-rows/{env}/{draw}").bytes() {
        hash ^= u64::from(byte);
        hash = hash.wrapping_mul(0x0000_0100_0000_01b3);
    }
    hash
}

/// A graph file for the environment `spec` describes: the shape and 0/1
/// checks of [`GraphReport::load`], then the names (a graph written in
/// another state order would feed every subnetwork the wrong inputs) and
/// an edge for every action.
pub fn load_for(path: &Path, spec: &EnvSpec) -> Result<GraphReport, GraphError> {
    let text = std::fs::read_to_string(path).map_err(|source| GraphError::Io { path: path.into(), source })?;
    parse_for(&text, path, spec)
}

/// [`load_for`] on a graph file's text; `path` names it in errors and in
/// the origin (fuzzed by fuzz/fuzz_targets/graph_json.rs).
pub fn parse_for(text: &str, path: &Path, spec: &EnvSpec) -> Result<GraphReport, GraphError> {
    let report = parse_measured_for(text, path, spec)?;
    if let Some(i) = report.g.iter().position(|row| !row.contains(&1)) {
        let message = format!("action {} ({}) has no edge; every action's subnetwork needs at least one state", i + 1, report.action_names[i]);
        return Err(GraphError::BadGraphFile { path: path.into(), message });
    }
    Ok(report)
}

/// A graph CS3 measured (`lcrl graph --out`, `lcrl-learner --graph`): the
/// checks of [`load_for`] but the edge per action. CS3 may find an action
/// that moves no state above the cut; its subnetwork then sees no state and
/// learns a constant, which the networks support (learner/src/algo/nets.rs).
pub fn load_measured_for(path: &Path, spec: &EnvSpec) -> Result<GraphReport, GraphError> {
    let text = std::fs::read_to_string(path).map_err(|source| GraphError::Io { path: path.into(), source })?;
    parse_measured_for(&text, path, spec)
}

fn parse_measured_for(text: &str, path: &Path, spec: &EnvSpec) -> Result<GraphReport, GraphError> {
    let mut report = GraphReport::from_json(text, path)?;
    let bad = |message: String| GraphError::BadGraphFile { path: path.into(), message };
    let (n, m) = (spec.action_dim(), spec.state_dim());
    if (report.actions(), report.states()) != (n, m) {
        return Err(bad(format!(
            "the graph is {}×{} (actions × states) but environment {} has {n} actions and {m} states; build the graph for this environment",
            report.actions(),
            report.states(),
            spec.name
        )));
    }
    if report.state_names != spec.state_names || report.action_names != spec.action_names {
        return Err(bad(format!(
            "its actions {:?} and states {:?} are not those of environment {} (actions {:?}, states {:?}, in this order)",
            report.action_names, report.state_names, spec.name, spec.action_names, spec.state_names
        )));
    }
    if report.origin.is_none() {
        report.origin = Some(format!("graph:{}", path.display()));
    }
    Ok(report)
}

/// A report around a given G: no CS3 values, `origin` says where G came from.
pub fn from_matrix(spec: &EnvSpec, g: Vec<Vec<u8>>, origin: String, seed: u64) -> GraphReport {
    let (n, m) = (spec.action_dim(), spec.state_dim());
    GraphReport {
        env: spec.name.clone(),
        state_names: spec.state_names.clone(),
        action_names: spec.action_names.clone(),
        samples: 0,
        threshold: None,
        exact: false,
        tolerance: None,
        seed,
        threads: 0,
        bootstrap_resamples: 0,
        phi: vec![vec![0.0; m]; n],
        phi_normalized: vec![vec![0.0; m]; n],
        g,
        stability: vec![vec![1.0; m]; n],
        unmoved_states: Vec::new(),
        start: None,
        margin: Vec::new(),
        sweep: Vec::new(),
        elapsed_s: 0.0,
        origin: Some(origin),
        rows: Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(n: usize, m: usize) -> EnvSpec {
        EnvSpec {
            name: "test".into(),
            state_names: (0..m).map(|j| format!("s{j}")).collect(),
            action_names: (0..n).map(|i| format!("a{i}")).collect(),
            action_low: vec![-1.0; n],
            action_high: vec![1.0; n],
        }
    }

    #[test]
    fn random_draws_exactly_k_edges_with_one_per_action_and_repeats_per_seed() {
        let spec = spec(6, 12);
        let mut seen = std::collections::BTreeSet::new();
        for seed in 0..50 {
            let a = random(&spec, 23, seed).unwrap();
            assert_eq!(a.edges(), 23, "seed {seed}");
            assert!(a.g.iter().all(|row| row.contains(&1)), "seed {seed}: an action without an edge");
            assert_eq!(a, random(&spec, 23, seed).unwrap(), "seed {seed} is not reproducible");
            assert_eq!(a.origin.as_deref(), Some(format!("random@23, draw seed {seed}").as_str()));
            seen.insert(a.g);
        }
        // Different seeds give different graphs (C(72, 23) of them).
        assert!(seen.len() > 45, "only {} distinct graphs in 50 seeds", seen.len());
    }

    #[test]
    fn random_edges_cover_every_entry_about_equally() {
        // Uniform: each of the 4 × 5 entries is kept with probability 8/20.
        let spec = spec(4, 5);
        let mut count = vec![vec![0usize; 5]; 4];
        let draws = 4000;
        for seed in 0..draws {
            for (c, g) in count.iter_mut().flatten().zip(random(&spec, 8, seed).unwrap().g.iter().flatten()) {
                *c += usize::from(*g);
            }
        }
        for c in count.iter().flatten() {
            let share = *c as f64 / draws as f64;
            // Binomial standard error √(0.4·0.6/4000) ≈ 0.008: 5 of them.
            assert!((share - 0.4).abs() < 0.04, "entry kept in {share} of draws");
        }
    }

    #[test]
    fn random_rows_keep_every_row_degree_and_vary_the_states() {
        let (spec, other) = (spec(3, 6), spec(2, 6));
        let of = from_matrix(&spec, vec![vec![1, 1, 0, 0, 0, 0], vec![0; 6], vec![1, 1, 1, 1, 0, 1]], "measured".into(), 0);
        let mut first_rows = std::collections::BTreeSet::new();
        for seed in 0..40 {
            let draw = random_rows(&spec, &of, seed).unwrap();
            let degrees: Vec<usize> = draw.g.iter().map(|row| row.iter().filter(|&&e| e == 1).count()).collect();
            assert_eq!(degrees, [2, 0, 5], "seed {seed}");
            assert_eq!(draw, random_rows(&spec, &of, seed).unwrap(), "seed {seed} is not reproducible");
            first_rows.insert(draw.g[0].clone());
        }
        // C(6, 2) = 15 possible first rows: 40 draws see most of them.
        assert!(first_rows.len() >= 10, "only {} distinct rows", first_rows.len());
        let wrong = from_matrix(&other, vec![vec![1; 6]; 2], "other".into(), 0);
        assert!(random_rows(&spec, &wrong, 0).unwrap_err().to_string().contains("3 actions"));
    }

    #[test]
    fn draw_seeds_differ_by_environment_and_draw() {
        let seeds: std::collections::BTreeSet<u64> = ["peg-group1", "peg-group2"].iter().flat_map(|env| (0..10).map(move |d| draw_seed(env, d))).collect();
        assert_eq!(seeds.len(), 20);
        assert_eq!(draw_seed("peg-group1", 3), draw_seed("peg-group1", 3));
        // Pinned: a change of the hash would change every archived draw
        // (FNV-1a 64 of "random-rows/peg-group1/0", computed independently).
        assert_eq!(draw_seed("peg-group1", 0), 9_611_119_715_683_273_235);
    }

    #[test]
    fn impossible_edge_counts_are_refused_with_the_range() {
        let spec = spec(6, 12);
        for k in [0, 5, 73] {
            let err = random(&spec, k, 0).unwrap_err().to_string();
            assert!(err.contains("between 6 and 72"), "{err}");
        }
        assert_eq!(random(&spec, 72, 0).unwrap().edges(), 72);
        assert_eq!(random(&spec, 6, 3).unwrap().edges(), 6);
    }

    #[test]
    fn a_graph_file_is_checked_against_the_environment() {
        let dir = tempfile::tempdir().unwrap();
        let spec = spec(2, 3);
        let path = dir.path().join("g.json");
        let mut report = from_matrix(&spec, vec![vec![1, 0, 0], vec![0, 1, 1]], "hand-made".into(), 0);
        report.write_json(&path).unwrap();
        let loaded = load_for(&path, &spec).unwrap();
        assert_eq!((loaded.g.clone(), loaded.origin.as_deref()), (report.g.clone(), Some("hand-made")));

        report.g[0] = vec![0, 0, 0];
        report.write_json(&path).unwrap();
        let err = load_for(&path, &spec).unwrap_err().to_string();
        assert!(err.contains("g.json") && err.contains("action 1 (a0) has no edge"), "{err}");
        // A measured graph may leave an action unconnected (CS3 found it moves nothing).
        assert_eq!(load_measured_for(&path, &spec).unwrap().g[0], vec![0, 0, 0]);

        let mut renamed = spec.clone();
        renamed.state_names.swap(0, 1);
        report.g[0] = vec![1, 0, 0];
        report.write_json(&path).unwrap();
        let err = load_for(&path, &renamed).unwrap_err().to_string();
        assert!(err.contains("g.json") && err.contains("in this order"), "{err}");

        std::fs::write(&path, "{\"not\": \"a graph\"}").unwrap();
        let err = load_for(&path, &spec).unwrap_err().to_string();
        assert!(err.contains("g.json") && err.contains("not a valid graph.json"), "{err}");
        let err = load_for(&dir.path().join("missing.json"), &spec).unwrap_err().to_string();
        assert!(err.contains("missing.json"), "{err}");
    }
}
