//! The gRPC wire types, generated from `proto/loopd/v1/loopd.proto`: the server's API and its
//! clients (`loopd eval --server`, tests) share them, so they live outside `api/`.
tonic::include_proto!("loopd.v1");

/// The encoded proto descriptors, for server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("loopd_descriptor");

/// A frame's pose on the wire and in the index: the server's gRPC API and the clients that
/// read it (`loopd ros2`) convert alike.
impl From<Pose> for crate::index::query::Pose {
    fn from(p: Pose) -> Self {
        Self { x: p.x, y: p.y, z: p.z, qx: p.qx, qy: p.qy, qz: p.qz, qw: p.qw }
    }
}

impl From<crate::index::query::Pose> for Pose {
    fn from(p: crate::index::query::Pose) -> Self {
        Self { x: p.x, y: p.y, z: p.z, qx: p.qx, qy: p.qy, qz: p.qz, qw: p.qw }
    }
}
