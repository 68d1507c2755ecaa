//! One process, both APIs: gRPC (tonic) and HTTP (axum) over one engine and one store.
use super::conn::{accept, ConnLimits, Connections, Slots};
use super::grpc::admin::{AdminApi, AdminServer};
use super::grpc::{self, GrpcApi, LoopdServer};
use super::http::{router, AppState};
use super::service::LoopService;
use super::tls::{Conn, Tls, TlsFiles};
use super::watch::{follow_cluster, follow_members, watch_storage};
use crate::auth::{Auth, AuthConfig};
use crate::engine::metrics::ModelMetrics;
use crate::engine::{Engine, EngineConfig};
use crate::model::preprocess::ImageLimits;
use crate::model::served::{load_dir as load_models, Served};
use crate::model::Model;
use crate::pb;
use crate::store::pg::{LogConfig, Replication};
use crate::store::{Membership, SearchConfig, Store};
use crate::verify::confidence::{Calibration, SHIPPED};
use crate::verify::pool::VerifyConfig;
use anyhow::{Context, Result};
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use hyper_util::service::TowerToHyperService;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tonic::service::interceptor::InterceptedService;

#[derive(Clone, Debug)]
pub struct ServerConfig {
    pub grpc_addr: SocketAddr,
    pub http_addr: SocketAddr,
    pub data_dir: PathBuf,
    pub engine: EngineConfig,
    pub limits: ImageLimits,
    /// Largest HTTP body (sequence uploads are the big ones).
    pub max_body_bytes: usize,
    pub max_jobs: usize,
    /// A keyed tenant's sequence jobs running at once at most (None: `max_jobs`); a tenant that
    /// runs one never takes the last free slot either (`jobs::Jobs::admit`).
    pub max_jobs_per_tenant: Option<usize>,
    /// Where loop searches run (host kernels or a libtorch device).
    pub search: SearchConfig,
    /// Local features kept per frame and the workers that extract and check them.
    pub verify: VerifyConfig,
    /// Where the calibrated confidence of this server's descriptors comes from.
    pub calibration: Calibration,
    /// How long shutdown waits for open connections after streams were told to end; then they
    /// are cut (acknowledged frames are durable either way).
    pub shutdown_grace: std::time::Duration,
    /// How often a store whose writes failed (a full disk) tries to reopen.
    pub storage_retry: std::time::Duration,
    pub connections: ConnectionConfig,
    /// The admin key, if any (keys are required once it is set or any tenant exists).
    pub auth: AuthConfig,
    /// Listen beyond loopback without keys (refused otherwise).
    pub insecure: bool,
    /// TLS on both servers (certificate, key, optional client CA for mTLS).
    pub tls: Option<TlsFiles>,
    /// Sessions and frames in a cluster's replicated log instead of `data_dir` alone.
    pub cluster: Option<ClusterConfig>,
    /// The built-in model's name among the served models (`--model-name`).
    pub model_name: String,
    /// A folder of TorchScript models served beside the built-in one, one subfolder each
    /// (`--models`; docs/models.md).
    pub models_dir: Option<PathBuf>,
}

/// `serve --cluster`: the log's PostgreSQL URL and this node's connections to it.
#[derive(Clone, Debug)]
pub struct ClusterConfig {
    pub url: String,
    pub connections: usize,
    /// The longest any call waits on the log's database (see `LogConfig::deadline`).
    pub deadline: Duration,
    /// Trials only: accept a primary whose commits do not wait for a synchronous standby.
    pub unreplicated: bool,
    /// How often the node reads the tenants again (keys issued or revoked through other nodes
    /// take effect here within this), probes the log, and heartbeats as a member.
    pub tenant_refresh: Duration,
    /// This node's name among the members (empty: the host's name and the gRPC port).
    pub node: String,
    /// Nodes that hold each session warm (see `store/owners.rs`).
    pub owners: usize,
    /// A member not seen for this long is gone.
    pub member_ttl: Duration,
    /// A session this node does not own is dropped once unused for this long (None: never).
    pub evict_idle: Option<Duration>,
}

