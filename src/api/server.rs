//! One process, both APIs: gRPC (tonic) and HTTP (axum) over one engine and one store.
use super::grpc::{GrpcApi, LoopdServer};
use super::http::{router, AppState};
use super::service::LoopService;
use crate::engine::{Engine, EngineConfig};
use crate::model::preprocess::ImageLimits;
use crate::model::Model;
use crate::pb;
use crate::store::{SearchConfig, Store};
use crate::verify::pool::VerifyConfig;
use anyhow::{Context, Result};
use axum::serve::ListenerExt;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use tonic::transport::server::TcpIncoming;

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
    /// Where loop searches run (host kernels or a libtorch device).
    pub search: SearchConfig,
    /// Local features kept per frame and the workers that extract and check them.
    pub verify: VerifyConfig,
    /// How long shutdown waits for open connections after streams were told to end; then they
    /// are cut (acknowledged frames are durable either way).
    pub shutdown_grace: std::time::Duration,
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
            search: SearchConfig::default(),
            verify: VerifyConfig::default(),
            shutdown_grace: std::time::Duration::from_secs(10),
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
}

impl RunningServer {
    /// Binds both listeners (port 0 picks a free one) and starts serving.
    pub async fn start(cfg: ServerConfig, model: Model) -> Result<Self> {
        let store = Arc::new(
            Store::open_with(&cfg.data_dir, cfg.search)
                .with_context(|| format!("opening store in {}", cfg.data_dir.display()))?,
        );
        let engine = Engine::start(model, cfg.engine.clone(), cfg.limits)?;
        let service = LoopService::new(engine, store, cfg.max_jobs, cfg.verify.clone());
        let (shutdown, rx) = tokio::sync::watch::channel(false);

        let http = tokio::net::TcpListener::bind(cfg.http_addr)
            .await
            .with_context(|| format!("binding HTTP {}", cfg.http_addr))?;
        let grpc = tokio::net::TcpListener::bind(cfg.grpc_addr)
            .await
            .with_context(|| format!("binding gRPC {}", cfg.grpc_addr))?;
        let (http_addr, grpc_addr) = (http.local_addr()?, grpc.local_addr()?);

        let state = Arc::new(AppState { service: service.clone() });
        let app = router(state, cfg.max_body_bytes);
        let mut http_rx = rx.clone();
        // No Nagle: small answers leave at once instead of waiting for the client's delayed ACK.
        let http = http.tap_io(|tcp| {
            if let Err(e) = tcp.set_nodelay(true) {
                tracing::debug!(error = %e, "TCP_NODELAY not set");
            }
        });
        let http_task = tokio::spawn(async move {
            axum::serve(http, app)
                .with_graceful_shutdown(async move {
                    let _ = http_rx.wait_for(|s| *s).await;
                })
                .await?;
            Ok(())
        });

        let (health, health_service) = tonic_health::server::health_reporter();
        health.set_serving::<LoopdServer<GrpcApi>>().await;
        let reflection = tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
            .build_v1()?;
        let api = LoopdServer::new(GrpcApi { service: service.clone(), shutdown: rx.clone() })
            .max_decoding_message_size(cfg.limits.max_bytes + 64 * 1024)
            .max_encoding_message_size(64 << 20);
        let mut grpc_rx = rx;
        let grpc_task = tokio::spawn(async move {
            tonic::transport::Server::builder()
                .add_service(health_service)
                .add_service(reflection)
                .add_service(api)
                .serve_with_incoming_shutdown(TcpIncoming::from(grpc).with_nodelay(Some(true)), async move {
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
            tasks: vec![http_task, grpc_task],
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
        self.service.store.flush()?;
        Ok(())
    }
}
