//! HTTP (axum, JSON) routes; `openapi.yaml` describes each of them.
use super::error::ApiError;
use crate::engine::Engine;
use crate::model::network::{Variant, DESCRIPTOR_DIM};
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, Query, State};
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

pub struct AppState {
    pub engine: Engine,
}

pub fn router(state: Arc<AppState>) -> Router {
    // Slightly above the image limit so an oversized image gets our 413 message, not a bare one.
    let body_limit = state.engine.info().limits.max_bytes + 1024;
    Router::new()
        .route("/healthz", get(|| async { "ok" }))
        .route("/readyz", get(|| async { "ready" }))
        .route("/metrics", get(metrics))
        .route("/v1/info", get(info))
        .route("/v1/embed", post(embed))
        .layer(DefaultBodyLimit::max(body_limit))
        .with_state(state)
}

async fn metrics(State(s): State<Arc<AppState>>) -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], s.engine.metrics().render_prometheus())
}

#[derive(Serialize)]
struct Info {
    descriptor_id: String,
    dim: i64,
    device: String,
    dtype: String,
    max_batch: usize,
    version: &'static str,
}

async fn info(State(s): State<Arc<AppState>>) -> Json<Info> {
    let i = s.engine.info();
    Json(Info {
        descriptor_id: i.descriptor_id.clone(),
        dim: DESCRIPTOR_DIM,
        device: i.device.clone(),
        dtype: i.dtype.clone(),
        max_batch: s.engine.config().max_batch,
        version: env!("CARGO_PKG_VERSION"),
    })
}

#[derive(Deserialize)]
struct EmbedQuery {
    #[serde(default = "yes")]
    attention: bool,
    #[serde(default = "yes")]
    fusion: bool,
}

fn yes() -> bool {
    true
}

#[derive(Serialize)]
struct EmbedResponse {
    descriptor_id: String,
    descriptor: Vec<f32>,
}

/// Raw image bytes in, unit descriptor out.
async fn embed(
    State(s): State<Arc<AppState>>,
    Query(q): Query<EmbedQuery>,
    body: Bytes,
) -> Result<Json<EmbedResponse>, ApiError> {
    let variant = Variant { attention: q.attention, fusion: q.fusion };
    let descriptor = s.engine.embed_image(body, variant, None).await?;
    Ok(Json(EmbedResponse { descriptor_id: s.engine.info().descriptor_id.clone(), descriptor }))
}
