//! Algorithm 1 against systems whose graph is known exactly.

use lcrl_sim::lti::{LtiConfig, LtiEnv};
use lcrl_sim::make_env;
use nalgebra::DMatrix;
use proptest::prelude::*;

use crate::lemma1::lemma1_graph;
use crate::{build_graph, Cs3Config, GraphOptions, Rule, EXACT_TOLERANCE};

/// docs/method.md §4: the action × state graph of eq. 10 (the transposition
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
    // s2 has no input and no coupling: no action moves it (docs/method.md §3 decision).
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

    /// CS3 with eq. 6 equals the Lemma 1 pattern (H transposed, docs/method.md §4).
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

/// Trajectory starts (the default on peg tasks) are mostly in contact and
/// mid-insertion; episode starts never are (the peg starts above the hole).
#[test]
fn peg_trajectory_starts_are_mostly_in_contact() {
    use rand::SeedableRng;
    let env = make_env("peg-group1").unwrap();
    assert_eq!(crate::Start::default_for(env.as_ref()), crate::Start::Trajectory);
    assert_eq!(crate::Start::default_for(make_env("lti-paper").unwrap().as_ref()), crate::Start::Reset);
    let in_contact = |start: crate::Start| {
        (0..64u64)
            .filter(|&k| {
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(k);
                let s0 = crate::cs3::draw_start(env.as_ref(), start, &mut rng).unwrap();
                s0.state()[6..12].iter().any(|&w| w != 0.0)
            })
            .count()
    };
    let (trajectory, reset) = (in_contact(crate::Start::Trajectory), in_contact(crate::Start::Reset));
    assert_eq!(reset, 0);
    assert!(trajectory > 40, "only {trajectory} of 64 trajectory starts touch the hole");
}

#[test]
fn peg_trajectory_graph_does_not_depend_on_thread_count() {
    let env = make_env("peg-group1").unwrap();
    let one = build_graph(env.as_ref(), &options(4, Rule::Threshold(0.1), 1, 7), &|| {}).unwrap();
    let two = build_graph(env.as_ref(), &options(4, Rule::Threshold(0.1), 2, 7), &|| {}).unwrap();
    assert_eq!(one.start.as_deref(), Some("trajectory"));
    assert_eq!(one.phi, two.phi); // bit-identical f64
    assert_eq!(one.stability, two.stability);
}

/// Peg and hole are symmetric under the mirror x ↔ y. Under it the tip
/// offsets and forces swap (x↔y, Fx↔Fy); angles and moments are
/// pseudovectors, so alpha ↔ −beta, gamma → −gamma, Mx ↔ −My, Mz → −Mz;
/// and the actions swap dx↔dy, dalpha↔dbeta. phi sums absolute
/// differences, so signs drop out: phi of a start distribution and phi of
/// its mirror image must be the same table with those rows and columns
/// swapped. The distributions are deliberately lopsided (offset in x,
/// tilted about x) so a mirror bug cannot hide in a symmetric average.
/// Tolerance: each pair of entries within 4 combined standard errors (the
/// per-sample spread over √ST) plus 2% of the larger: CS3 samples are
/// independent, so a true difference of zero exceeds that rarely, and the
/// seeds are fixed, so the test is deterministic.
#[test]
fn peg_phi_is_mirror_symmetric_under_x_y_swap() {
    use lcrl_sim::peg::{PegConfig, PegEnv};
    let mut cfg = PegConfig::group1();
    cfg.episode.position_offset_mm = [0.12, 0.0];
    cfg.episode.angle_offset_deg = [0.3, 0.0, 0.1];
    let mut mirrored = cfg.clone();
    mirrored.episode.position_offset_mm = [0.0, 0.12];
    mirrored.episode.angle_offset_deg = [0.0, -0.3, -0.1];
    let cs3 = |cfg: PegConfig, seed: u64| {
        let env = PegEnv::new("mirror", cfg).unwrap();
        let samples = crate::cs3::measure(&env, &Cs3Config { samples: 96, seed, threads: 0, start: None }, &|| {}).unwrap();
        (samples.phi(), samples.phi_stderr())
    };
    let (phi, se) = cs3(cfg, 1);
    let (phi_m, se_m) = cs3(mirrored, 2);
    let actions = [1, 0, 2, 4, 3, 5];
    let states = [1, 0, 2, 4, 3, 5, 7, 6, 8, 10, 9, 11];
    let mut worst = (0.0, 0, 0);
    for i in 0..6 {
        for j in 0..12 {
            let (a, b) = (phi[i][j], phi_m[actions[i]][states[j]]);
            let tolerance = 4.0 * (se[i][j].powi(2) + se_m[actions[i]][states[j]].powi(2)).sqrt() + 0.02 * a.max(b);
            let z = (a - b).abs() / tolerance;
            if z > worst.0 {
                worst = (z, i, j);
            }
            assert!((a - b).abs() <= tolerance, "phi({i},{j}) = {a} but its mirror phi({},{}) = {b} (tolerance {tolerance})", actions[i], states[j]);
        }
    }
    // The mirror must also be different from the identity: a lopsided
    // distribution makes x and y columns differ, so the test has teeth.
    let unswapped_gap = (0..6).map(|i| (phi[i][0] - phi_m[i][0]).abs() / phi[i][0].max(phi_m[i][0])).fold(0.0, f64::max);
    assert!(unswapped_gap > 0.2, "the distributions are too symmetric for the test to mean anything ({unswapped_gap})");
    eprintln!("worst mirror difference: {:.2} of the tolerance at ({}, {})", worst.0, worst.1, worst.2);
}

