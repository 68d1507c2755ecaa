//! What the loop inspector reads beyond the loops: a session's frames page by page,
//! a frame's thumbnail and the similarity matrix. Both APIs reach these through `tenancy.rs`.
use super::error::ApiError;
use super::service::LoopService;
use crate::inspect::similarity::{self, Similarity};
use crate::store::record::FrameHeader;
use crate::store::Session;
use std::sync::Arc;

/// Most frames one listing returns.
pub const MAX_FRAMES_PER_PAGE: usize = 10_000;

/// One page of frames, and the `after` of the next page (None: the last page).
pub type FramePage = (Vec<(u64, FrameHeader)>, Option<u64>);

impl LoopService {
    pub fn frames(&self, s: &Session, after: Option<u64>, limit: usize) -> Result<FramePage, ApiError> {
        Ok(s.headers_page(after, limit.clamp(1, MAX_FRAMES_PER_PAGE))?)
    }

    /// A frame's thumbnail (JPEG); NotFound says why there is none.
    pub fn thumbnail(&self, s: &Session, frame_id: u64) -> Result<Vec<u8>, ApiError> {
        match s.thumbnail(frame_id)? {
            Some(t) => Ok(t.to_vec()),
            None if s.meta.thumbnails => Err(ApiError::NotFound(format!(
                "frame {frame_id} has no thumbnail (it was sent as a descriptor, or its image could not be shrunk)"
            ))),
            None => Err(ApiError::NotFound(
                "this session keeps no thumbnails (create it with thumbnails: true)".to_string(),
            )),
        }
    }

    /// The similarity matrix of up to `size` frames, computed off the async workers.
    pub async fn similarity(&self, s: Arc<Session>, size: usize) -> Result<Similarity, ApiError> {
        tokio::task::spawn_blocking(move || similarity::matrix(&s, size))
            .await
            .map_err(|e| ApiError::Internal(format!("similarity worker failed: {e}")))?
            .map_err(ApiError::from)
    }
}
