//! What the cluster benches (frame_log, cluster_nodes) write: 2,048-d f16 sessions, and unit rows
//! that differ per frame (write and search costs do not depend on the values).
use loopd::index::query::LoopQuery;
use loopd::index::Storage;
use loopd::store::record::SessionMeta;
use loopd::store::{NewFrame, NewSession};

pub const DIM: usize = 2048;
/// Writers at once, and robots the frames are spread over.
pub const WRITERS: usize = 16;

pub fn descriptor(i: usize) -> Vec<f32> {
    let mut d: Vec<f32> = (0..DIM).map(|j| (((i * 31 + j * 7) % 97) as f32 + 1.0) / 97.0).collect();
    loopd::index::normalize(&mut d).expect("non-zero");
    d
}

pub fn frame(i: usize) -> NewFrame {
    NewFrame {
        frame_id: None,
        robot_id: format!("robot{}", i % WRITERS),
        timestamp: i as f64,
        pose: None,
        metadata: None,
        descriptor: descriptor(i),
        features: None,
        thumbnail: None,
        idempotency_key: None,
    }
}

pub fn meta(id: &str) -> SessionMeta {
    SessionMeta {
        id: id.into(),
        name: id.into(),
        created: 0.0,
        dim: DIM,
        descriptor_id: "bench".into(),
        storage: Storage::F16,
        default_query: LoopQuery::default(),
        camera: None,
        thumbnails: false,
        index: Default::default(),
        model: None,
    }
}

/// What `Store::create_session` takes for a session like `meta`'s.
pub fn new_session(id: &str) -> NewSession {
    let m = meta(id);
    NewSession {
        name: m.name,
        dim: m.dim,
        descriptor_id: m.descriptor_id,
        storage: m.storage,
        default_query: m.default_query,
        camera: m.camera,
        thumbnails: m.thumbnails,
        index: m.index,
        model: m.model.clone(),
    }
}
