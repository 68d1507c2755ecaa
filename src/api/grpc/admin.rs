//! The gRPC Admin service: tenants and keys for the admin key, as HTTP's /v1/tenants.
use crate::api::error::ApiError;
use crate::auth::{Auth, Limits, TenantInfo};
use crate::pb;
use std::sync::Arc;
use tonic::{Request, Response, Status};

pub use pb::admin_server::AdminServer;

pub struct AdminApi {
    pub auth: Arc<Auth>,
}

impl AdminApi {
    fn require_admin<T>(&self, req: &Request<T>) -> Result<(), Status> {
        let caller = super::caller(req)?;
        Ok(self.auth.require_admin(&caller, true).map_err(ApiError::from)?)
    }
}

fn limits(l: Option<pb::TenantLimits>) -> Limits {
    let l = l.unwrap_or_default();
    Limits {
        max_sessions: l.max_sessions,
        max_frames: l.max_frames,
        rate: l.rate,
        max_in_flight: l.max_in_flight,
        weight: l.weight,
    }
}

fn tenant(t: TenantInfo) -> pb::Tenant {
    let l = t.limits;
    pb::Tenant {
        name: t.name,
        key_id: t.key_id,
        created: t.created,
        revoked: t.revoked,
        limits: Some(pb::TenantLimits {
            max_sessions: l.max_sessions,
            max_frames: l.max_frames,
            rate: l.rate,
            max_in_flight: l.max_in_flight,
            weight: l.weight,
        }),
    }
}

#[tonic::async_trait]
impl pb::admin_server::Admin for AdminApi {
    async fn create_tenant(
        &self,
        req: Request<pb::CreateTenantRequest>,
    ) -> Result<Response<pb::CreateTenantResponse>, Status> {
        self.require_admin(&req)?;
        let r = req.into_inner();
        let (info, key) = self.auth.create_tenant(&r.name, limits(r.limits)).await.map_err(ApiError::from)?;
        Ok(Response::new(pb::CreateTenantResponse { tenant: Some(tenant(info)), key }))
    }

    async fn list_tenants(
        &self,
        req: Request<pb::ListTenantsRequest>,
    ) -> Result<Response<pb::ListTenantsResponse>, Status> {
        self.require_admin(&req)?;
        Ok(Response::new(pb::ListTenantsResponse { tenants: self.auth.list().into_iter().map(tenant).collect() }))
    }

    async fn revoke_tenant(&self, req: Request<pb::RevokeTenantRequest>) -> Result<Response<pb::Tenant>, Status> {
        self.require_admin(&req)?;
        let info = self.auth.revoke(&req.into_inner().name_or_key_id).await.map_err(ApiError::from)?;
        Ok(Response::new(tenant(info)))
    }
}