impl ClusterConfig {
    /// A node of the cluster whose log is at `url`, with the defaults of `loopd serve`.
    pub fn new(url: &str) -> Self {
        Self {
            url: url.into(),
            connections: 16,
            deadline: Duration::from_secs(10),
            unreplicated: false,
            tenant_refresh: Duration::from_secs(1),
            node: String::new(),
            owners: 2,
            member_ttl: Duration::from_secs(5),
            evict_idle: Some(Duration::from_secs(600)),
        }
    }

    /// The node's membership; `grpc` is the address it serves on.
    fn membership(&self, grpc: SocketAddr) -> Membership {
        let node = if self.node.is_empty() {
            // The kernel's host name (a container's id under Docker); the port tells apart
            // nodes on one host.
            let host = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
            format!("{}:{}", host.trim(), grpc.port())
        } else {
            self.node.clone()
        };
        Membership { node, owners: self.owners.max(1), ttl: self.member_ttl, evict_idle: self.evict_idle }
    }
}

/// What one client connection may hold (see `conn.rs`).
#[derive(Clone, Copy, Debug)]
pub struct ConnectionConfig {
    /// A request line and headers (HTTP), or the HTTP/2 preface (gRPC), must arrive within this.
    pub header_timeout: Duration,
    /// An HTTP connection with nothing read or written for this long is closed (gRPC channels
    /// may idle: HTTP/2 keep-alive pings every `idle / 2` close those whose peer is gone).
    pub idle_timeout: Duration,
    /// One HTTP request, its body included, must be answered within this (408 otherwise).
    pub request_timeout: Duration,
    /// Open connections per server (HTTP and gRPC each); more are closed at once.
    pub max_connections: usize,
}

impl Default for ConnectionConfig {
    fn default() -> Self {
        Self {
            header_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(60),
            request_timeout: Duration::from_secs(300),
            max_connections: 1024,
        }
    }
}

impl ServerConfig {
    /// Both APIs on free loopback ports over `data_dir`, every other setting at its default:
    /// what tests and benchmarks start from.
    pub fn on_loopback(data_dir: PathBuf) -> Self {
        let loopback = SocketAddr::from(([127, 0, 0, 1], 0));
        Self {
            grpc_addr: loopback,
            http_addr: loopback,
            data_dir,
            engine: EngineConfig::default(),
            limits: ImageLimits::default(),
            max_body_bytes: 8 << 20,
            max_jobs: 1,
            max_jobs_per_tenant: None,
            search: SearchConfig::default(),
            verify: VerifyConfig::default(),
            calibration: Calibration::Shipped(SHIPPED.into()),
            shutdown_grace: std::time::Duration::from_secs(10),
            storage_retry: std::time::Duration::from_secs(2),
            connections: ConnectionConfig::default(),
            auth: AuthConfig::default(),
            insecure: false,
            tls: None,
            cluster: None,
            model_name: crate::model::served::BUILTIN_NAME.into(),
            models_dir: None,
        }
    }
}

pub struct RunningServer {
    pub grpc_addr: SocketAddr,
    pub http_addr: SocketAddr,
    pub service: LoopService,
    shutdown: tokio::sync::watch::Sender<bool>,
    grace: std::time::Duration,
    tasks: Vec<tokio::task::JoinHandle<Result<()>>>,
    /// A cluster node's membership task (it leaves the members as it ends).
    members: Option<tokio::task::JoinHandle<()>>,
}

