//! The store's rules for what it is given, in one place: session ids (and the one generator),
//! robot ids, a new session's metadata and a new frame's checks against its session.
use super::record::{FrameHeader, SessionMeta};
use super::{NewFrame, NewSession, Session, StoreError, MAX_CLIENT_FRAME_ID};

/// Letters, digits, '-', '_' and '.', with at least one letter or digit ("." and ".." are path
/// names, not ids); a tenant's session is stored as `tenant/id` (the API never lets a client
/// name one with '/').
pub(super) fn valid_session_id(id: &str) -> bool {
    let one = |p: &str| {
        (1..=64).contains(&p.len())
            && p.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
            && p.chars().any(|c| c.is_ascii_alphanumeric())
    };
    match id.split_once('/') {
        None => one(id),
        Some((tenant, id)) => one(tenant) && one(id),
    }
}

/// A session id picked for a request that names none: `s` and the time in hex (the store's and
/// a tenant's, which prefixes it).
pub fn new_session_id() -> String {
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
    format!("s{:x}", now.as_nanos())
}

/// The one robot id rule: why `robot` is not a robot id (1-128 bytes without control
/// characters), or None.
pub fn robot_id_error(robot: &str) -> Option<&'static str> {
    if robot.is_empty() {
        Some("robot_id is required")
    } else if robot.len() > 128 || robot.chars().any(char::is_control) {
        Some("robot_id must be 1-128 bytes without control characters")
    } else {
        None
    }
}

/// A new session's metadata, its id checked (or picked by [`new_session_id`]).
pub(super) fn new_meta(id: Option<String>, new: NewSession) -> Result<SessionMeta, StoreError> {
    let NewSession { name, dim, descriptor_id, storage, default_query, camera, thumbnails, index, model } = new;
    if !(1..=65536).contains(&dim) {
        return Err(StoreError::InvalidArgument(format!("descriptor dimension {dim} out of range 1..=65536")));
    }
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
    let id = id.unwrap_or_else(new_session_id);
    if !valid_session_id(&id) {
        return Err(StoreError::InvalidArgument(format!(
            "session id '{id}' must be 1-64 characters of letters, digits, '-', '_' or '.', with a letter or digit"
        )));
    }
    Ok(SessionMeta {
        id,
        name,
        created: now.as_secs_f64(),
        dim,
        descriptor_id,
        storage,
        default_query,
        camera,
        thumbnails,
        index,
        model,
    })
}

impl NewFrame {
    /// What the frame record holds beside the descriptor.
    pub(super) fn header(&self) -> FrameHeader {
        FrameHeader {
            robot_id: self.robot_id.clone(),
            timestamp: self.timestamp,
            pose: self.pose,
            metadata: self.metadata.clone(),
            idempotency_key: self.idempotency_key.clone(),
        }
    }
}

/// What a frame must be before anything is written (the dimension, ids and fields).
pub(super) fn check_new_frame(s: &Session, f: &NewFrame) -> Result<(), StoreError> {
    if f.descriptor.len() != s.meta.dim {
        return Err(StoreError::InvalidArgument(format!(
            "descriptor has {} values; session '{}' holds {}-d descriptors",
            f.descriptor.len(),
            s.meta.id,
            s.meta.dim
        )));
    }
    if let Some(e) = robot_id_error(&f.robot_id) {
        return Err(StoreError::InvalidArgument(e.into()));
    }
    if !f.timestamp.is_finite() {
        return Err(StoreError::InvalidArgument("timestamp must be a finite number".into()));
    }
    if f.frame_id.is_some_and(|id| id > MAX_CLIENT_FRAME_ID) {
        return Err(StoreError::InvalidArgument(format!("frame_id must be at most {MAX_CLIENT_FRAME_ID}")));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_robot_id_rule_in_bytes_without_control_characters() {
        assert_eq!(robot_id_error(""), Some("robot_id is required"));
        assert_eq!(robot_id_error(&"r".repeat(128)), None);
        assert!(robot_id_error(&"r".repeat(129)).is_some());
        // 64 two-byte characters are 128 bytes; one more is over, in bytes.
        assert_eq!(robot_id_error(&"é".repeat(64)), None);
        assert!(robot_id_error(&"é".repeat(65)).is_some());
        assert!(robot_id_error("robot\n1").is_some());
        assert!(new_session_id().starts_with('s') && valid_session_id(&new_session_id()));
    }
}
