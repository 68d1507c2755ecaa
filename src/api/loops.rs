//! Kept loop candidates: how clients list what the service recorded after answering, and give
//! their verdict. Both APIs reach these through `tenancy.rs`.
use super::error::ApiError;
use super::kept::{loop_records, now, QueryFrame};
use super::service::{LoopMatch, LoopService};
use crate::store::loops::{LoopFilter, LoopRecord, Page, Transform, Verdict};
use crate::store::Session;
use std::sync::Arc;

impl LoopService {
    /// Keeps the candidates answered again for a stored frame (a query on it; a new frame's
    /// are kept in its own flush, see `add_and_query`). A failure to keep them is logged and
    /// counted, not answered: the answer itself is right.
    pub(super) async fn keep_loops(&self, s: &Arc<Session>, q: QueryFrame<'_>, matches: &[LoopMatch]) {
        let records = loop_records(q, matches);
        if let Err(e) = self.store.keep_loops(s, records).await {
            self.loops_not_kept.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            tracing::warn!(session = %s.meta.id, error = %e, "loop candidates answered but not kept");
        }
    }

    pub fn loops(&self, s: &Session, filter: &LoopFilter) -> Result<Page, ApiError> {
        Ok(s.loops(filter)?)
    }

    /// A session's frames and kept loops as of now, for an export.
    pub fn snapshot(&self, s: &Session) -> Result<crate::export::Snapshot, ApiError> {
        Ok(crate::export::Snapshot { frames: s.headers()?, loops: s.all_loops()? })
    }

    pub async fn set_verdict(
        &self,
        s: &Arc<Session>,
        query: u64,
        matched: u64,
        accepted: bool,
        relative_pose: Option<Transform>,
        covariance: Option<Vec<f64>>,
    ) -> Result<LoopRecord, ApiError> {
        if let Some(p) = &relative_pose {
            let values = [p.qx, p.qy, p.qz, p.qw, p.tx, p.ty, p.tz];
            let norm = (p.qx * p.qx + p.qy * p.qy + p.qz * p.qz + p.qw * p.qw).sqrt();
            if values.iter().any(|v| !v.is_finite()) || (norm - 1.0).abs() > 1e-3 {
                return Err(ApiError::InvalidArgument(
                    "relative_pose needs finite values and a unit quaternion (qx qy qz qw)".into(),
                ));
            }
        }
        let verdict = Verdict { accepted, relative_pose, covariance, at: now() };
        Ok(self.store.set_verdict(s, query, matched, verdict).await?)
    }
}
