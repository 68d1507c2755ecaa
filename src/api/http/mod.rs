//! HTTP (axum, JSON under /v1): the operations of `LoopService`, as gRPC has them, plus embedding,
//! frame reads, the loop inspector and offline sequence jobs. Each route's handler carries its
//! part of the OpenAPI document (`#[utoipa::path]`) and the router is built from those handlers,
//! so `openapi.yaml` (`loopd openapi`) names exactly the routes served.
pub mod doc;
pub mod form;
pub mod frames;
pub mod inspect;
pub mod jobs;
pub mod loops;
pub mod node;
pub mod sessions;
mod state;
pub mod tenants;

use crate::api::error::ApiError;
use crate::auth::{Auth, Caller};
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::header;
use axum::response::IntoResponse;
use axum::Router;
pub use form::parse_frame_request;
pub use state::{AppState, FrameView};
use std::sync::Arc;
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// Every route with its document; `max_body_bytes` bounds sequence uploads, `frame_body` the
/// other routes' bodies (at most one image plus form fields), so a client cannot make the server
/// buffer a huge body there.
fn routes(frame_body: usize, max_body_bytes: usize) -> OpenApiRouter<Arc<AppState>> {
    let sequences =
        OpenApiRouter::new().routes(routes!(jobs::start_sequence)).layer(DefaultBodyLimit::max(max_body_bytes));
    OpenApiRouter::with_openapi(doc::ApiDoc::openapi())
        .routes(routes!(node::healthz))
        .routes(routes!(node::ready))
        .routes(routes!(node::metrics))
        .routes(routes!(node::info))
        .routes(routes!(node::models))
        .routes(routes!(node::cluster))
        .routes(routes!(node::embed))
        .routes(routes!(sessions::create_session, sessions::list_sessions))
        .routes(routes!(sessions::get_session, sessions::delete_session))
        .routes(routes!(frames::add_frame, inspect::list_frames))
        .routes(routes!(frames::get_frame))
        .routes(routes!(inspect::thumbnail))
        .routes(routes!(inspect::similarity))
        .routes(routes!(inspect::page))
        .routes(routes!(inspect::script))
        .routes(routes!(inspect::style))
        .routes(routes!(frames::query))
        .routes(routes!(frames::add_and_query))
        .routes(routes!(loops::list_loops))
        .routes(routes!(loops::export))
        .routes(routes!(loops::set_verdict))
        .routes(routes!(jobs::job_status))
        .routes(routes!(tenants::create_tenant, tenants::list_tenants))
        .routes(routes!(tenants::revoke_tenant))
        .layer(DefaultBodyLimit::max(frame_body))
        .merge(sequences)
}

pub fn router(state: Arc<AppState>, max_body_bytes: usize) -> Router {
    let frame_body = state.service.engine().info().limits.max_bytes + (1 << 20);
    let (router, _) = routes(frame_body, max_body_bytes).split_for_parts();
    router
        .layer(axum::middleware::from_fn_with_state(state.clone(), authenticate))
        .layer(axum::middleware::from_fn(mark_stale))
        .with_state(state)
}

/// The OpenAPI document of the routes [`router`] serves.
pub fn openapi() -> utoipa::openapi::OpenApi {
    routes(0, 0).into_openapi()
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
