//! A served environment's Step replies (sim/src/remote.rs) as `RemoteEnv`
//! reads them: any protobuf bytes are refused with a message or give one
//! finite step of the spec's length per session.
#![no_main]

use libfuzzer_sys::fuzz_target;
use lcrl_proto::v1::StepResponse;
use lcrl_sim::remote::read_step_reply;
use prost::Message;

fuzz_target!(|data: &[u8]| {
    let Ok(reply) = StepResponse::decode(data) else { return };
    let env = lcrl_sim::make_env("lti-paper").expect("lti-paper is built in");
    let spec = env.spec();
    let sessions = reply.results.len().max(1) - usize::from(data.len() % 5 == 0 && !reply.results.is_empty());
    let Ok(steps) = read_step_reply(spec, sessions, reply) else { return };
    assert_eq!(steps.len(), sessions);
    assert!(steps.iter().all(|s| s.state.len() == spec.state_dim() && s.reward.is_finite() && s.state.iter().all(|v| v.is_finite())));
});
