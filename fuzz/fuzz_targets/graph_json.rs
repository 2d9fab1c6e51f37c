//! Graph files (`graph:PATH`, `lcrl-learner --graph`): any text is either
//! refused with a message or yields a graph that fits the environment and
//! that everything downstream can use: the terminal table, the gRPC
//! message and the mask a local actor is built from.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let env = lcrl_sim::make_env("lti-paper").expect("lti-paper is built in");
    let spec = env.spec();
    let Ok(report) = lcrl_graph_builder::given::parse_for(text, Path::new("fuzz.json"), spec) else { return };
    let (n, m) = (spec.action_dim(), spec.state_dim());
    assert_eq!(report.g.len(), n);
    assert!(report.g.iter().all(|row| row.len() == m && row.contains(&1) && row.iter().all(|&v| v <= 1)));
    let _ = report.table();
    let _ = report.sweep_table();
    let message = lcrl_proto::v1::ConnectionGraph::from(&report);
    let mask = lcrl_graph_builder::report::mask_from_message(&message, n, m).expect("a loaded graph's message is a valid mask");
    assert_eq!(mask, report.g);
});