/// A graph builder's message becomes G only when it is whole: the right
/// shape for the environment, n·m entries, each 0 or 1.
#[test]
fn a_malformed_graph_message_is_refused_with_what_is_wrong() {
    use crate::report::mask_from_message;
    let good = lcrl_proto::v1::ConnectionGraph { actions: 2, states: 3, g: vec![1, 0, 1, 0, 0, 0], ..Default::default() };
    assert_eq!(mask_from_message(&good, 2, 3).unwrap(), vec![vec![1, 0, 1], vec![0, 0, 0]]);
    let cases = [
        (lcrl_proto::v1::ConnectionGraph { g: vec![1, 0, 1], ..good.clone() }, "has 3 entries but a 2×3 graph needs 6"),
        (lcrl_proto::v1::ConnectionGraph { g: vec![1, 0, 1, 0, 0, 0, 1], ..good.clone() }, "has 7 entries"),
        (lcrl_proto::v1::ConnectionGraph { g: vec![1, 0, 1, 0, 7, 0], ..good.clone() }, "G[1][1] = 7"),
        (lcrl_proto::v1::ConnectionGraph { actions: 3, ..good.clone() }, "is 3×3 but this environment needs 2×3"),
    ];
    for (message, needle) in cases {
        let err = mask_from_message(&message, 2, 3).unwrap_err();
        assert!(err.contains(needle), "{err}");
    }
    let empty = lcrl_proto::v1::ConnectionGraph { actions: 0, states: 3, g: vec![], ..Default::default() };
    assert!(mask_from_message(&empty, 0, 3).unwrap_err().contains("no rows"));
}

/// lti-blocks-N (docs/lcrl-value.md): the sparse family whose G is known.
/// CS3 (eq. 6, eq. 7 at T = 0.1, and at T_rule = 1 from N = 8 on) gives Lemma 1's exact G for every
/// registered N up to 32, and that G is what the construction says: a_k
/// sees x_k, y_k and its partner's x (3 edges per action).
#[test]
fn lti_blocks_graphs_equal_lemma1_up_to_32_actions() {
    for n in LtiConfig::BLOCK_SIZES {
        let env = make_env(&format!("lti-blocks-{n}")).unwrap();
        let lti = lcrl_sim::lti::LtiEnv::of(env.as_ref()).unwrap().system();
        let exact = lemma1_graph(&lti.e, &lti.f);
        for (k, row) in exact.iter().enumerate() {
            let expected: Vec<u8> = (0..2 * n).map(|j| u8::from(j == 2 * k || j == 2 * k + 1 || j == 2 * (k ^ 1))).collect();
            assert_eq!(row, &expected, "N = {n}: Lemma 1's row of a{}", k + 1);
        }
        // T_rule (the above-average rule) recovers it too on the sizes the
        // rule is held to (docs/method.md, "Choosing T").
        let rule_too = (n >= 8).then_some(Rule::Threshold(crate::choose_t::RULE_THRESHOLD));
        for rule in [Rule::Exact { tolerance: EXACT_TOLERANCE }, Rule::Threshold(0.1)].into_iter().chain(rule_too) {
            let report = build_graph(env.as_ref(), &GraphOptions { bootstrap: 0, ..options(16, rule, 0, 1) }, &|| {}).unwrap();
            assert_eq!(report.g, exact, "N = {n}, rule {rule:?}");
            assert_eq!(report.edges(), 3 * n);
        }
    }
    assert!(make_env("lti-blocks-5").is_err(), "odd N has no pairs");
}

