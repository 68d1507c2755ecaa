use super::ModelArgs;
use crate::api::server::{ClusterConfig, ConnectionConfig, RunningServer, ServerConfig};
use crate::api::tls::TlsFiles;
use crate::auth::AuthConfig;
use crate::engine::EngineConfig;
use crate::index::graph::{GraphParams, GraphScalar};
use crate::model::device::parse_device;
use crate::model::preprocess::ImageLimits;
use crate::store::SearchConfig;
use crate::verify::features::{parse_descriptor_bits, FeatureParams, DEFAULT_DESCRIPTOR_BITS};
use crate::verify::pool::VerifyConfig;
use anyhow::Result;
use clap::Args;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;
use tch::Device;

#[derive(Args)]
pub struct ServeArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    #[arg(long, env = "LOOPD_GRPC_ADDR", default_value = "127.0.0.1:50051")]
    pub grpc_addr: SocketAddr,
    #[arg(long, env = "LOOPD_HTTP_ADDR", default_value = "127.0.0.1:8080")]
    pub http_addr: SocketAddr,
    /// Where map sessions live (sled database).
    #[arg(long, env = "LOOPD_DATA_DIR", default_value = "data")]
    pub data_dir: PathBuf,
    /// A model repository: each subfolder a TorchScript model (`model.json` and its file,
    /// docs/models.md) served beside the built-in one; sessions name theirs (`model`).
    #[arg(long, env = "LOOPD_MODELS")]
    pub models: Option<PathBuf>,
    /// The built-in model's name among the served models (sessions created without `model` get it).
    #[arg(long, env = "LOOPD_MODEL_NAME", default_value = crate::model::served::BUILTIN_NAME)]
    pub model_name: String,
    /// Most images per forward pass.
    #[arg(long, env = "LOOPD_MAX_BATCH", default_value_t = 32)]
    pub max_batch: usize,
    /// Longest a frame waits for others to join its batch.
    #[arg(long, env = "LOOPD_MAX_DELAY_MS", default_value_t = 5)]
    pub max_delay_ms: u64,
    /// Pad batches to powers of two (and --max-batch), so the GPU meets few batch shapes, each
    /// warmed up at start on a CUDA device (the CPU warms up batch 1 only); auto: on a CUDA device
    /// only (docs/performance.md "GPU figures").
    #[arg(long, env = "LOOPD_BATCH_BUCKETS", value_enum, default_value = "auto")]
    pub batch_buckets: Switch,
    /// While two or more tenants have work for the model, each batch is cut to what runs in this
    /// many milliseconds (measured per image), so that one tenant's frame never waits behind a
    /// long batch of another's (a batch of 32 takes seconds on a CPU); a tenant alone keeps whole
    /// batches. 0: off.
    #[arg(long, env = "LOOPD_SHARED_BATCH_MS", default_value_t = 100)]
    pub shared_batch_ms: u64,
    /// Frames admitted at once (decoding, queued, running); beyond it: RESOURCE_EXHAUSTED / 429.
    #[arg(long, env = "LOOPD_QUEUE_CAPACITY", default_value_t = 256)]
    pub queue_capacity: usize,
    #[arg(long, env = "LOOPD_MAX_IMAGE_BYTES", default_value_t = 16 << 20)]
    pub max_image_bytes: usize,
    #[arg(long, env = "LOOPD_MAX_IMAGE_PIXELS", default_value_t = 40_000_000)]
    pub max_image_pixels: u64,
    /// Largest HTTP request body (offline sequence uploads).
    #[arg(long, env = "LOOPD_MAX_BODY_BYTES", default_value_t = 512 << 20)]
    pub max_body_bytes: usize,
    /// Offline sequence jobs running at once.
    #[arg(long, env = "LOOPD_MAX_JOBS", default_value_t = 2)]
    pub max_jobs: usize,
    /// A keyed tenant's sequence jobs running at once at most (default: --max-jobs). Whatever
    /// it is, a tenant that runs a job never takes the last free slot: it is kept for another.
    #[arg(long, env = "LOOPD_MAX_JOBS_PER_TENANT")]
    pub max_jobs_per_tenant: Option<usize>,
    /// Threads decoding images at once (default: number of cores).
    #[arg(long, env = "LOOPD_DECODE_WORKERS")]
    pub decode_workers: Option<usize>,
    /// Where loop searches run: auto (the model's device when it is a GPU, else the host's SIMD
    /// kernels), cpu, cuda or cuda:N.
    #[arg(long, env = "LOOPD_SEARCH_DEVICE", default_value = "auto")]
    pub search_device: String,
    /// Sessions with fewer frames search on the host even when a device is set.
    #[arg(long, env = "LOOPD_SEARCH_DEVICE_MIN_FRAMES", default_value_t = 4096)]
    pub search_device_min_frames: usize,
    /// Sessions created with `index: auto` (the default) switch to the approximate index
    /// (docs/storage.md) once they hold this many frames.
    #[arg(long, env = "LOOPD_APPROX_MIN_FRAMES", default_value_t = GraphParams::default().min_frames)]
    pub approx_min_frames: usize,
    /// Values of each descriptor the approximate index's graph holds (the first, PCA-ordered
    /// ones of loopd's whitened descriptors; 0: all). Candidates are re-scored on the full rows.
    #[arg(long, env = "LOOPD_APPROX_DIMS", default_value_t = GraphParams::default().dims)]
    pub approx_dims: usize,
    /// Candidates the approximate index keeps while searching (HNSW efSearch): recall against time.
    #[arg(long, env = "LOOPD_APPROX_EXPANSION", default_value_t = GraphParams::default().expansion_search)]
    pub approx_expansion: usize,
    /// Candidates the approximate index keeps while linking a new frame (HNSW efConstruction):
    /// the graph's quality, hence the recall every later search can reach, against build rate.
    #[arg(long, env = "LOOPD_APPROX_EXPANSION_ADD", default_value_t = GraphParams::default().expansion_add)]
    pub approx_expansion_add: usize,
    /// How the approximate index's graph stores each frame's reduced values: `f16`, or `i8`
    /// (each frame scaled to ±127, compared by cosine: 0.61x the graph's bytes of f16 at 256-d,
    /// faster to build and search). Candidates are re-scored on the full rows either way; a saved
    /// graph keeps the scalar it was built with.
    #[arg(long, env = "LOOPD_APPROX_SCALAR", default_value = GraphParams::default().scalar.as_str(),
          value_parser = GraphScalar::parse)]
    pub approx_scalar: GraphScalar,
    /// A query whose filters leave fewer frames than this is answered by scanning those frames
    /// exactly instead (0: every query of an approximate session goes through the graph).
    #[arg(long, env = "LOOPD_APPROX_EXACT_BELOW", default_value_t = GraphParams::default().exact_below)]
    pub approx_exact_below: usize,
    /// ...and so is one whose filters leave less than this share of the session's frames.
    #[arg(long, env = "LOOPD_APPROX_EXACT_SHARE", default_value_t = GraphParams::default().exact_share)]
    pub approx_exact_share: f32,
    /// A session's approximate index is saved (`<data-dir>/graphs/`) each time it has grown by
    /// this many frames, and at most a minute after it last grew, so a restart loads it.
    #[arg(long, env = "LOOPD_APPROX_SAVE_FRAMES", default_value_t = GraphParams::default().save_rows)]
    pub approx_save_frames: usize,
    /// A session's approximate index keeps at most this many frames' graph in the server's memory:
    /// past it, they are sealed into a file of their own that is mapped, not held (0: never;
    /// docs/storage.md). Each sealed part costs a query one more graph search.
    #[arg(long, env = "LOOPD_APPROX_SEAL_FRAMES", default_value_t = GraphParams::default().seal_rows)]
    pub approx_seal_frames: usize,
    /// Each session's descriptors live in a file under `<data-dir>/rows/` mapped into memory,
    /// and the server keeps at most this many MiB of each session's rows in its own memory
    /// (the rest is the kernel's page cache, dropped under pressure; docs/storage.md).
    #[arg(long, env = "LOOPD_ROWS_RESIDENT_MB", default_value_t = (crate::store::ROWS_RESIDENT >> 20) as u64)]
    pub rows_resident_mb: u64,
    /// MiB of each session's sealed graph parts (`--approx-seal-frames`) the server keeps mapped
    /// in before it releases them (default: `--rows-resident-mb`). A search visits nodes all over
    /// its parts: below their size, queries pay page faults (docs/performance.md).
    #[arg(long, env = "LOOPD_APPROX_SEALED_RESIDENT_MB")]
    pub approx_sealed_resident_mb: Option<u64>,
    /// Keep every session's descriptors in the server's own memory instead (no row files; the
    /// process's memory grows with the maps).
    #[arg(long, env = "LOOPD_ROWS_IN_MEMORY")]
    pub rows_in_memory: bool,
    /// With mapped rows, each session's rows and frame records are kept in `<data-dir>/rows/`
    /// across restarts, checkpointed each time the session has grown by this many frames and at
    /// most a minute after it last grew: a restart reads only the frames after the checkpoint
    /// from the database (docs/storage.md).
    #[arg(long, env = "LOOPD_ROWS_CHECKPOINT_FRAMES", default_value_t = crate::store::CHECKPOINT_FRAMES)]
    pub rows_checkpoint_frames: usize,
    /// Loop searches running at once, on blocking threads off the request executor (default:
    /// number of cores); more wait their turn.
    #[arg(long, env = "LOOPD_SEARCH_WORKERS")]
    pub search_workers: Option<usize>,
    /// ORB features extracted per frame for geometric verification.
    #[arg(long, env = "LOOPD_MAX_FEATURES", default_value_t = 1000)]
    pub max_features: usize,
    /// ORB descriptor bits kept per keypoint (a multiple of 8 in 64..=256): the first tests of
    /// ORB's pattern. 112 stores 17 bytes per keypoint, 256 stores 35 (docs/verification.md).
    #[arg(long, env = "LOOPD_FEATURE_BITS", default_value_t = DEFAULT_DESCRIPTOR_BITS,
          value_parser = parse_descriptor_bits)]
    pub feature_bits: usize,
    /// Largest stored feature record per frame (bytes; 0 keeps no features, so stored frames
    /// cannot be verified).
    #[arg(long, env = "LOOPD_MAX_FEATURE_BYTES", default_value_t = 64 << 10)]
    pub max_feature_bytes: usize,
    /// Largest decoded image buffer (width x height x bytes per pixel); decoding memory is at most
    /// this per decode worker.
    #[arg(long, env = "LOOPD_MAX_DECODE_BYTES", default_value_t = 192 << 20)]
    pub max_decode_bytes: u64,
    /// Seconds shutdown waits for open connections once streams were told to end.
    #[arg(long, env = "LOOPD_SHUTDOWN_GRACE_SECS", default_value_t = 10.0)]
    pub shutdown_grace_secs: f64,
    /// Seconds between attempts to reopen the store after its writes failed (a full disk);
    /// writes are refused and readiness is 503 until one succeeds.
    #[arg(long, env = "LOOPD_STORAGE_RETRY_SECS", default_value_t = 2.0)]
    pub storage_retry_secs: f64,
    /// Seconds a client has for an HTTP request's headers or gRPC's connection preface.
    #[arg(long, env = "LOOPD_HEADER_TIMEOUT_SECS", default_value_t = 10.0)]
    pub header_timeout_secs: f64,
    /// Seconds an HTTP connection may sit with nothing read or written (gRPC channels may idle;
    /// keep-alive pings every half of this find dead peers).
    #[arg(long, env = "LOOPD_IDLE_TIMEOUT_SECS", default_value_t = 60.0)]
    pub idle_timeout_secs: f64,
    /// Seconds one HTTP request, body included, may take before 408.
    #[arg(long, env = "LOOPD_REQUEST_TIMEOUT_SECS", default_value_t = 300.0)]
    pub request_timeout_secs: f64,
    /// Open connections per server (HTTP and gRPC each); more are closed at once.
    #[arg(long, env = "LOOPD_MAX_CONNECTIONS", default_value_t = 1024)]
    pub max_connections: usize,
    /// A file holding the admin key (manages tenants; `LOOPD_ADMIN_KEY` gives it directly). Once
    /// it is set or any tenant exists, every request needs a key.
    #[arg(long, env = "LOOPD_ADMIN_KEY_FILE")]
    pub admin_key_file: Option<PathBuf>,
    /// TLS certificate chain (PEM) for both servers; with --tls-key. Reloaded on SIGHUP.
    #[arg(long, env = "LOOPD_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM) for --tls-cert.
    #[arg(long, env = "LOOPD_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// A CA (PEM) that every client certificate must chain to: mutual TLS for robots.
    #[arg(long, env = "LOOPD_TLS_CLIENT_CA", requires = "tls_cert")]
    pub tls_client_ca: Option<PathBuf>,
    /// The share of --queue-capacity one tenant's requests may hold at once (unless its limits
    /// set max_in_flight), so a flooding tenant cannot starve the others; 1 = no cap.
    #[arg(long, env = "LOOPD_TENANT_QUEUE_SHARE", default_value_t = 0.5)]
    pub tenant_queue_share: f64,
    /// Serve without keys on a non-loopback address (refused otherwise).
    #[arg(long, env = "LOOPD_INSECURE")]
    pub insecure: bool,
    /// Feature extractions and candidate checks running at once (default: number of cores).
    #[arg(long, env = "LOOPD_VERIFY_WORKERS")]
    pub verify_workers: Option<usize>,
    /// Keep sessions and frames in a cluster's PostgreSQL log (synchronous replication), e.g.
    /// postgres://loopd@h1,h2,h3/loopd?target_session_attrs=read-write; --data-dir is then this
    /// node's cache, emptied at start.
    #[arg(long, env = "LOOPD_CLUSTER")]
    pub cluster: Option<String>,
    /// Connections this node keeps to the cluster's database.
    #[arg(long, env = "LOOPD_CLUSTER_CONNECTIONS", default_value_t = 16)]
    pub cluster_connections: usize,
    /// Seconds any call waits on the cluster's database (a connection, a statement, a write up to
    /// its commit); past it the call answers unavailable and its connection is dropped.
    #[arg(long, env = "LOOPD_CLUSTER_DEADLINE_SECS", default_value_t = 10.0)]
    pub cluster_deadline_secs: f64,
    /// Trials only: accept a database whose commits do not wait for a synchronous standby (an
    /// acknowledged frame may then be lost with the primary).
    #[arg(long, env = "LOOPD_CLUSTER_UNREPLICATED", requires = "cluster")]
    pub cluster_unreplicated: bool,
    /// How often a cluster node reads the tenants again (keys issued or revoked through another
    /// node take effect here within this) and checks that the log takes writes (readiness).
    #[arg(long, env = "LOOPD_CLUSTER_TENANT_REFRESH_SECS", default_value_t = 1.0)]
    pub cluster_tenant_refresh_secs: f64,
    /// This node's name among the cluster's members, unique (default: host name:gRPC port).
    #[arg(long, env = "LOOPD_CLUSTER_NODE", default_value = "")]
    pub cluster_node: String,
    /// Nodes that hold each session's index warm (rendezvous hashing over the live members).
    #[arg(long, env = "LOOPD_CLUSTER_OWNERS", default_value_t = 2)]
    pub cluster_owners: usize,
    /// A member not heard from for this long is gone (its sessions move to the next owner).
    #[arg(long, env = "LOOPD_CLUSTER_MEMBER_TTL_SECS", default_value_t = 5.0)]
    pub cluster_member_ttl_secs: f64,
    /// A session this node does not own is dropped from memory once unused for this long
    /// (0: kept until deleted).
    #[arg(long, env = "LOOPD_CLUSTER_EVICT_IDLE_SECS", default_value_t = 600.0)]
    pub cluster_evict_idle_secs: f64,
}

