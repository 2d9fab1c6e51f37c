//! `lcrl-learner`: the learner process of a distributed run. Actors stream
//! transitions in over gRPC; the training thread learns; new policy
//! versions go out over `WatchPolicy`; `Policy.Act` serves the newest
//! policy. Checkpoints periodically and on SIGTERM/Ctrl-C, and resumes from
//! its newest checkpoint when started again on the same run directory.
//! The process is `lcrl_learner::service::launch::run`; this file parses
//! its arguments.

use clap::Parser;
use lcrl_learner::service::launch::{run, LearnerArgs};
use lcrl_runtime::process::shutdown_signal;

fn main() -> std::process::ExitCode {
    let args = LearnerArgs::parse();
    // Training has its own thread; the runtime serves gRPC and metrics.
    // "listening on ADDR" is the first line of stdout, for launchers.
    lcrl_runtime::process::run_service("lcrl-learner", args.log_json, 2, run(args, shutdown_signal(), |addr| println!("listening on {addr}")))
}
