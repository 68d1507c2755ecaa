//! The service as one tenant sees it: its session ids mapped to the store's, other tenants'
//! sessions and jobs answered NOT_FOUND (never "forbidden": ids cannot be probed). Both APIs
//! reach the service through this.
use super::error::ApiError;
use super::inspect::FramePage;
use super::jobs::{Jobs, SequenceRequest};
use super::service::{CreateSession, FrameInput, LoopMatch, LoopService, QueryOverrides, QueryTarget};
use super::wire::JobStatus;
use crate::auth::quota::{InFlight, Refusal};
use crate::auth::Caller;
use crate::engine::{in_lane, Lane};
use crate::inspect::similarity::Similarity;
use crate::model::network::Variant;
use crate::store::loops::{LoopFilter, LoopRecord, Page, Transform};
use crate::store::record::FrameHeader;
use crate::store::{Session, SessionInfo};
use std::sync::Arc;

pub struct Scoped<'a> {
    service: &'a LoopService,
    caller: Caller,
}

impl LoopService {
    pub fn scoped(&self, caller: Caller) -> Scoped<'_> {
        Scoped { service: self, caller }
    }
}

impl Scoped<'_> {
    /// The store's id of one of this tenant's sessions; an id with '/' names none of them.
    fn sid(&self, id: &str) -> Result<String, ApiError> {
        if id.contains('/') {
            return Err(ApiError::NotFound(format!("session '{}' not found", id.chars().take(80).collect::<String>())));
        }
        Ok(self.caller.store_id(id))
    }

    /// The caller's session `id`, brought up to date first (in a cluster: loaded from the log,
    /// every frame acknowledged through any node applied, gone if deleted elsewhere): the one
    /// lookup of a call, handed to the service.
    async fn fresh(&self, id: &str) -> Result<Arc<Session>, ApiError> {
        Ok(self.service.store.fresh(&self.sid(id)?).await?)
    }

    /// Limits checked before a write or query: the rate first, then stored frames (`adding`
    /// more), then the tenant's share of the queue (the slot is held until the guard drops).
    /// Checked per request: writes in flight at once may pass a frame limit by their number.
    async fn admit(&self, adding: usize) -> Result<Option<InFlight>, ApiError> {
        let Some(quota) = self.caller.quota_arc() else { return Ok(None) };
        quota.counters.requests.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let refuse = |why: Refusal, message: String| {
            quota.refused(why);
            ApiError::Overloaded(message)
        };
        quota.take().map_err(|m| refuse(Refusal::Rate, m))?;
        if let (Some(max), true) = (quota.limits.max_frames, adding > 0) {
            // Every session of the tenant (in a cluster, as the log counts them: a node may not
            // hold them all).
            let counts = self.service.store.frame_counts().await?;
            let held: u64 = counts.iter().filter(|(id, _)| self.caller.own(id).is_some()).map(|(_, n)| n).sum();
            if held + adding as u64 > max {
                return Err(refuse(
                    Refusal::Frames,
                    format!(
                        "tenant '{}' stores {held} frames; its limit is {max} (delete sessions or raise the limit)",
                        self.caller.tenant_name()
                    ),
                ));
            }
        }
        quota.enter().map(Some).map_err(|m| refuse(Refusal::Queue, m))
    }

    /// The caller's lane in the engine: its tenant, at its weight (default 1).
    fn lane(&self) -> Lane {
        let weight = self.caller.quota().and_then(|q| q.limits.weight).unwrap_or(1);
        Lane { name: Arc::from(self.caller.tenant_name()), weight }
    }

    /// Counts frames a tenant stored.
    fn added(&self, frames: usize) {
        if let Some(q) = self.caller.quota() {
            q.added(frames);
        }
    }

    pub async fn create_session(&self, mut req: CreateSession) -> Result<SessionInfo, ApiError> {
        if let Some(max) = self.caller.quota().and_then(|q| q.limits.max_sessions) {
            let held = self.list_sessions().await?.len();
            if held as u64 >= max {
                if let Some(q) = self.caller.quota() {
                    q.refused(Refusal::Sessions);
                }
                return Err(ApiError::Overloaded(format!(
                    "tenant '{}' has {held} sessions; its limit is {max}",
                    self.caller.tenant_name()
                )));
            }
        }
        let id = req.id.take().filter(|s| !s.is_empty()).unwrap_or_else(crate::store::new_session_id);
        if id.contains('/') {
            return Err(ApiError::InvalidArgument(
                "session id must be 1-64 characters of letters, digits, '-', '_' or '.', with a letter or digit".into(),
            ));
        }
        req.id = Some(self.caller.store_id(&id));
        Ok(self.caller.view(self.service.create_session(req).await?))
    }

    pub async fn session(&self, id: &str) -> Result<SessionInfo, ApiError> {
        Ok(self.caller.view(self.fresh(id).await?.info()))
    }

    pub async fn list_sessions(&self) -> Result<Vec<SessionInfo>, ApiError> {
        let all = self.service.store.list_fresh().await?;
        Ok(self.own(all))
    }

    fn own(&self, all: Vec<SessionInfo>) -> Vec<SessionInfo> {
        all.into_iter().filter(|s| self.caller.own(&s.meta.id).is_some()).map(|s| self.caller.view(s)).collect()
    }

    pub async fn delete_session(&self, id: &str) -> Result<(), ApiError> {
        self.service.delete_session(&self.sid(id)?).await
    }

    pub async fn frame(&self, session: &str, frame_id: u64) -> Result<FrameHeader, ApiError> {
        self.service.frame(&*self.fresh(session).await?, frame_id)
    }

    pub async fn frames(&self, session: &str, after: Option<u64>, limit: usize) -> Result<FramePage, ApiError> {
        self.service.frames(&*self.fresh(session).await?, after, limit)
    }

    pub async fn thumbnail(&self, session: &str, frame_id: u64) -> Result<Vec<u8>, ApiError> {
        self.service.thumbnail(&*self.fresh(session).await?, frame_id)
    }

    pub async fn similarity(&self, session: &str, size: usize) -> Result<Similarity, ApiError> {
        let s = self.fresh(session).await?;
        // A matrix costs size² dot products: it counts against the tenant's rate like a query.
        let _slot = self.admit(0).await?;
        self.service.similarity(s, size).await
    }

    pub async fn loops(&self, session: &str, filter: &LoopFilter) -> Result<Page, ApiError> {
        let s = self.fresh(session).await?;
        self.service.store.fresh_loops(&s.meta.id).await?;
        self.service.loops(&s, filter)
    }

    pub async fn snapshot(&self, session: &str) -> Result<crate::export::Snapshot, ApiError> {
        let s = self.fresh(session).await?;
        self.service.store.fresh_loops(&s.meta.id).await?;
        self.service.snapshot(&s)
    }

    pub async fn set_verdict(
        &self,
        session: &str,
        (query, matched): (u64, u64),
        accepted: bool,
        relative_pose: Option<Transform>,
        covariance: Option<Vec<f64>>,
    ) -> Result<LoopRecord, ApiError> {
        let s = self.fresh(session).await?;
        self.service.set_verdict(&s, query, matched, accepted, relative_pose, covariance).await
    }

    /// An image's descriptor (no session), in the caller's lane of the model.
    pub async fn embed(
        &self,
        image: bytes::Bytes,
        variant: Variant,
        model: Option<&str>,
    ) -> Result<(String, Vec<f32>), ApiError> {
        in_lane(self.lane(), self.service.embed(image, variant, model)).await
    }

    pub async fn add_frame(&self, session: &str, f: FrameInput) -> Result<u64, ApiError> {
        let s = self.fresh(session).await?;
        let _slot = self.admit(1).await?;
        let id = in_lane(self.lane(), self.service.add_frame(&s, f)).await?;
        self.added(1);
        Ok(id)
    }

    pub async fn query(
        &self,
        session: &str,
        robot_id: Option<String>,
        at_time: Option<f64>,
        target: QueryTarget,
        options: &QueryOverrides,
    ) -> Result<Vec<LoopMatch>, ApiError> {
        let s = self.fresh(session).await?;
        let _slot = self.admit(0).await?;
        in_lane(self.lane(), self.service.query(&s, robot_id, at_time, target, options)).await
    }

    pub async fn add_and_query(
        &self,
        session: &str,
        f: FrameInput,
        options: &QueryOverrides,
    ) -> Result<(u64, Vec<LoopMatch>), ApiError> {
        let s = self.fresh(session).await?;
        let _slot = self.admit(1).await?;
        let answer = in_lane(self.lane(), self.service.add_and_query(&s, f, options)).await?;
        self.added(1);
        Ok(answer)
    }

    pub async fn start_sequence(&self, jobs: &Jobs, session: &str, seq: SequenceRequest) -> Result<String, ApiError> {
        let s = self.fresh(session).await?;
        // A job runs after this returns: the slot checks the share at submission only; the
        // job's frames then wait for the tenant's rate, one token each, and are counted as its.
        drop(self.admit(seq.frames.len()).await?);
        let tenant = self.caller.quota_arc().map(|q| (self.caller.tenant_name().to_string(), q.clone()));
        jobs.start_sequence(self.service, &s, seq, tenant, self.lane()).await
    }

    /// A job of one of this tenant's sessions.
    pub async fn job(&self, jobs: &Jobs, job_id: &str) -> Result<JobStatus, ApiError> {
        let not_found =
            || ApiError::NotFound(format!("job '{}' not found", job_id.chars().take(80).collect::<String>()));
        let mut status = match jobs.job(job_id).await {
            Err(ApiError::NotFound(_)) => return Err(not_found()),
            other => other?,
        };
        let own = self.caller.own(&status.session_id).ok_or_else(not_found)?.to_string();
        status.session_id = own;
        Ok(status)
    }
}
