//! End-to-end tests: the real binaries as a user runs them. One test binary
//! (modules below) keeps the build small.

mod e2e {
    pub mod common;
    mod doctor;
    mod graph_cli;
    mod graph_service;
    mod sim_cli;
    mod train_cli;
    mod distributed;
    mod distributed_learning;
    mod observability;
    mod deploy;
    mod run_cli;
    mod experiment_cli;
    mod security;
    mod hostile;
    mod faults;
    mod served_env;
    mod gymnasium_face;
    mod export;
    mod readme;
}