impl ServeArgs {
    /// The search placement, given the device the model runs on.
    pub fn search_config(&self, model_device: Device) -> Result<SearchConfig> {
        let device = match self.search_device.as_str() {
            "auto" => model_device.is_cuda().then_some(model_device),
            "cpu" => None,
            other => Some(parse_device(other)?),
        };
        let defaults = SearchConfig::default();
        Ok(SearchConfig {
            device,
            device_min_rows: self.search_device_min_frames,
            max_concurrent: self.search_workers.unwrap_or(defaults.max_concurrent).max(1),
            graph: GraphParams {
                min_frames: self.approx_min_frames,
                dims: self.approx_dims,
                expansion_search: self.approx_expansion.max(1),
                expansion_add: self.approx_expansion_add.max(1),
                scalar: self.approx_scalar,
                exact_below: self.approx_exact_below,
                exact_share: self.approx_exact_share.clamp(0.0, 1.0),
                save_rows: self.approx_save_frames.max(1),
                seal_rows: self.approx_seal_frames,
                sealed_resident: (self.approx_sealed_resident_mb.unwrap_or(self.rows_resident_mb) as usize)
                    .saturating_mul(1 << 20),
                ..defaults.graph
            },
            rows_resident: (!self.rows_in_memory).then_some((self.rows_resident_mb as usize).saturating_mul(1 << 20)),
            checkpoint_frames: self.rows_checkpoint_frames.max(1),
        })
    }

