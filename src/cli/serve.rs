use super::ModelArgs;
use crate::api::http::{router, AppState};
use crate::engine::{Engine, EngineConfig};
use crate::model::preprocess::ImageLimits;
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

#[derive(Args)]
pub struct ServeArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    #[arg(long, env = "LOOPD_HTTP_ADDR", default_value = "127.0.0.1:8080")]
    pub http_addr: String,
    /// Where map sessions live (sled database).
    #[arg(long, env = "LOOPD_DATA_DIR", default_value = "data")]
    pub data_dir: PathBuf,
    #[arg(long, env = "LOOPD_MAX_BATCH", default_value_t = 32)]
    pub max_batch: usize,
    #[arg(long, env = "LOOPD_MAX_DELAY_MS", default_value_t = 5)]
    pub max_delay_ms: u64,
    #[arg(long, env = "LOOPD_QUEUE", default_value_t = 256)]
    pub queue_capacity: usize,
    #[arg(long, env = "LOOPD_MAX_IMAGE_BYTES", default_value_t = 16 << 20)]
    pub max_image_bytes: usize,
    #[arg(long, env = "LOOPD_MAX_IMAGE_PIXELS", default_value_t = 40_000_000)]
    pub max_image_pixels: u64,
    /// Threads decoding images at once (default: number of cores).
    #[arg(long, env = "LOOPD_DECODE_WORKERS")]
    pub decode_workers: Option<usize>,
}

pub fn run(a: ServeArgs) -> Result<ExitCode> {
    std::fs::create_dir_all(&a.data_dir).with_context(|| format!("creating data dir {}", a.data_dir.display()))?;
    let db = sled::open(a.data_dir.join("db")).with_context(|| format!("opening sled in {}", a.data_dir.display()))?;
    let model = a.model.load()?;
    let defaults = EngineConfig::default();
    let cfg = EngineConfig {
        max_batch: a.max_batch,
        max_delay: Duration::from_millis(a.max_delay_ms),
        queue_capacity: a.queue_capacity,
        decode_workers: a.decode_workers.unwrap_or(defaults.decode_workers),
        warm_up: true,
    };
    let limits = ImageLimits { max_bytes: a.max_image_bytes, max_pixels: a.max_image_pixels, ..Default::default() };
    let engine = Engine::start(model, cfg, limits)?;
    let state = Arc::new(AppState { engine });
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let listener =
            tokio::net::TcpListener::bind(&a.http_addr).await.with_context(|| format!("binding {}", a.http_addr))?;
        tracing::info!(addr = %listener.local_addr()?, data_dir = %a.data_dir.display(), "loopd serving HTTP");
        axum::serve(listener, router(state))
            .with_graceful_shutdown(async {
                let _ = tokio::signal::ctrl_c().await;
                tracing::info!("shutting down");
            })
            .await?;
        anyhow::Ok(())
    })?;
    db.flush()?;
    Ok(ExitCode::SUCCESS)
}
