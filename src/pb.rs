//! The gRPC wire types, generated from `proto/loopd/v1/loopd.proto`: the server's API and its
//! clients (`loopd eval --server`, tests) share them, so they live outside `api/`.
tonic::include_proto!("loopd.v1");

/// The encoded proto descriptors, for server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("loopd_descriptor");
