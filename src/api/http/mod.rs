//! HTTP (axum, JSON under /v1): the operations of `LoopService`, as gRPC has them, plus embedding,
//! frame reads and offline sequence jobs; `openapi.yaml` describes each route.
pub mod inspect;
pub mod loops;
mod state;

use crate::api::error::ApiError;
use crate::api::jobs::SequenceRequest;
use crate::api::service::{Content, CreateSession, FrameInput, LoopMatch, QueryOverrides, QueryTarget};
use crate::api::wire::JobStatus;
use crate::auth::{Auth, Caller};
use crate::index::query::Pose;
use crate::model::network::Variant;
use crate::store::SessionInfo;
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, FromRequest, Multipart, Path, Query, Request, State};
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use axum::routing::{get, post};
use axum::Extension;
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use state::{body_error, json_error, parse_u64};
pub use state::{AppState, FrameView};
use std::collections::HashMap;
use std::sync::Arc;

/// `max_body_bytes` bounds sequence uploads only; every other route takes at most one image
/// (plus form fields), so a client cannot make the server buffer a huge body there.
pub fn router(state: Arc<AppState>, max_body_bytes: usize) -> Router {
    let frame_body = state.service.engine.info().limits.max_bytes + (1 << 20);
    let sequences = Router::new()
        .route("/v1/sessions/{id}/sequences", post(start_sequence))
        .layer(DefaultBodyLimit::max(max_body_bytes));
    Router::new()
        .route("/healthz", get(|| async { "ok" }))
        .route("/readyz", get(ready))
        .route("/metrics", get(metrics))
        .route("/v1/info", get(info))
        .route("/v1/cluster", get(cluster))
        .route("/v1/embed", post(embed))
        .route("/v1/sessions", post(create_session).get(list_sessions))
        .route("/v1/sessions/{id}", get(get_session).delete(delete_session))
        .route("/v1/sessions/{id}/frames", post(add_frame).get(inspect::list_frames))
        .route("/v1/sessions/{id}/frames/{frame_id}", get(get_frame))
        .route("/v1/sessions/{id}/frames/{frame_id}/thumbnail", get(inspect::thumbnail))
        .route("/v1/sessions/{id}/similarity", get(inspect::similarity))
        .route("/v1/sessions/{id}/inspect", get(inspect::page))
        .route("/v1/inspector/app.js", get(inspect::script))
        .route("/v1/inspector/app.css", get(inspect::style))
        .route("/v1/sessions/{id}/query", post(query))
        .route("/v1/sessions/{id}/add_and_query", post(add_and_query))
        .route("/v1/sessions/{id}/loops", get(loops::list_loops))
        .route("/v1/sessions/{id}/export", get(loops::export))
        .route("/v1/sessions/{id}/loops/{query_frame}/{match_frame}/verdict", post(loops::set_verdict))
        .route("/v1/jobs/{job_id}", get(job_status))
        .route("/v1/tenants", post(create_tenant).get(list_tenants))
        .route("/v1/tenants/{name}", axum::routing::delete(revoke_tenant))
        .layer(DefaultBodyLimit::max(frame_body))
        .merge(sequences)
        .layer(axum::middleware::from_fn_with_state(state.clone(), authenticate))
        .layer(axum::middleware::from_fn(mark_stale))
        .with_state(state)
}

/// `X-Loopd-Stale: 1` on an answer a cluster node gave from its own index while the log's
/// version could not be read (no writable primary): it may lack the frames acknowledged last.
async fn mark_stale(req: Request, next: axum::middleware::Next) -> axum::response::Response {
    let (mut response, stale) = crate::store::tracking_staleness(next.run(req)).await;
    if stale {
        response.headers_mut().insert("x-loopd-stale", header::HeaderValue::from_static("1"));
    }
    response
}

/// 503 while writes cannot succeed (a storage failure not yet recovered, or in a cluster no
/// writable primary at the last probe): a balancer or an orchestrator sends robots elsewhere.
async fn ready(State(s): State<Arc<AppState>>) -> Result<&'static str, ApiError> {
    match s.service.store.readiness() {
        None => Ok("ready"),
        Some(e) => Err(ApiError::Unavailable(format!("not ready: {e}; writes are refused until it recovers"))),
    }
}

