//! Algorithm 1 against systems whose graph is known exactly.

use lcrl_sim::lti::{LtiConfig, LtiEnv};
use lcrl_sim::make_env;
use nalgebra::DMatrix;
use proptest::prelude::*;

use crate::lemma1::lemma1_graph;
use crate::{build_graph, Cs3Config, GraphOptions, Rule, EXACT_TOLERANCE};

/// METHOD.md §4: the action × state graph of eq. 10 (the transposition
/// decision applied).
const PAPER_G: [[u8; 3]; 3] = [[1, 0, 0], [1, 1, 0], [0, 0, 1]];

fn options(samples: usize, rule: Rule, threads: usize, seed: u64) -> GraphOptions {
    GraphOptions { cs3: Cs3Config { samples, seed, threads, start: None }, rule, bootstrap: 50 }
}

#[test]
fn lti_paper_graph_under_eq6_and_eq7() {
    let env = make_env("lti-paper").unwrap();
    for rule in [Rule::Exact { tolerance: EXACT_TOLERANCE }, Rule::Threshold(0.1)] {
        let report = build_graph(env.as_ref(), &options(64, rule, 0, 3), &|| {}).unwrap();
        assert_eq!(report.g, PAPER_G.map(Vec::from).to_vec(), "rule {rule:?}");
        assert!(report.unmoved_states.is_empty());
        // Unconnected entries are exactly zero, not merely small.
        assert_eq!(report.phi[0][1], 0.0);
        assert_eq!(report.phi[2][0], 0.0);
        // Noise-free: every resample agrees.
        assert!(report.stability.iter().flatten().all(|&s| s == 1.0));
    }
}

#[test]
fn result_does_not_depend_on_thread_count() {
    let env = LtiEnv::new("r", &LtiConfig::random_sparse(8, 4, 0.3, 5)).unwrap();
    let one = build_graph(&env, &options(40, Rule::Threshold(0.1), 1, 9), &|| {}).unwrap();
    let two = build_graph(&env, &options(40, Rule::Threshold(0.1), 2, 9), &|| {}).unwrap();
    assert_eq!(one.phi, two.phi); // bit-identical f64
    assert_eq!(one.stability, two.stability);
    let other_seed = build_graph(&env, &options(40, Rule::Threshold(0.1), 2, 10), &|| {}).unwrap();
    assert_ne!(one.phi, other_seed.phi, "the seed must matter");
}

#[test]
fn unmoved_state_column_is_all_zero_and_reported() {
    // s2 has no input and no coupling: no action moves it (METHOD.md §3 decision).
    let cfg = LtiConfig::from_matrices(vec![vec![0.5, 0.0], vec![0.0, 0.9]], vec![vec![1.0, 1.0], vec![0.0, 0.0]]);
    let env = LtiEnv::new("u", &cfg).unwrap();
    let report = build_graph(&env, &options(16, Rule::Threshold(0.1), 1, 0), &|| {}).unwrap();
    assert_eq!(report.g, vec![vec![1, 0], vec![1, 0]]);
    assert_eq!(report.unmoved_states, vec![1]);
}

/// Noise on: the primed and plain branches draw independent process noise,
/// so every phi(i, j) carries a noise floor and eq. 6 no longer applies.
/// With noise_std = 0.01 (1% of the initial-state range) eq. 7 with T = 0.1
/// recovers the exact graph from ST = 64 on, for every seed tried.
#[test]
fn noisy_linear_system_still_gives_the_right_graph_with_eq7() {
    let cfg = LtiConfig { noise_std: 0.01, ..LtiConfig::paper_example() };
    let env = LtiEnv::new("lti-paper-noisy", &cfg).unwrap();
    for seed in 0..5 {
        let report = build_graph(&env, &options(64, Rule::Threshold(0.1), 0, seed), &|| {}).unwrap();
        assert_eq!(report.g, PAPER_G.map(Vec::from).to_vec(), "seed {seed}");
        assert!(report.phi[0][1] > 0.0, "noise must reach unconnected entries");
    }
    // ...whereas the exact rule sees the noise floor as connections.
    let exact = build_graph(&env, &options(64, Rule::Exact { tolerance: EXACT_TOLERANCE }, 0, 0), &|| {}).unwrap();
    assert!(exact.g.iter().flatten().all(|&v| v == 1));
}

/// Sparse E (m × m) and F (m × n) with small integer entries, so Lemma 1's
/// sums are exact in f64.
fn sparse_system() -> impl Strategy<Value = (Vec<Vec<f64>>, Vec<Vec<f64>>)> {
    (1usize..=6, 1usize..=4).prop_flat_map(|(m, n)| {
        let entry = prop_oneof![6 => Just(0.0), 1 => Just(1.0), 1 => Just(-1.0), 1 => Just(2.0), 1 => Just(-2.0)];
        (
            proptest::collection::vec(proptest::collection::vec(entry.clone(), m), m),
            proptest::collection::vec(proptest::collection::vec(entry, n), m),
        )
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// CS3 with eq. 6 equals the Lemma 1 pattern (H transposed, METHOD.md §4).
    #[test]
    fn cs3_eq6_matches_lemma1((e, f) in sparse_system(), seed in 0u64..1000) {
        let (m, n) = (e.len(), f[0].len());
        let truth = lemma1_graph(
            &DMatrix::from_fn(m, m, |i, j| e[i][j]),
            &DMatrix::from_fn(m, n, |i, j| f[i][j]),
        );
        let env = LtiEnv::new("p", &LtiConfig::from_matrices(e, f)).unwrap();
        let report = build_graph(&env, &options(4, Rule::Exact { tolerance: EXACT_TOLERANCE }, 1, seed), &|| {}).unwrap();
        prop_assert_eq!(report.g, truth);
    }
}
