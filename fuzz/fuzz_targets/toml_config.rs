//! The TOML files a user hands lcrl: an environment file (`kind = "lti"`
//! or `"peg"`), a training config (`lcrl train --config`, `lcrl-learner
//! --config`) and a preset (`lcrl run --config`). Each refuses what it
//! cannot use with a message and never panics; what loads passes its own
//! checks again after a round trip through TOML.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use lcrl_learner::config::TrainConfig;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    // Served environments are reached over the network (fuzzed through
    // their replies, step_reply.rs), not from here.
    if text.contains("grpc") {
        return;
    }
    if let Ok(env) = lcrl_sim::env_from_toml(text, "fuzz.toml") {
        let spec = env.spec();
        assert!(spec.state_dim() > 0 && spec.action_dim() > 0);
    }
    for env in ["lti-paper", "peg-group1"] {
        if let Ok(cfg) = TrainConfig::parse_for_env(text, env) {
            let again = toml::to_string(&cfg).expect("a loaded config writes back");
            let reread = TrainConfig::parse_for_env(&again, env).expect("a written config loads again");
            assert_eq!(format!("{reread:?}"), format!("{cfg:?}"));
        }
    }
    let _ = lcrl::preset::Preset::parse(text.to_string(), Path::new("fuzz/preset.toml"));
});
