//! Paths and loaders shared by the integration tests (real data, real weights).
pub mod certs;
pub mod pg;
pub mod proc;
use loopd::model::config::ModelConfig;
use loopd::model::device::DType;
use loopd::model::Model;
use std::path::{Path, PathBuf};

pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `../shared/data` beside the checkout (LOOPD_SHARED_DATA overrides).
pub fn data(rel: &str) -> PathBuf {
    let base = std::env::var("LOOPD_SHARED_DATA").map(PathBuf::from).unwrap_or_else(|_| root().join("../shared/data"));
    let p = base.join(rel);
    assert!(p.exists(), "missing real data {} (../shared/data beside the repo)", p.display());
    p
}

/// The imported ImageNet weights (scripts/dev setup writes them).
pub fn weights() -> PathBuf {
    let p = root().join("weights/resnet50-imagenet.safetensors");
    assert!(p.exists(), "missing {}: run scripts/dev setup", p.display());
    p
}

pub fn imagenet_model() -> Model {
    Model::load(&weights(), ModelConfig::default(), tch::Device::Cpu, DType::F32).expect("loading weights").0
}

pub const PHOTOS: [&str; 9] = [
    "dog.jpg",
    "eagle.jpg",
    "giraffe.jpg",
    "horses.jpg",
    "kite.jpg",
    "person.jpg",
    "scream.jpg",
    "tokyo_db.png",
    "tokyo_query.jpg",
];

pub fn photo_inputs(model: &Model) -> Vec<tch::Tensor> {
    PHOTOS
        .iter()
        .map(|p| {
            let bytes = std::fs::read(data(&format!("photos/{p}"))).expect("reading photo");
            loopd::model::preprocess::prepare(&bytes, &Default::default(), &model.config.preprocess)
                .expect("photo decodes")
        })
        .collect()
}

pub fn loopd_bin() -> std::process::Command {
    let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_loopd"));
    // The identity heads: these tests compare the CLI with servers built on the plain ImageNet
    // model; the shipped heads have their own tests (tests/it/train.rs).
    c.current_dir(root()).env("LOOPD_DEVICE", "cpu").env("LOOPD_HEADS", "none");
    c
}

/// A descriptor cache (`loopd eval --cache-dir`) that every `loopd eval` of this test process may
/// share: its entries are computed by this build's binary (the cache's key names the model, its
/// weights and the files, not the code that embeds them, so a cache kept across builds could hand
/// a changed network descriptors made before the change; one made per test process cannot). The
/// Corridor's two traversals are embedded once for both tests that evaluate them.
pub fn process_cache() -> &'static Path {
    static DIR: std::sync::OnceLock<tempfile::TempDir> = std::sync::OnceLock::new();
    DIR.get_or_init(|| tempfile::tempdir().expect("a temporary folder")).path()
}

/// The model `loopd serve` runs by default: the ImageNet backbone with the shipped heads and
/// whitening (`models/heads.safetensors`).
pub fn shipped_model() -> Model {
    let mut m = imagenet_model();
    m.load_heads(&root().join(loopd::cli::DEFAULT_HEADS)).expect("loading the shipped heads");
    m
}

/// The ImageNet model at another input size (another descriptor space).
pub fn imagenet_model_at(width: u32, height: u32) -> Model {
    let mut cfg = ModelConfig::default();
    cfg.preprocess.width = width;
    cfg.preprocess.height = height;
    Model::load(&weights(), cfg, tch::Device::Cpu, DType::F32).expect("loading weights").0
}

/// A Corridor reference frame (frame `i` modulo the 111) as an AddFrame request asking for 3
/// matches: the frame the server-level tests stream.
pub fn corridor_frame(session: &str, robot: &str, i: usize) -> loopd::pb::AddFrameRequest {
    let image = std::fs::read(data(&format!("corridor/ref/{:07}.jpg", i % 111))).expect("reading a Corridor frame");
    loopd::pb::AddFrameRequest {
        session_id: session.into(),
        robot_id: robot.into(),
        timestamp: Some(i as f64),
        content: Some(loopd::pb::add_frame_request::Content::Image(image.into())),
        options: Some(loopd::pb::QueryOptions { k: Some(3), ..Default::default() }),
        ..Default::default()
    }
}

/// A desk frame (slambook2: 10.png revisits 1.png) as an image asking for 3 verified candidates.
pub fn desk_frame(session: &str, i: usize) -> loopd::pb::AddFrameRequest {
    let image = std::fs::read(data(&format!("slambook2-ch11/{i}.png"))).expect("reading a desk frame");
    loopd::pb::AddFrameRequest {
        session_id: session.into(),
        robot_id: "desk".into(),
        timestamp: Some(i as f64),
        content: Some(loopd::pb::add_frame_request::Content::Image(image.into())),
        options: Some(loopd::pb::QueryOptions { k: Some(3), verify: Some(true), ..Default::default() }),
        ..Default::default()
    }
}

/// A new session of 2048-d descriptors (the ImageNet model's) named `name`, stored as `storage`,
/// with the default query options: what the store-level tests create.
pub fn session(name: &str, storage: loopd::index::Storage) -> loopd::store::NewSession {
    loopd::store::NewSession {
        name: name.into(),
        dim: 2048,
        descriptor_id: "t".into(),
        storage,
        default_query: Default::default(),
        camera: None,
        thumbnails: false,
        index: Default::default(),
        model: None,
    }
}

/// The Corridor's ground truth (corridor/gt.csv): each query frame's reference frames.
pub fn corridor_truth() -> std::collections::HashMap<usize, Vec<usize>> {
    let gt = std::fs::read_to_string(data("corridor/gt.csv")).expect("reading corridor/gt.csv");
    gt.lines()
        .skip(1)
        .filter_map(|line| line.split_once(','))
        .map(|(q, refs)| {
            (q.parse().expect("a query index"), refs.split_whitespace().map(|r| r.parse().expect("an index")).collect())
        })
        .collect()
}

/// POSTs `body` as JSON and reads the answer as JSON (any status: the caller asserts on it).
pub async fn post_json(
    http: &reqwest::Client,
    url: impl reqwest::IntoUrl,
    body: &serde_json::Value,
) -> serde_json::Value {
    http.post(url).json(body).send().await.expect("the server answers").json().await.expect("a JSON answer")
}

/// Starts a real server on a thread and runtime of its own, so that it outlives each test's
/// runtime (one server per test file, the model loaded once); its gRPC and HTTP URLs. `config`
/// gets a fresh data directory, which lasts as long as the process.
pub fn background_server(
    config: impl FnOnce(PathBuf) -> loopd::api::server::ServerConfig + Send + 'static,
    model: impl FnOnce() -> Model + Send + 'static,
) -> (String, String) {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let rt = tokio::runtime::Runtime::new().unwrap();
        rt.block_on(async move {
            let dir = tempfile::tempdir().unwrap();
            let server =
                loopd::api::server::RunningServer::start(config(dir.path().to_path_buf()), model()).await.unwrap();
            tx.send((format!("http://{}", server.grpc_addr), format!("http://{}", server.http_addr))).unwrap();
            std::future::pending::<()>().await;
            drop((server, dir));
        });
    });
    rx.recv().unwrap()
}
