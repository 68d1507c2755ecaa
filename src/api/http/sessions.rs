//! HTTP routes of map sessions: create, list, describe, delete.
use super::doc::{BadRequest, Conflict, NotFound, Unauthorized, Unavailable};
use super::state::{json_error, AppState};
use crate::api::error::ApiError;
use crate::api::service::CreateSession;
use crate::auth::Caller;
use crate::store::SessionInfo;
use axum::extract::rejection::JsonRejection;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::{Extension, Json};
use serde::Serialize;
use std::sync::Arc;

/// Create a map session
#[utoipa::path(
    post, path = "/v1/sessions", tag = "sessions",
    request_body = CreateSession,
    responses(
        (status = 201, description = "Created.", body = SessionInfo),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 409, response = Conflict), (status = 429, response = super::doc::Overloaded),
        (status = 503, response = Unavailable),
    )
)]
pub async fn create_session(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    body: Result<Json<CreateSession>, JsonRejection>,
) -> Result<(StatusCode, Json<SessionInfo>), ApiError> {
    let Json(req) = body.map_err(json_error)?;
    Ok((StatusCode::CREATED, Json(s.service.scoped(caller).create_session(req).await?)))
}

/// All the caller's sessions, oldest first.
#[derive(Serialize, utoipa::ToSchema)]
pub struct SessionList {
    sessions: Vec<SessionInfo>,
}

/// List sessions
#[utoipa::path(
    get, path = "/v1/sessions", tag = "sessions",
    responses(
        (status = 200, description = "All sessions, oldest first.", body = SessionList),
        (status = 401, response = Unauthorized), (status = 503, response = Unavailable),
    )
)]
pub async fn list_sessions(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
) -> Result<Json<SessionList>, ApiError> {
    Ok(Json(SessionList { sessions: s.service.scoped(caller).list_sessions().await? }))
}

/// Describe a session (frames, robots, bytes)
#[utoipa::path(
    get, path = "/v1/sessions/{id}", tag = "sessions",
    params(("id" = String, Path)),
    responses(
        (status = 200, description = "The session.", body = SessionInfo),
        (status = 401, response = Unauthorized), (status = 404, response = NotFound),
        (status = 503, response = Unavailable),
    )
)]
pub async fn get_session(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Json<SessionInfo>, ApiError> {
    Ok(Json(s.service.scoped(caller).session(&id).await?))
}

/// Delete a session and its frames (disk and memory)
#[utoipa::path(
    delete, path = "/v1/sessions/{id}", tag = "sessions",
    params(("id" = String, Path)),
    responses(
        (status = 204, description = "Deleted."),
        (status = 401, response = Unauthorized), (status = 404, response = NotFound),
        (status = 503, response = Unavailable),
    )
)]
pub async fn delete_session(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    s.service.scoped(caller).delete_session(&id).await?;
    Ok(StatusCode::NO_CONTENT)
}
