//! End-to-end tests: the real binaries as a user runs them. One test binary
//! (modules below) keeps the build small.

mod e2e {
    pub mod common;
    mod deploy;
    mod distributed;
    mod distributed_learning;
    mod doctor;
    mod experiment_cli;
    mod graph_cli;
    mod graph_service;
    mod hostile;
    mod observability;
    mod run_cli;
    mod security;
    mod served_env;
    mod sim_cli;
    mod train_cli;
}
