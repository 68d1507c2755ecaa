//! HTTP routes of the node itself: liveness, readiness, metrics, what it computes, its view of
//! the cluster, and embedding an image without storing it.
use super::doc::{BadRequest, Binary, Forbidden, Overloaded, TooLarge, Unauthorized, Unavailable};
use super::state::AppState;
use crate::api::error::{ApiError, ErrorBody};
use crate::auth::Caller;
use crate::model::network::Variant;
use crate::store::ClusterView;
use axum::body::Bytes;
use axum::extract::rejection::{BytesRejection, QueryRejection};
use axum::extract::{Query, State};
use axum::http::header;
use axum::response::IntoResponse;
use axum::Extension;
use axum::Json;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Liveness
#[utoipa::path(
    get, path = "/healthz", tag = "node", security(()),
    responses((status = 200, description = "The process is up.", body = String, content_type = "text/plain"))
)]
pub async fn healthz() -> &'static str {
    "ok"
}

/// Readiness (model loaded and warmed up, store open and taking writes; in a cluster, a writable primary with a synchronous standby at the last probe)
///
/// 503 while writes cannot succeed (a storage failure not yet recovered, or in a cluster no
/// writable primary at the last probe): a balancer or an orchestrator sends robots elsewhere.
#[utoipa::path(
    get, path = "/readyz", tag = "node", security(()),
    responses(
        (status = 200, description = "Ready.", body = String, content_type = "text/plain"),
        (status = 503, response = Unavailable),
    )
)]
pub async fn ready(State(s): State<Arc<AppState>>) -> Result<&'static str, ApiError> {
    match s.service.store.readiness() {
        None => Ok("ready"),
        Some(e) => Err(ApiError::Unavailable(format!("not ready: {e}; writes are refused until it recovers"))),
    }
}

/// Prometheus metrics (engine batch sizes, queue wait, forward time, images/s; tenants; open connections; admin key)
#[utoipa::path(
    get, path = "/metrics", tag = "node",
    responses(
        (status = 200, description = "OpenMetrics text format (prometheus-client's encoder).", body = String,
         content_type = "application/openmetrics-text"),
        (status = 401, response = Unauthorized), (status = 403, response = Forbidden),
    )
)]
pub async fn metrics(State(s): State<Arc<AppState>>) -> Result<impl IntoResponse, ApiError> {
    let body = crate::api::metrics::encode(&s.metrics)
        .map_err(|e| ApiError::Internal(format!("encoding the metrics failed: {e}")))?;
    Ok(([(header::CONTENT_TYPE, crate::api::metrics::CONTENT_TYPE)], body))
}

/// What this server computes.
#[derive(Serialize, utoipa::ToSchema)]
pub struct Info {
    /// Names the descriptor space (model, variant, input size).
    descriptor_id: String,
    dim: i64,
    device: String,
    dtype: String,
    max_batch: usize,
    max_image_bytes: usize,
    version: &'static str,
    /// The threshold of the calibrated confidence this server trusts as a loop (the calibrator's
    /// `loop_confidence`: every training query's first candidate at or above it was right), or
    /// null when its answers carry no confidence.
    loop_confidence: Option<f32>,
}

/// Model, device and limits
#[utoipa::path(
    get, path = "/v1/info", tag = "node",
    responses(
        (status = 200, description = "What this server computes.", body = Info),
        (status = 401, response = Unauthorized),
    )
)]
pub async fn info(State(s): State<Arc<AppState>>) -> Json<Info> {
    let e = s.service.engine();
    let i = e.info();
    Json(Info {
        descriptor_id: i.descriptor_id.clone(),
        dim: i.dim as i64,
        device: i.device.clone(),
        dtype: i.dtype.clone(),
        max_batch: e.config().max_batch,
        max_image_bytes: i.limits.max_bytes,
        version: env!("CARGO_PKG_VERSION"),
        loop_confidence: s.service.calibrator().map(|c| c.loop_confidence),
    })
}

