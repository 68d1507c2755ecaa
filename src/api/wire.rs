//! What both transports read the same way from their requests, below both (neither imports
//! the other).
use super::error::ApiError;

/// A loop listing's cursor (`after=`, gRPC's `after`): QUERY-MATCH frame ids of the last loop of
/// the previous page.
pub fn cursor(s: &str) -> Result<(u64, u64), ApiError> {
    s.split_once('-')
        .and_then(|(q, m)| Some((q.parse().ok()?, m.parse().ok()?)))
        .ok_or_else(|| ApiError::InvalidArgument(format!("after must be QUERY-MATCH frame ids, got '{s}'")))
}
