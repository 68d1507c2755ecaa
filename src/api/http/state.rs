//! What every HTTP handler shares: the router's state, a stored frame's view, and how path
//! fields and bodies that do not parse become errors.
use crate::api::error::ApiError;
use crate::api::jobs::Jobs;
use crate::api::service::LoopService;
use crate::auth::Auth;
use crate::index::query::Pose;
use axum::http::StatusCode;
use serde::Serialize;
use std::sync::Arc;

pub struct AppState {
    pub service: LoopService,
    pub auth: Arc<Auth>,
    /// Offline sequence jobs; they call the service.
    pub jobs: Arc<Jobs>,
    /// Every layer's counters (`/metrics`).
    pub metrics: Arc<prometheus_client::registry::Registry>,
}

/// A stored frame as HTTP answers it (one frame, or each of a listing's).
#[derive(Serialize, utoipa::ToSchema)]
#[schema(as = Frame)]
pub struct FrameView {
    frame_id: u64,
    robot_id: String,
    timestamp: f64,
    pose: Option<Pose>,
    /// The JSON object stored with the frame.
    #[schema(value_type = Option<Object>)]
    metadata: Option<serde_json::Value>,
}

impl FrameView {
    pub fn new(frame_id: u64, h: crate::store::record::FrameHeader) -> Self {
        Self { frame_id, robot_id: h.robot_id, timestamp: h.timestamp, pose: h.pose, metadata: h.metadata }
    }
}

pub fn parse_u64(name: &str, v: &str) -> Result<u64, ApiError> {
    v.parse().map_err(|_| ApiError::InvalidArgument(format!("{name} must be a non-negative integer, got '{v}'")))
}

pub fn body_error(status: StatusCode, text: String) -> ApiError {
    if status == StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::TooLarge(text)
    } else {
        ApiError::InvalidArgument(text)
    }
}

pub fn json_error(e: axum::extract::rejection::JsonRejection) -> ApiError {
    body_error(e.status(), e.body_text())
}
