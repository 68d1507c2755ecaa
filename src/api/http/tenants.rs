//! HTTP routes of tenants (admin key): create one (or give it a new key), list, revoke.
use super::doc::{BadRequest, Forbidden, NotFound, Unauthorized};
use super::state::{json_error, AppState};
use crate::api::error::ApiError;
use crate::auth::{Limits, TenantInfo};
use axum::extract::rejection::JsonRejection;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::Json;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// A tenant to create, or one to give a new key.
#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewTenant {
    name: String,
    #[serde(default)]
    limits: Limits,
}

/// The tenant and its key.
#[derive(Serialize, utoipa::ToSchema)]
pub struct TenantCreated {
    #[serde(flatten)]
    tenant: TenantInfo,
    /// Shown once; only its hash is kept.
    key: String,
}

/// Create a tenant (admin key); its key is in the answer, once
#[utoipa::path(
    post, path = "/v1/tenants", tag = "tenants",
    request_body = NewTenant,
    responses(
        (status = 201, description = "The tenant and its key (an existing tenant gets a new key; the old one stops working).",
         body = TenantCreated),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 403, response = Forbidden),
    )
)]
pub async fn create_tenant(
    State(s): State<Arc<AppState>>,
    body: Result<Json<NewTenant>, JsonRejection>,
) -> Result<(StatusCode, Json<TenantCreated>), ApiError> {
    let Json(t) = body.map_err(json_error)?;
    let (tenant, key) = s.auth.create_tenant(&t.name, t.limits).await?;
    Ok((StatusCode::CREATED, Json(TenantCreated { tenant, key })))
}

/// Every tenant.
#[derive(Serialize, utoipa::ToSchema)]
pub struct TenantList {
    tenants: Vec<TenantInfo>,
}

/// List tenants (admin key; no keys or hashes)
#[utoipa::path(
    get, path = "/v1/tenants", tag = "tenants",
    responses(
        (status = 200, description = "Every tenant.", body = TenantList),
        (status = 401, response = Unauthorized), (status = 403, response = Forbidden),
    )
)]
pub async fn list_tenants(State(s): State<Arc<AppState>>) -> Json<TenantList> {
    Json(TenantList { tenants: s.auth.list() })
}

/// Revoke a tenant's key (admin key); its sessions stay
#[utoipa::path(
    delete, path = "/v1/tenants/{name}", tag = "tenants",
    params(("name" = String, Path, description = "tenant name or key id")),
    responses(
        (status = 200, description = "The revoked tenant.", body = TenantInfo),
        (status = 401, response = Unauthorized), (status = 403, response = Forbidden),
        (status = 404, response = NotFound),
    )
)]
pub async fn revoke_tenant(
    State(s): State<Arc<AppState>>,
    Path(name): Path<String>,
) -> Result<Json<TenantInfo>, ApiError> {
    Ok(Json(s.auth.revoke(&name).await?))
}
