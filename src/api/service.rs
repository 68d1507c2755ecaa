//! What both APIs do, written once: gRPC and HTTP only translate to and from these calls.
use super::error::ApiError;
use crate::engine::Engine;
use crate::model::network::{Variant, DESCRIPTOR_DIM};
use crate::store::index::Storage;
use crate::store::query::{LoopQuery, Match, Pose, Scope};
use crate::store::{NewFrame, Session, SessionInfo, Store};
use bytes::Bytes;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

#[derive(Clone)]
pub struct LoopService {
    pub engine: Engine,
    pub store: Arc<Store>,
}

/// A frame's picture: image bytes to embed, or a descriptor computed elsewhere.
pub enum Content {
    Image(Bytes),
    Descriptor(Vec<f32>),
}

/// Query options as sent: unset fields fall back to the session's defaults.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct QueryOverrides {
    pub k: Option<usize>,
    pub min_score: Option<f32>,
    pub exclude_last_frames: Option<usize>,
    pub exclude_last_seconds: Option<f64>,
    pub scope: Option<Scope>,
    pub time_range: Option<(f64, f64)>,
    pub frame_id_range: Option<(u64, u64)>,
}

impl QueryOverrides {
    pub fn apply(&self, base: &LoopQuery) -> LoopQuery {
        let mut q = base.clone();
        if let Some(v) = self.k {
            q.k = v;
        }
        if let Some(v) = self.min_score {
            q.min_score = v;
        }
        if let Some(v) = self.exclude_last_frames {
            q.exclude_last_frames = v;
        }
        if let Some(v) = self.exclude_last_seconds {
            q.exclude_last_seconds = v;
        }
        if let Some(v) = self.scope {
            q.scope = v;
        }
        if self.time_range.is_some() {
            q.time_range = self.time_range;
        }
        if self.frame_id_range.is_some() {
            q.frame_id_range = self.frame_id_range;
        }
        q
    }
}

pub struct FrameInput {
    pub robot_id: String,
    pub timestamp: f64,
    pub frame_id: Option<u64>,
    pub pose: Option<Pose>,
    pub metadata: Option<serde_json::Value>,
    pub content: Content,
}

pub enum QueryTarget {
    Content(Content),
    Frame(u64),
}

#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct CreateSession {
    pub id: Option<String>,
    pub name: String,
    pub storage: Storage,
    pub default_query: QueryOverrides,
}

impl LoopService {
    pub async fn create_session(&self, req: CreateSession) -> Result<SessionInfo, ApiError> {
        let defaults = req.default_query.apply(&LoopQuery::default());
        check_query(&defaults)?;
        let descriptor_id = self.engine.info().descriptor_id.clone();
        let meta = self
            .store
            .create_session(
                req.id.filter(|s| !s.is_empty()),
                req.name,
                DESCRIPTOR_DIM as usize,
                descriptor_id,
                req.storage,
                defaults,
            )
            .await?;
        Ok(self.store.session(&meta.id)?.info())
    }

    pub fn session(&self, id: &str) -> Result<SessionInfo, ApiError> {
        Ok(self.store.session(id)?.info())
    }

    pub fn list_sessions(&self) -> Vec<SessionInfo> {
        self.store.list()
    }

    pub async fn delete_session(&self, id: &str) -> Result<(), ApiError> {
        Ok(self.store.delete_session(id).await?)
    }

    async fn descriptor(&self, content: Content) -> Result<Vec<f32>, ApiError> {
        match content {
            Content::Image(bytes) => Ok(self.engine.embed_image(bytes, Variant::FULL, None).await?),
            Content::Descriptor(d) => Ok(d),
        }
    }

    /// The frame's session, after the checks that need no forward pass (unknown session first).
    fn check_frame(&self, session: &str, f: &FrameInput) -> Result<Arc<Session>, ApiError> {
        let s = self.store.session(session)?;
        if f.robot_id.is_empty() {
            return Err(ApiError::InvalidArgument("robot_id is required".into()));
        }
        if f.metadata.as_ref().is_some_and(|m| !m.is_object()) {
            return Err(ApiError::InvalidArgument("metadata must be a JSON object".into()));
        }
        Ok(s)
    }

    pub async fn add_frame(&self, session: &str, f: FrameInput) -> Result<u64, ApiError> {
        self.check_frame(session, &f)?;
        let descriptor = self.descriptor(f.content).await?;
        self.store_frame(session, f.robot_id, f.timestamp, f.frame_id, f.pose, f.metadata, descriptor).await
    }

    #[allow(clippy::too_many_arguments)]
    async fn store_frame(
        &self,
        session: &str,
        robot_id: String,
        timestamp: f64,
        frame_id: Option<u64>,
        pose: Option<Pose>,
        metadata: Option<serde_json::Value>,
        descriptor: Vec<f32>,
    ) -> Result<u64, ApiError> {
        let frame = NewFrame { frame_id, robot_id, timestamp, pose, metadata, descriptor };
        let ids = self.store.add_frames(session, vec![frame]).await?;
        ids.first().copied().ok_or_else(|| ApiError::Internal("no frame id returned".into()))
    }

    pub async fn query(
        &self,
        session: &str,
        robot_id: Option<String>,
        at_time: Option<f64>,
        target: QueryTarget,
        options: &QueryOverrides,
    ) -> Result<Vec<Match>, ApiError> {
        let s = self.store.session(session)?;
        let mut q = options.apply(&s.meta.default_query);
        q.robot_id = robot_id.filter(|r| !r.is_empty());
        q.at_time = at_time;
        check_query(&q)?;
        match target {
            QueryTarget::Frame(id) => Ok(self.store.query_frame(session, id, &q)?),
            QueryTarget::Content(c) => {
                let d = self.descriptor(c).await?;
                Ok(self.store.query(session, d, &q)?)
            }
        }
    }

    /// Queries with the new frame first (so it cannot match itself), then stores it.
    pub async fn add_and_query(
        &self,
        session: &str,
        f: FrameInput,
        options: &QueryOverrides,
    ) -> Result<(u64, Vec<Match>), ApiError> {
        let s = self.check_frame(session, &f)?;
        let mut q = options.apply(&s.meta.default_query);
        q.robot_id = Some(f.robot_id.clone());
        q.at_time = Some(f.timestamp);
        check_query(&q)?;
        let descriptor = self.descriptor(f.content).await?;
        let matches = self.store.query(session, descriptor.clone(), &q)?;
        let id = self.store_frame(session, f.robot_id, f.timestamp, f.frame_id, f.pose, f.metadata, descriptor).await?;
        Ok((id, matches))
    }
}

fn check_query(q: &LoopQuery) -> Result<(), ApiError> {
    if q.k == 0 || q.k > crate::store::query::MAX_K {
        return Err(ApiError::InvalidArgument(format!("k must be 1..={}", crate::store::query::MAX_K)));
    }
    if !q.min_score.is_finite() || !q.exclude_last_seconds.is_finite() || q.exclude_last_seconds < 0.0 {
        return Err(ApiError::InvalidArgument(
            "min_score and exclude_last_seconds must be finite (seconds >= 0)".into(),
        ));
    }
    Ok(())
}