impl RunningServer {
    /// Binds both listeners (port 0 picks a free one) and starts serving.
    pub async fn start(cfg: ServerConfig, model: Model) -> Result<Self> {
        let store = Arc::new(match &cfg.cluster {
            None => Store::open_with(&cfg.data_dir, cfg.search)
                .with_context(|| format!("opening store in {}", cfg.data_dir.display()))?,
            Some(c) => {
                let replication = if c.unreplicated { Replication::NotRequired } else { Replication::Synchronous };
                let log = LogConfig { deadline: c.deadline, ..LogConfig::new(c.connections, replication) };
                // A database not reachable yet (the whole cluster starting at once, a failover)
                // is waited for, with backoff: the node listens once it has joined. Any other
                // error (a wrong URL, an unreplicated primary) ends the start.
                let mut wait = Duration::from_millis(500);
                let store = loop {
                    match Store::open_cluster(&cfg.data_dir, &c.url, log, cfg.search).await {
                        Err(crate::store::StoreError::Unavailable(why)) => {
                            tracing::warn!(error = %why, retry_in = ?wait, "the cluster's database is not reachable yet");
                            tokio::time::sleep(wait).await;
                            wait = (wait * 2).min(Duration::from_secs(10));
                        }
                        opened => {
                            break opened.with_context(|| {
                                format!("joining the cluster (its cache in {})", cfg.data_dir.display())
                            })?
                        }
                    }
                };
                tracing::info!(cache = %cfg.data_dir.display(), "sessions and frames in the cluster's log");
                store
            }
        });
        let device = model.device;
        crate::model::script::check_name(&cfg.model_name).context("--model-name")?;
        // A repository's `builtin` folders run on the default network's weights: loaded before
        // it moves to its engine.
        let repository = match &cfg.models_dir {
            Some(dir) => load_models(dir, device, Some(&model))?,
            None => Vec::new(),
        };
        let builtin = Served::builtin(&cfg.model_name, model);
        let mut models = vec![Engine::start(builtin, cfg.engine.clone(), cfg.limits)?];
        let dir = cfg.models_dir.as_deref().unwrap_or(std::path::Path::new(""));
        for m in repository {
            if let Some(same) = models.iter().find(|e| e.info().name == m.name) {
                anyhow::bail!(
                    "{}: two models are named '{}' (the other: {}); names must differ",
                    dir.display(),
                    m.name,
                    same.info().descriptor_id
                );
            }
            let engine = Engine::start(m, cfg.engine.clone(), cfg.limits)?;
            let i = engine.info();
            if let Some(same) = models.iter().find(|e| e.info().descriptor_id == i.descriptor_id) {
                tracing::warn!(model = %i.name, same = %same.info().name, descriptor_id = %i.descriptor_id,
                    "two served models compute the same descriptors: sessions of either are embedded by the first");
            }
            tracing::info!(model = %i.name, kind = i.about.kind, descriptor_id = %i.descriptor_id, dim = i.dim, "serving a model");
            models.push(engine);
        }
        let engine = models[0].clone();
        // Each model's calibrator from the one file: the default's must be there when the file
        // was given on purpose; another model's is used when the file holds one.
        let mut calibrators = vec![cfg.calibration.resolve(&engine.info().descriptor_id)?];
        for e in &models[1..] {
            calibrators.push(cfg.calibration.resolve_other(&e.info().name, &e.info().descriptor_id));
        }
        for (e, c) in models.iter().zip(&calibrators) {
            if let Some(c) = c {
                tracing::info!(model = %e.info().name, descriptor_id = %c.descriptor_id, loop_confidence = c.loop_confidence, "calibrated confidence");
            }
        }
        let auth = Arc::new(Auth::new(&cfg.auth, store.clone())?);
        let tls = match &cfg.tls {
            None => None,
            Some(files) => Some(Arc::new(Tls::load(files.clone())?)),
        };
        if let Some(tls) = &tls {
            // Registered now, before the first connection: SIGHUP then never ends the process.
            let mut hangups = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup())?;
            let tls = tls.clone();
            tokio::spawn(async move {
                while hangups.recv().await.is_some() {
                    match tls.reload() {
                        Ok(()) => {
                            tracing::info!("TLS certificate and key reloaded (SIGHUP); open connections keep theirs")
                        }
                        Err(e) => tracing::error!(error = %e, "TLS reload failed: the previous certificate stays"),
                    }
                }
            });
        }
        let loopback = cfg.grpc_addr.ip().is_loopback() && cfg.http_addr.ip().is_loopback();
        if !auth.enabled() && !loopback {
            if !cfg.insecure {
                anyhow::bail!(
                    "refusing to listen on {} / {} without keys: set an admin key (LOOPD_ADMIN_KEY_FILE or \
                     LOOPD_ADMIN_KEY) and create tenants, or pass --insecure to serve anyone who connects",
                    cfg.grpc_addr,
                    cfg.http_addr
                );
            }
            tracing::warn!(
                "INSECURE: no keys required on a non-loopback address; anyone who connects can read, \
                            write and delete every session"
            );
        }
        let service =
            LoopService::with_models(models.into_iter().zip(calibrators).collect(), store, cfg.verify.clone());
        let jobs = Arc::new(super::jobs::Jobs::new(cfg.max_jobs, cfg.max_jobs_per_tenant, service.store.clone()));
        let (shutdown, rx) = tokio::sync::watch::channel(false);
        if let Some(c) = &cfg.cluster {
            tokio::spawn(follow_cluster(auth.clone(), service.store.clone(), c.tenant_refresh, rx.clone()));
        }

