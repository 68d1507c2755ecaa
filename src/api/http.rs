//! HTTP (axum, JSON) routes; `openapi.yaml` describes each of them.
use super::error::ApiError;
use crate::engine::Engine;
use crate::model::network::{Variant, DESCRIPTOR_DIM};
use crate::model::preprocess::{prepare, ImageLimits};
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, Query, State};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

pub struct AppState {
    pub engine: Engine,
    pub limits: ImageLimits,
    pub device: String,
}

pub fn router(state: Arc<AppState>) -> Router {
    // Slightly above the image limit so an oversized image gets our 413 message, not a bare one.
    let body_limit = state.limits.max_bytes + 1024;
    Router::new()
        .route("/healthz", get(|| async { "ok" }))
        .route("/readyz", get(|| async { "ready" }))
        .route("/v1/info", get(info))
        .route("/v1/embed", post(embed))
        .layer(DefaultBodyLimit::max(body_limit))
        .with_state(state)
}

#[derive(Serialize)]
struct Info {
    descriptor_id: String,
    dim: i64,
    device: String,
    version: &'static str,
}

async fn info(State(s): State<Arc<AppState>>) -> Json<Info> {
    Json(Info {
        descriptor_id: s.engine.descriptor_id.clone(),
        dim: DESCRIPTOR_DIM,
        device: s.device.clone(),
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
    let (limits, pre) = (s.limits, s.engine.preprocess.clone());
    // Decoding runs on the blocking pool, never on the model thread.
    let input = tokio::task::spawn_blocking(move || prepare(&body, &limits, &pre))
        .await
        .map_err(|e| ApiError::BadRequest(format!("decoder failed: {e}")))??;
    let descriptor = s.engine.embed(input, Variant { attention: q.attention, fusion: q.fusion }).await?;
    Ok(Json(EmbedResponse { descriptor_id: s.engine.descriptor_id.clone(), descriptor }))
}