/// A model this server serves.
#[derive(Serialize, utoipa::ToSchema)]
pub struct ModelInfo {
    /// Its name: sessions created with `model` set to it hold its descriptors.
    name: String,
    /// "builtin" or "torchscript".
    kind: String,
    /// The server's default model (sessions created without `model`).
    default: bool,
    descriptor_id: String,
    dim: i64,
    /// Input width and height in pixels (a "keep" resize fits the image inside them).
    input_width: u32,
    input_height: u32,
    device: String,
    license: String,
    source: String,
}

/// Every model this server serves.
#[derive(Serialize, utoipa::ToSchema)]
pub struct ModelList {
    models: Vec<ModelInfo>,
}

/// The served models (`serve --models`), the default first
#[utoipa::path(
    get, path = "/v1/models", tag = "node",
    responses(
        (status = 200, description = "The served models.", body = ModelList),
        (status = 401, response = Unauthorized),
    )
)]
pub async fn models(State(s): State<Arc<AppState>>) -> Json<ModelList> {
    Json(ModelList { models: s.service.models.iter().enumerate().map(|(n, e)| model_info(e, n == 0)).collect() })
}

fn model_info(e: &crate::engine::Engine, default: bool) -> ModelInfo {
    let i = e.info();
    let (input_width, input_height) = i.input.size();
    ModelInfo {
        name: i.name.clone(),
        kind: i.about.kind.into(),
        default,
        descriptor_id: i.descriptor_id.clone(),
        dim: i.dim as i64,
        input_width,
        input_height,
        device: i.device.clone(),
        license: i.about.license.clone(),
        source: i.about.source.clone(),
    }
}

/// A cluster node's view: its name, the live members and the sessions it holds, each with whether it is one of its owners (admin key)
#[utoipa::path(
    get, path = "/v1/cluster", tag = "node",
    responses(
        (status = 200, description = "This node's view of the cluster.", body = ClusterView),
        (status = 401, response = Unauthorized), (status = 403, response = Forbidden),
        (status = 404, description = "Not a cluster node (sessions in sled).", body = ErrorBody),
    )
)]
pub async fn cluster(State(s): State<Arc<AppState>>) -> Result<Json<ClusterView>, ApiError> {
    s.service.store.cluster_view().map(Json).ok_or_else(|| {
        ApiError::NotFound("this server keeps its sessions in sled, not in a cluster (serve --cluster)".into())
    })
}

#[derive(Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct EmbedQuery {
    /// The attention heads (default true).
    attention: Option<bool>,
    /// The layer1/layer4 fusion (default true).
    fusion: Option<bool>,
    /// The served model (default: the server's default; `GET /v1/models`).
    model: Option<String>,
}

/// The unit descriptor of an image.
#[derive(Serialize, utoipa::ToSchema)]
pub struct EmbedResponse {
    descriptor_id: String,
    descriptor: Vec<f32>,
}

/// Descriptor of one image (stores nothing)
#[utoipa::path(
    post, path = "/v1/embed", tag = "node",
    params(EmbedQuery),
    request_body(content((Binary = "application/octet-stream"))),
    responses(
        (status = 200, description = "The unit descriptor.", body = EmbedResponse),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 413, response = TooLarge), (status = 429, response = Overloaded),
        (status = 503, response = Unavailable),
    )
)]
pub async fn embed(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    q: Result<Query<EmbedQuery>, QueryRejection>,
    body: Result<Bytes, BytesRejection>,
) -> Result<Json<EmbedResponse>, ApiError> {
    let Query(q) = q.map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    let body = body.map_err(|e| ApiError::TooLarge(e.body_text()))?;
    let variant = Variant { attention: q.attention.unwrap_or(true), fusion: q.fusion.unwrap_or(true) };
    let (descriptor_id, descriptor) = s.service.scoped(caller).embed(body, variant, q.model.as_deref()).await?;
    Ok(Json(EmbedResponse { descriptor_id, descriptor }))
}
