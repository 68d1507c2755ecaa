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

/// The one rigid transform type (a verified pose, a kept loop's, a client's verdict) on the wire.
impl From<RelativePose> for crate::store::loops::Transform {
    fn from(p: RelativePose) -> Self {
        Self { qx: p.qx, qy: p.qy, qz: p.qz, qw: p.qw, tx: p.tx, ty: p.ty, tz: p.tz }
    }
}

impl From<crate::store::loops::Transform> for RelativePose {
    fn from(t: crate::store::loops::Transform) -> Self {
        Self { qx: t.qx, qy: t.qy, qz: t.qz, qw: t.qw, tx: t.tx, ty: t.ty, tz: t.tz }
    }
}
