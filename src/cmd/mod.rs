//! One module per `lcrl` subcommand: its arguments and a thin `run` over
//! the library crates (and this crate's own library, `lcrl::*`; `lcrl run`
//! and `lcrl train` are there whole, as `lcrl::local_run` and `lcrl::train`).

pub mod bench;
pub mod bench_busy;
pub mod bench_env;
pub mod bench_sim;
pub mod bench_transport;
pub mod certs;
pub mod compare;
pub mod doctor;
pub mod export;
pub mod launch;
pub mod probe;
pub mod serve_env;
pub mod scale;
pub mod sim;
pub mod tune;