    /// The admin key (`auth::keys::read_admin_key`: the file's first line, or `LOOPD_ADMIN_KEY`).
    pub fn admin_key(&self) -> Result<Option<String>> {
        crate::auth::keys::read_admin_key(self.admin_key_file.as_deref())
    }

    pub fn server_config(&self) -> ServerConfig {
        let defaults = EngineConfig::default();
        ServerConfig {
            grpc_addr: self.grpc_addr,
            http_addr: self.http_addr,
            data_dir: self.data_dir.clone(),
            engine: EngineConfig {
                max_batch: self.max_batch,
                max_delay: Duration::from_millis(self.max_delay_ms),
                queue_capacity: self.queue_capacity,
                decode_workers: self.decode_workers.unwrap_or(defaults.decode_workers),
                warm_up: true,
                batch_buckets: match self.batch_buckets {
                    Switch::Auto => None,
                    Switch::On => Some(true),
                    Switch::Off => Some(false),
                },
                shared_batch_time: Duration::from_millis(self.shared_batch_ms),
                ..defaults
            },
            limits: ImageLimits {
                max_bytes: self.max_image_bytes,
                max_pixels: self.max_image_pixels,
                max_decode_bytes: self.max_decode_bytes,
                ..Default::default()
            },
            max_body_bytes: self.max_body_bytes.max(self.max_image_bytes + (1 << 20)),
            max_jobs: self.max_jobs,
            max_jobs_per_tenant: self.max_jobs_per_tenant,
            search: SearchConfig::default(),
            shutdown_grace: Duration::from_secs_f64(self.shutdown_grace_secs.clamp(0.0, 3600.0)),
            storage_retry: Duration::from_secs_f64(self.storage_retry_secs.clamp(0.1, 3600.0)),
            auth: AuthConfig { admin_key: None, tenant_in_flight: self.tenant_in_flight() },
            insecure: self.insecure,
            tls: match (&self.tls_cert, &self.tls_key) {
                (Some(cert), Some(key)) => {
                    Some(TlsFiles { cert: cert.clone(), key: key.clone(), client_ca: self.tls_client_ca.clone() })
                }
                _ => None,
            },
            cluster: self.cluster.as_ref().map(|url| ClusterConfig {
                url: url.clone(),
                connections: self.cluster_connections.clamp(1, 1024),
                deadline: Duration::from_secs_f64(self.cluster_deadline_secs.clamp(0.1, 3600.0)),
                unreplicated: self.cluster_unreplicated,
                tenant_refresh: Duration::from_secs_f64(self.cluster_tenant_refresh_secs.clamp(0.01, 3600.0)),
                node: self.cluster_node.clone(),
                owners: self.cluster_owners.clamp(1, 64),
                member_ttl: Duration::from_secs_f64(self.cluster_member_ttl_secs.clamp(0.1, 3600.0)),
                evict_idle: (self.cluster_evict_idle_secs > 0.0)
                    .then(|| Duration::from_secs_f64(self.cluster_evict_idle_secs.min(30.0 * 86400.0))),
            }),
            connections: ConnectionConfig {
                header_timeout: Duration::from_secs_f64(self.header_timeout_secs.clamp(0.1, 3600.0)),
                idle_timeout: Duration::from_secs_f64(self.idle_timeout_secs.clamp(0.1, 86400.0)),
                request_timeout: Duration::from_secs_f64(self.request_timeout_secs.clamp(0.1, 86400.0)),
                max_connections: self.max_connections.max(1),
            },
            calibration: self.model.calibration(),
            model_name: self.model_name.clone(),
            models_dir: self.models.clone(),
            verify: {
                let defaults = VerifyConfig::default();
                VerifyConfig {
                    features: FeatureParams {
                        max_features: self.max_features.clamp(1, 20_000),
                        descriptor_bits: self.feature_bits,
                        ..defaults.features
                    },
                    max_feature_bytes: self.max_feature_bytes,
                    workers: self.verify_workers.unwrap_or(defaults.workers).max(1),
                }
            },
        }
    }
}

impl ServeArgs {
    /// One tenant's requests in flight at once: its share of the queue (at least 1).
    fn tenant_in_flight(&self) -> Option<u64> {
        let share = if self.tenant_queue_share.is_finite() { self.tenant_queue_share.clamp(0.0, 1.0) } else { 1.0 };
        (share < 1.0).then(|| ((self.queue_capacity as f64 * share).ceil() as u64).max(1))
    }
}

pub fn run(a: ServeArgs) -> Result<ExitCode> {
    let model = a.model.load()?;
    let cfg = ServerConfig {
        search: a.search_config(model.device)?,
        auth: AuthConfig { admin_key: a.admin_key()?, tenant_in_flight: a.tenant_in_flight() },
        ..a.server_config()
    };
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let server = RunningServer::start(cfg, model).await?;
        wait_for_signal().await;
        tracing::info!("shutting down: finishing acknowledged work");
        server.shutdown().await
    })?;
    Ok(ExitCode::SUCCESS)
}

pub(super) async fn wait_for_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(s) => s,
            Err(_) => return std::future::pending().await,
        };
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    let _ = ctrl_c.await;
}

/// On, off, or chosen by the device.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Switch {
    Auto,
    On,
    Off,
}
