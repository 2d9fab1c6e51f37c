//! The `lcrl.v1` contract and what crosses the wire: the gRPC types and
//! stubs generated from `proto/lcrl.proto` ([`v1`]; the `.proto` file
//! documents every field), the codec that bounds a message's repeated
//! fields before decoding ([`codec`]), and the same-host wire format
//! ([`shm`]: transitions and policies in iceoryx2 shared memory). What a
//! service process needs at start-up and at run time (security, limits,
//! files, metrics over HTTP) is lcrl-runtime's.

pub mod codec;
pub mod shm;

/// Generated types and stubs of package `lcrl.v1`.
pub mod v1 {
    tonic::include_proto!("lcrl.v1");

    /// Encoded file descriptor set, for gRPC server reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("lcrl_descriptor");
}