async fn metrics(State(s): State<Arc<AppState>>) -> Result<impl IntoResponse, ApiError> {
    let body = crate::api::metrics::encode(&s.metrics)
        .map_err(|e| ApiError::Internal(format!("encoding the metrics failed: {e}")))?;
    Ok(([(header::CONTENT_TYPE, crate::api::metrics::CONTENT_TYPE)], body))
}

#[derive(Serialize)]
struct Info {
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

async fn info(State(s): State<Arc<AppState>>) -> Json<Info> {
    let e = &s.service.engine;
    let i = e.info();
    Json(Info {
        descriptor_id: i.descriptor_id.clone(),
        dim: i.dim as i64,
        device: i.device.clone(),
        dtype: i.dtype.clone(),
        max_batch: e.config().max_batch,
        max_image_bytes: i.limits.max_bytes,
        version: env!("CARGO_PKG_VERSION"),
        loop_confidence: s.service.calibrator.as_ref().map(|c| c.loop_confidence),
    })
}

/// A cluster node's members and the sessions it holds (admin key: it names every tenant's
/// sessions).
async fn cluster(State(s): State<Arc<AppState>>) -> Result<Json<crate::store::ClusterView>, ApiError> {
    s.service.store.cluster_view().map(Json).ok_or_else(|| {
        ApiError::NotFound("this server keeps its sessions in sled, not in a cluster (serve --cluster)".into())
    })
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct EmbedQuery {
    attention: Option<bool>,
    fusion: Option<bool>,
}

#[derive(Serialize)]
struct EmbedResponse {
    descriptor_id: String,
    descriptor: Vec<f32>,
}

/// Raw image bytes in, unit descriptor out.
async fn embed(
    State(s): State<Arc<AppState>>,
    q: Result<Query<EmbedQuery>, axum::extract::rejection::QueryRejection>,
    body: Result<Bytes, axum::extract::rejection::BytesRejection>,
) -> Result<Json<EmbedResponse>, ApiError> {
    let Query(q) = q.map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    let body = body.map_err(|e| ApiError::TooLarge(e.body_text()))?;
    let variant = Variant { attention: q.attention.unwrap_or(true), fusion: q.fusion.unwrap_or(true) };
    let (descriptor_id, descriptor) = s.service.embed(body, variant).await?;
    Ok(Json(EmbedResponse { descriptor_id, descriptor }))
}

async fn create_session(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    body: Result<Json<CreateSession>, axum::extract::rejection::JsonRejection>,
) -> Result<(StatusCode, Json<SessionInfo>), ApiError> {
    let Json(req) = body.map_err(json_error)?;
    Ok((StatusCode::CREATED, Json(s.service.scoped(caller).create_session(req).await?)))
}

#[derive(Serialize)]
struct SessionList {
    sessions: Vec<SessionInfo>,
}

async fn list_sessions(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
) -> Result<Json<SessionList>, ApiError> {
    Ok(Json(SessionList { sessions: s.service.scoped(caller).list_sessions().await? }))
}

async fn get_session(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Json<SessionInfo>, ApiError> {
    Ok(Json(s.service.scoped(caller).session(&id).await?))
}

async fn delete_session(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    s.service.scoped(caller).delete_session(&id).await?;
    Ok(StatusCode::NO_CONTENT)
}

async fn get_frame(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path((id, frame_id)): Path<(String, String)>,
) -> Result<Json<FrameView>, ApiError> {
    let frame_id = parse_u64("frame_id", &frame_id)?;
    Ok(Json(FrameView::new(frame_id, s.service.scoped(caller).frame(&id, frame_id).await?)))
}

/// A frame or query as sent: JSON body, multipart form (an `image` file plus fields), or a raw
/// image body with the fields in the query string. Field names are the same in all three.
#[derive(Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct FrameFields {
    robot_id: Option<String>,
    timestamp: Option<f64>,
    frame_id: Option<u64>,
    pose: Option<Pose>,
    metadata: Option<serde_json::Value>,
    descriptor: Option<Vec<f32>>,
    options: Option<QueryOverrides>,
    #[serde(skip)]
    image: Option<Bytes>,
}

/// Text form fields (multipart or query string) into the same JSON shape as a JSON body.
fn fields_from_text(map: HashMap<String, String>, image: Option<Bytes>) -> Result<FrameFields, ApiError> {
    let mut obj = serde_json::Map::new();
    for (k, v) in map {
        let value = match k.as_str() {
            "robot_id" => serde_json::Value::String(v),
            "timestamp" | "frame_id" | "pose" | "metadata" | "descriptor" | "options" => serde_json::from_str(&v)
                .map_err(|e| ApiError::InvalidArgument(format!("field {k}: not valid JSON/number ({e})")))?,
            other => return Err(ApiError::InvalidArgument(format!("unknown field '{other}'"))),
        };
        obj.insert(k, value);
    }
    let mut f: FrameFields =
        serde_json::from_value(serde_json::Value::Object(obj)).map_err(|e| ApiError::InvalidArgument(e.to_string()))?;
    f.image = image;
    Ok(f)
}

/// A frame request as `POST /v1/sessions/{id}/frames` reads it (JSON, multipart or raw body),
/// converted and validated: the fuzz target's entry.
pub async fn parse_frame_request(req: Request) -> Result<(FrameInput, QueryOverrides), ApiError> {
    let (f, opts) = frame_input(read_fields(req).await?)?;
    f.validate(&opts)?;
    Ok((f, opts))
}

async fn read_fields(req: Request) -> Result<FrameFields, ApiError> {
    if content_type(&req).starts_with("application/json") {
        let Json(f) = Json::<FrameFields>::from_request(req, &()).await.map_err(json_error)?;
        return Ok(f);
    }
    let mut form = read_form(req, &["image"]).await?;
    let image = match (form.files.pop(), form.body) {
        (Some(_), _) if !form.files.is_empty() => {
            return Err(ApiError::InvalidArgument("one 'image' part per frame".into()));
        }
        (Some(file), _) => Some(file.data),
        (None, body) => body.filter(|b| !b.is_empty()),
    };
    fields_from_text(form.fields, image)
}

fn content_type(req: &Request) -> String {
    req.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_string()
}

/// One uploaded file of a form.
pub struct FormFile {
    /// The form part's name (`image`, `archive`).
    pub part: String,
    /// The client's file name, if it sent one.
    pub file_name: Option<String>,
    pub data: Bytes,
}

/// A request as fields and files: a multipart form (parts named in `file_parts` are files, the
/// rest text fields), or a raw body with the fields in the query string. The one form reader
/// of the HTTP API: size limits answer 413 wherever they are hit.
pub struct Form {
    pub fields: HashMap<String, String>,
    pub files: Vec<FormFile>,
    /// The raw body of a non-multipart request.
    pub body: Option<Bytes>,
}

async fn read_form(req: Request, file_parts: &[&str]) -> Result<Form, ApiError> {
    let Query(mut fields) = Query::<HashMap<String, String>>::try_from_uri(req.uri())
        .map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    if !content_type(&req).starts_with("multipart/form-data") {
        let body = Bytes::from_request(req, &()).await.map_err(|e| body_error(e.status(), e.body_text()))?;
        return Ok(Form { fields, files: Vec::new(), body: Some(body) });
    }
    let mut mp = Multipart::from_request(req, &()).await.map_err(|e| body_error(e.status(), e.body_text()))?;
    let mut files = Vec::new();
    while let Some(field) = mp.next_field().await.map_err(multipart_error)? {
        let part = field.name().unwrap_or("").to_string();
        if file_parts.contains(&part.as_str()) {
            let file_name = field.file_name().filter(|n| !n.is_empty()).map(str::to_string);
            files.push(FormFile { part, file_name, data: field.bytes().await.map_err(multipart_error)? });
        } else {
            let data = field.bytes().await.map_err(multipart_error)?;
            let text = String::from_utf8(data.to_vec())
                .map_err(|_| ApiError::InvalidArgument(format!("field {part} is not text")))?;
            fields.insert(part, text);
        }
    }
    Ok(Form { fields, files, body: None })
}

fn multipart_error(e: axum::extract::multipart::MultipartError) -> ApiError {
    body_error(e.status(), e.body_text())
}

fn content(f: &mut FrameFields) -> Result<Content, ApiError> {
    match (f.image.take(), f.descriptor.take()) {
        (Some(_), Some(_)) => Err(ApiError::InvalidArgument("send an image or a descriptor, not both".into())),
        (Some(img), None) => Ok(Content::Image(img)),
        (None, Some(d)) => Ok(Content::Descriptor(d)),
        (None, None) => Err(ApiError::InvalidArgument("an image or a descriptor is required".into())),
    }
}

fn frame_input(mut f: FrameFields) -> Result<(FrameInput, QueryOverrides), ApiError> {
    let content = content(&mut f)?;
    let input = FrameInput {
        robot_id: f.robot_id.unwrap_or_default(),
        timestamp: f.timestamp,
        frame_id: f.frame_id,
        pose: f.pose,
        metadata: f.metadata,
        content,
        thumbnail: None,
    };
    Ok((input, f.options.unwrap_or_default()))
}

#[derive(Serialize)]
struct AddFrameResponse {
    frame_id: u64,
}

async fn add_frame(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    req: Request,
) -> Result<(StatusCode, Json<AddFrameResponse>), ApiError> {
    let (f, _) = frame_input(read_fields(req).await?)?;
    Ok((StatusCode::CREATED, Json(AddFrameResponse { frame_id: s.service.scoped(caller).add_frame(&id, f).await? })))
}

#[derive(Serialize)]
struct QueryResponse {
    matches: Vec<LoopMatch>,
}

async fn query(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    req: Request,
) -> Result<Json<QueryResponse>, ApiError> {
    let mut f = read_fields(req).await?;
    let target = match f.frame_id {
        Some(frame) if f.image.is_none() && f.descriptor.is_none() => QueryTarget::Frame(frame),
        _ => QueryTarget::Content(content(&mut f)?),
    };
    let opts = f.options.unwrap_or_default();
    Ok(Json(QueryResponse {
        matches: s.service.scoped(caller).query(&id, f.robot_id, f.timestamp, target, &opts).await?,
    }))
}

#[derive(Serialize)]
struct AddAndQueryResponse {
    frame_id: u64,
    matches: Vec<LoopMatch>,
}

async fn add_and_query(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    req: Request,
) -> Result<Json<AddAndQueryResponse>, ApiError> {
    let (f, opts) = frame_input(read_fields(req).await?)?;
    let (frame_id, matches) = s.service.scoped(caller).add_and_query(&id, f, &opts).await?;
    Ok(Json(AddAndQueryResponse { frame_id, matches }))
}

#[derive(Serialize)]
struct JobCreated {
    job_id: String,
    status_url: String,
}

/// An offline sequence: multipart with many `image` files (in the order sent, or natural name
/// order with `order=name`), one tar archive (`archive` part or a tar body), or a bag (`bag`
/// parts, the files of a split bag in order, or an MCAP / ROS 1 bag body).
async fn start_sequence(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    req: Request,
) -> Result<(StatusCode, Json<JobCreated>), ApiError> {
    let scoped = s.service.scoped(caller);
    scoped.session(&id).await?;
    let form = read_form(req, &["image", "archive", "bag"]).await?;
    let files = form.files.into_iter().map(|f| (f.part, f.file_name, f.data)).collect();
    // Unpacking a bag (decompression, raw pixels to PNG) is CPU work: off the async workers.
    let seq = tokio::task::spawn_blocking(move || SequenceRequest::from_form(form.fields, files, form.body))
        .await
        .map_err(|e| ApiError::Internal(format!("reading the upload failed: {e}")))??;
    let job_id = scoped.start_sequence(&s.jobs, &id, seq).await?;
    Ok((StatusCode::ACCEPTED, Json(JobCreated { status_url: format!("/v1/jobs/{job_id}"), job_id })))
}

async fn job_status(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(job_id): Path<String>,
) -> Result<Json<JobStatus>, ApiError> {
    Ok(Json(s.service.scoped(caller).job(&s.jobs, &job_id).await?))
}

/// Who is calling, from `Authorization: Bearer <key>`, before any route runs: health, readiness
/// and the inspector's static files (no data; the page asks for a key) are open; metrics and tenant routes take the admin key; everything else a tenant's
/// key (or the admin's, acting for the default tenant). Keys in the URL are refused (they end up
/// in logs and browser histories).
async fn authenticate(
    State(s): State<Arc<AppState>>,
    mut req: Request,
    next: axum::middleware::Next,
) -> axum::response::Response {
    let path = req.uri().path();
    if path == "/healthz" || path == "/readyz" || inspect::is_static(path) {
        return next.run(req).await;
    }
    // Refused before its body is read: an HTTP/1 connection cannot be reused after that (the
    // unread body is still on it), so the answer says so and a client does not reuse it.
    let unread_body = req.version() <= axum::http::Version::HTTP_11
        && (req.headers().contains_key(header::TRANSFER_ENCODING)
            || req.headers().get(header::CONTENT_LENGTH).is_some_and(|v| v.as_bytes() != b"0"));
    match admit(&s.auth, &req) {
        Ok(caller) => {
            req.extensions_mut().insert(caller);
            next.run(req).await
        }
        Err(e) => {
            let mut r = e.into_response();
            if unread_body {
                r.headers_mut().insert(header::CONNECTION, axum::http::HeaderValue::from_static("close"));
            }
            r
        }
    }
}

fn admit(auth: &Auth, req: &Request) -> Result<Caller, ApiError> {
    let path = req.uri().path();
    let tenants = path.starts_with("/v1/tenants");
    let admin_only = path == "/metrics" || path == "/v1/cluster" || tenants;
    let in_url = req.uri().query().is_some_and(|q| {
        q.split('&').any(|kv| {
            let name = kv.split('=').next().unwrap_or("").to_ascii_lowercase();
            ["key", "api_key", "apikey", "token", "access_token", "authorization"].contains(&name.as_str())
        })
    });
    if in_url && auth.enabled() {
        return Err(ApiError::Unauthenticated("send the key in the Authorization header, never in the URL".into()));
    }
    let caller = auth.authenticate(req.headers().get(header::AUTHORIZATION).map(|v| v.as_bytes()))?;
    if admin_only {
        auth.require_admin(&caller, tenants)?;
    }
    Ok(caller)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct NewTenant {
    name: String,
    #[serde(default)]
    limits: crate::auth::Limits,
}

#[derive(Serialize)]
struct TenantCreated {
    #[serde(flatten)]
    tenant: crate::auth::TenantInfo,
    /// Shown once; only its hash is kept.
    key: String,
}

async fn create_tenant(
    State(s): State<Arc<AppState>>,
    body: Result<Json<NewTenant>, axum::extract::rejection::JsonRejection>,
) -> Result<(StatusCode, Json<TenantCreated>), ApiError> {
    let Json(t) = body.map_err(json_error)?;
    let (tenant, key) = s.auth.create_tenant(&t.name, t.limits).await?;
    Ok((StatusCode::CREATED, Json(TenantCreated { tenant, key })))
}

#[derive(Serialize)]
struct TenantList {
    tenants: Vec<crate::auth::TenantInfo>,
}

async fn list_tenants(State(s): State<Arc<AppState>>) -> Json<TenantList> {
    Json(TenantList { tenants: s.auth.list() })
}

async fn revoke_tenant(
    State(s): State<Arc<AppState>>,
    Path(name): Path<String>,
) -> Result<Json<crate::auth::TenantInfo>, ApiError> {
    Ok(Json(s.auth.revoke(&name).await?))
}