        let http = tokio::net::TcpListener::bind(cfg.http_addr)
            .await
            .with_context(|| format!("binding HTTP {}", cfg.http_addr))?;
        let grpc = tokio::net::TcpListener::bind(cfg.grpc_addr)
            .await
            .with_context(|| format!("binding gRPC {}", cfg.grpc_addr))?;
        let (http_addr, grpc_addr) = (http.local_addr()?, grpc.local_addr()?);
        let mut members = None;
        if let Some(c) = &cfg.cluster {
            let me = c.membership(grpc_addr);
            tracing::info!(node = %me.node, owners = me.owners, "joining the cluster's members");
            service.store.join_members(me);
            // Jobs it ran before a restart are over: say so to every node before taking calls.
            service.store.interrupt_logged_jobs().await;
            members = Some(tokio::spawn(follow_members(service.store.clone(), c.tenant_refresh, rx.clone())));
        }

        let connections = Arc::new(Connections::new(cfg.connections.max_connections));
        let metrics = Arc::new(super::metrics::registry(
            ModelMetrics(service.models.iter().map(|e| (e.info().name.clone(), e.metrics().clone())).collect()),
            auth.clone(),
            connections.clone(),
            service.loops_not_kept.clone(),
            service.verifier.extracted(),
        ));
        let state = Arc::new(AppState { service: service.clone(), auth: auth.clone(), jobs, metrics });
        let app = router(state, cfg.max_body_bytes).layer(tower_http::timeout::TimeoutLayer::with_status_code(
            axum::http::StatusCode::REQUEST_TIMEOUT,
            cfg.connections.request_timeout,
        ));
        let http_task =
            tokio::spawn(serve_http(http, app, cfg.connections, connections.http.clone(), tls.clone(), rx.clone()));

        let (health, health_service) = tonic_health::server::health_reporter();
        health.set_serving::<LoopdServer<GrpcApi>>().await;
        let reflection = tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
            .build_v1()?;
        let api = LoopdServer::new(GrpcApi { service: service.clone(), shutdown: rx.clone() })
            .max_decoding_message_size(cfg.limits.max_bytes + 64 * 1024)
            .max_encoding_message_size(64 << 20);
        // Keys on everything but health (reflection describes the API: a key's business too).
        let api = InterceptedService::new(api, grpc::authenticate(auth.clone()));
        let reflection = InterceptedService::new(reflection, grpc::authenticate(auth.clone()));
        let admin = InterceptedService::new(
            AdminServer::new(AdminApi { auth: auth.clone() }),
            grpc::authenticate(auth.clone()),
        );
        let watcher = tokio::spawn(watch_storage(service.store.clone(), health, cfg.storage_retry, rx.clone()));
        let mut grpc_rx = rx;
        let c = cfg.connections;
        // The preface is 24 bytes; a gRPC channel may then idle (keep-alive pings check the peer).
        let limits = ConnLimits { opening: c.header_timeout, opening_bytes: 24, idle: None };
        let incoming = grpc_incoming(grpc, limits, c, connections.grpc.clone(), tls.clone(), grpc_rx.clone());
        let grpc_task = tokio::spawn(async move {
            tonic::transport::Server::builder()
                .http2_keepalive_interval(Some(c.idle_timeout / 2))
                .http2_keepalive_timeout(Some(c.header_timeout))
                .add_service(health_service)
                .add_service(reflection)
                .add_service(api)
                .add_service(admin)
                .serve_with_incoming_shutdown(incoming, async move {
                    let _ = grpc_rx.wait_for(|s| *s).await;
                })
                .await?;
            Ok(())
        });
        tracing::info!(%http_addr, %grpc_addr, data_dir = %cfg.data_dir.display(), "loopd serving");
        Ok(Self {
            grpc_addr,
            http_addr,
            service,
            shutdown,
            grace: cfg.shutdown_grace,
            tasks: vec![http_task, grpc_task, watcher],
            members,
        })
    }

    /// Stops accepting, lets in-flight requests finish (their writes are acknowledged only
    /// once durable), ends open frame streams with UNAVAILABLE after the frame in hand, waits at
    /// most the grace time for connections to close, then flushes the store.
    pub async fn shutdown(self) -> Result<()> {
        let _ = self.shutdown.send(true);
        let deadline = tokio::time::Instant::now() + self.grace;
        for mut t in self.tasks {
            match tokio::time::timeout_at(deadline, &mut t).await {
                Ok(done) => done??,
                Err(_) => {
                    tracing::warn!(
                        grace_s = self.grace.as_secs_f64(),
                        "connections still open after the grace time: cut"
                    );
                    t.abort();
                }
            }
        }
        if let Some(m) = self.members {
            let _ = tokio::time::timeout(Duration::from_secs(3), m).await;
        }
        self.service.store.flush()?;
        Ok(())
    }
}

