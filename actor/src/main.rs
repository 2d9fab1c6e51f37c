//! `lcrl-actor`: runs K environments with its local copy of the newest
//! policy plus exploration noise, and streams their transitions to the
//! learner in batches. The process is `lcrl_actor::process::run`; this
//! file parses its arguments.

use clap::Parser;
use lcrl_actor::process::{run, ActorArgs};
use lcrl_runtime::process::shutdown_signal;

fn main() -> std::process::ExitCode {
    let args = ActorArgs::parse();
    // The environments step on their own thread; the runtime only talks.
    lcrl_runtime::process::run_service("lcrl-actor", args.log_json, 1, run(args, shutdown_signal()))
}
