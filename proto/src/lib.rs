//! The `lcrl.v1` gRPC contract, generated from `proto/lcrl.proto`.
//!
//! The `.proto` file is the documentation of every field; this crate only
//! re-exports what tonic/prost generate from it, plus [`security`]: how
//! every server and client of the contract authenticates (TLS, tokens), and
//! [`incoming`]: the TLS-accepting connection stream servers are fed from,
//! and [`process`]: the start-up, logging, shutdown and reflection every
//! service process shares, and [`files`]: the one atomic writer of the files
//! those processes hand on, and [`limits`] and [`codec`]: the bounds every
//! server keeps against its peers and the deadlines every client keeps.
//! The two other wire formats live here too: [`shm`], transitions and
//! policies in iceoryx2 shared memory on one host, and [`metrics_http`],
//! Prometheus `/metrics` and `/healthz` over HTTP.

pub mod codec;
pub mod files;
pub mod incoming;
pub mod limits;
pub mod metrics_http;
pub mod peer_rate;
pub mod process;
pub mod security;
pub mod shm;

/// Generated types and stubs of package `lcrl.v1`.
pub mod v1 {
    tonic::include_proto!("lcrl.v1");

    /// Encoded file descriptor set, for gRPC server reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("lcrl_descriptor");
}