/// A connection made usable: the TLS handshake (if on) within the header deadline.
async fn open(io: super::conn::Guarded, tls: Option<&Tls>, grpc: bool, deadline: Duration) -> Option<Conn> {
    match tokio::time::timeout(deadline, Conn::open(io, tls, grpc)).await {
        Ok(Ok(conn)) => Some(conn),
        Ok(Err(e)) => {
            tracing::debug!(error = %e, "TLS handshake failed");
            None
        }
        Err(_) => {
            tracing::debug!("TLS handshake not done within the header deadline");
            None
        }
    }
}

/// gRPC's connections: accepted under the limit, handshaken off the accept loop, until `stop`.
fn grpc_incoming(
    listener: tokio::net::TcpListener,
    limits: ConnLimits,
    c: ConnectionConfig,
    slots: Arc<Slots>,
    tls: Option<Arc<Tls>>,
    mut stop: tokio::sync::watch::Receiver<bool>,
) -> tokio_stream::wrappers::ReceiverStream<std::io::Result<Conn>> {
    let (tx, rx) = tokio::sync::mpsc::channel(64);
    tokio::spawn(async move {
        loop {
            let io = tokio::select! {
                _ = stop.wait_for(|s| *s) => break,
                io = accept(&listener, limits, &slots) => io,
            };
            let (tx, tls) = (tx.clone(), tls.clone());
            tokio::spawn(async move {
                if let Some(conn) = open(io, tls.as_deref(), true, c.header_timeout).await {
                    let _ = tx.send(Ok(conn)).await;
                }
            });
        }
    });
    tokio_stream::wrappers::ReceiverStream::new(rx)
}

/// The HTTP server: our own accept loop (axum::serve sets no header or idle deadline), hyper's
/// HTTP/1 and HTTP/2, graceful shutdown once `stop` turns true (connections finish their
/// request; the caller bounds the wait).
async fn serve_http(
    listener: tokio::net::TcpListener,
    app: axum::Router,
    c: ConnectionConfig,
    slots: Arc<Slots>,
    tls: Option<Arc<Tls>>,
    mut stop: tokio::sync::watch::Receiver<bool>,
) -> Result<()> {
    let limits = ConnLimits { opening: c.header_timeout, opening_bytes: 1, idle: Some(c.idle_timeout) };
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder.http1().timer(TokioTimer::new()).header_read_timeout(c.header_timeout);
    let graceful = hyper_util::server::graceful::GracefulShutdown::new();
    loop {
        let io = tokio::select! {
            _ = stop.wait_for(|s| *s) => break,
            io = accept(&listener, limits, &slots) => io,
        };
        let (service, builder, watcher, tls) =
            (TowerToHyperService::new(app.clone()), builder.clone(), graceful.watcher(), tls.clone());
        tokio::spawn(async move {
            let Some(conn) = open(io, tls.as_deref(), false, c.header_timeout).await else { return };
            let conn = watcher.watch(builder.serve_connection_with_upgrades(TokioIo::new(conn), service).into_owned());
            if let Err(e) = conn.await {
                tracing::debug!(error = %e, "HTTP connection ended");
            }
        });
    }
    drop(listener);
    graceful.shutdown().await;
    Ok(())
}