/// The publication's graph for the peg task as printed (eq. 21, restated
/// in the publication, eq. 21): states in the publication's column order, then one
/// row per action in its row order, 23 edges of 72.
const EQ21_STATES: [&str; 12] = ["x", "y", "z", "alpha", "beta", "gamma", "Fx", "Fy", "Fz", "Mx", "My", "Mz"];
const EQ21_ROWS: [(&str, [u8; 12]); 6] = [
    ("dx", [1, 0, 1, 0, 0, 0, 1, 0, 1, 0, 1, 0]),
    ("dy", [0, 1, 1, 0, 0, 0, 0, 1, 1, 1, 0, 0]),
    ("dz", [0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0]),
    ("dalpha", [0, 1, 0, 1, 0, 0, 0, 1, 1, 1, 0, 0]),
    ("dbeta", [1, 0, 0, 0, 1, 0, 1, 0, 1, 0, 1, 0]),
    ("dgamma", [0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 1]),
];
/// The same graph as eq. 22 prints it: each action's policy inputs.
const EQ22_INPUTS: [(&str, &[&str]); 6] = [
    ("dx", &["x", "z", "Fx", "Fz", "My"]),
    ("dy", &["y", "z", "Fy", "Fz", "Mx"]),
    ("dz", &["z"]),
    ("dalpha", &["y", "alpha", "Fy", "Fz", "Mx"]),
    ("dbeta", &["x", "beta", "Fx", "Fz", "My"]),
    ("dgamma", &["gamma", "Mz"]),
];

#[test]
fn eq21_graph_file_is_the_publications_edge_by_edge() {
    use std::collections::BTreeSet;
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../references/peg-eq21/graph.json");
    let report = crate::GraphReport::load(&path).unwrap();
    let (n, m) = (report.actions(), report.states());
    assert_eq!((n, m), (6, 12));
    // Both printed forms name the same actions and states as the file, each once.
    fn names(v: &[String]) -> BTreeSet<&str> {
        v.iter().map(String::as_str).collect()
    }
    assert_eq!(names(&report.action_names), EQ21_ROWS.iter().map(|r| r.0).collect::<BTreeSet<_>>());
    assert_eq!(names(&report.state_names), EQ21_STATES.into_iter().collect::<BTreeSet<_>>());
    assert_eq!((names(&report.action_names).len(), names(&report.state_names).len()), (n, m));

    // Eq. 21 mapped into the file's order by name, entry by entry.
    let action = |a: &str| report.action_names.iter().position(|x| x == a).unwrap();
    let state = |s: &str| report.state_names.iter().position(|x| x == s).unwrap();
    let mut checked = 0;
    let mut eq21 = vec![vec![0u8; m]; n];
    for (a, row) in EQ21_ROWS {
        for (s, published) in EQ21_STATES.into_iter().zip(row) {
            eq21[action(a)][state(s)] = published;
            assert_eq!(report.g[action(a)][state(s)], published, "G({a}, {s}) differs from eq. 21");
            checked += 1;
        }
    }
    assert_eq!(checked, 72);
    assert_eq!(report.edges(), 23);
    assert_eq!(EQ21_ROWS.iter().flat_map(|r| r.1).filter(|&v| v == 1).count(), 23);

    // Eq. 22's per-action inputs give the same graph.
    let mut eq22 = vec![vec![0u8; m]; n];
    for (a, inputs) in EQ22_INPUTS {
        for s in inputs {
            eq22[action(a)][state(s)] = 1;
        }
    }
    assert_eq!(eq22, eq21, "eq. 22 and eq. 21 disagree");
    assert_eq!(report.g, eq22);

    // It loads for every peg preset as a study's graph:PATH cell does
    // (given::load_for) and as `lcrl train --graph` does (load_measured_for).
    for name in lcrl_sim::peg::PegConfig::NAMES {
        let env = make_env(name).unwrap();
        let cell = crate::given::load_for(&path, env.spec()).unwrap_or_else(|e| panic!("{name}: {e}"));
        let train = crate::given::load_measured_for(&path, env.spec()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!((&cell.g, &train.g), (&report.g, &report.g), "{name}");
        assert!(cell.origin.as_deref().is_some_and(|o| o.contains("eq. 21") && o.contains("not measured")), "{name}: {:?}", cell.origin);
    }
}
