//! Idempotency keys. A client that lost a write's answer (a timeout, a dropped connection, a
//! failover) sends the write again with the same key; when the session holds a frame stored under
//! that key, the write stores nothing and answers that frame's id.
//!
//! The key is part of the frame's record (`FrameHeader::idempotency_key`), so it lasts exactly
//! as long as the frame: written in the same commit, gone with it, found again at start-up. In a
//! cluster the log keeps it too (`loopd_frame_keys`, written in the frame's transaction and
//! looked up under the session row's lock, `pg_writer.rs`), so a write sent again through
//! another node, or after a commit whose answer was lost, finds the first one. A
//! write in flight holds its key: another write with it meanwhile is refused Unavailable (retry
//! later) instead of racing it, and the key is let go only once the first write is searchable
//! or known not stored.
use super::{NewFrame, Session, StoreError};
use std::collections::{HashMap, HashSet};
use std::sync::Arc;

/// Longest idempotency key, in bytes.
pub const MAX_KEY_BYTES: usize = 128;

/// A session's keys: of its stored frames, and of the writes in flight.
#[derive(Default)]
pub(super) struct Keys {
    stored: HashMap<String, u64>,
    pending: HashSet<String>,
}

impl Keys {
    /// `key` names stored frame `id` from now on.
    pub(super) fn stored(&mut self, key: String, id: u64) {
        self.stored.insert(key, id);
    }
}

/// An idempotency key is 1 to 128 visible ASCII characters (a UUID, a robot's sequence number).
pub fn check_key(key: &str) -> Result<(), StoreError> {
    if key.is_empty() || key.len() > MAX_KEY_BYTES || !key.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(StoreError::InvalidArgument(format!(
            "idempotency_key must be 1 to {MAX_KEY_BYTES} visible ASCII characters (got {} bytes)",
            key.len()
        )));
    }
    Ok(())
}

/// What a write's idempotency key says before it runs.
pub(super) enum Claim {
    /// No key: write.
    Unkeyed,
    /// A new key, held for this write until the guard is dropped.
    Held(KeyGuard),
    /// A frame is stored under the key: answer its id, write nothing.
    Stored(u64),
}

/// Holds a key for the write in flight; dropping it lets the key go.
pub(super) struct KeyGuard {
    session: Arc<Session>,
    key: String,
}

impl Drop for KeyGuard {
    fn drop(&mut self) {
        self.session.keys.lock().pending.remove(&self.key);
    }
}

impl Session {
    /// The stored frame `key` names, if any.
    pub fn frame_of_key(&self, key: &str) -> Option<u64> {
        self.keys.lock().stored.get(key).copied()
    }

    /// The claim of a write of `frames` on its idempotency key: a keyed write holds one frame.
    pub(super) fn claim_key(self: &Arc<Self>, frames: &[NewFrame]) -> Result<Claim, StoreError> {
        let Some(first) = frames.iter().find(|f| f.idempotency_key.is_some()) else { return Ok(Claim::Unkeyed) };
        let Some(key) = first.idempotency_key.clone() else { return Ok(Claim::Unkeyed) };
        if frames.len() > 1 {
            return Err(StoreError::InvalidArgument(format!(
                "an idempotency key is for a write of one frame; this one has {}",
                frames.len()
            )));
        }
        check_key(&key)?;
        let stored = {
            let mut keys = self.keys.lock();
            let stored = keys.stored.get(&key).copied();
            if stored.is_none() && !keys.pending.insert(key.clone()) {
                return Err(in_progress(&key));
            }
            stored
        };
        let Some(id) = stored else { return Ok(Claim::Held(KeyGuard { session: self.clone(), key })) };
        // The same frame again (robot and timestamp), or the key reused for another one.
        let (h, _) = self.frame(id)?;
        if h.robot_id != first.robot_id || h.timestamp.to_bits() != first.timestamp.to_bits() {
            return Err(reused(&key, id, &h.robot_id, h.timestamp, first));
        }
        Ok(Claim::Stored(id))
    }
}

/// Another write with `key` has not ended yet.
fn in_progress(key: &str) -> StoreError {
    StoreError::Unavailable(format!("a write with idempotency key '{key}' is in progress; retry later"))
}

/// `key` stored frame `id` of `robot` at `time`, and `f` is another frame.
pub(super) fn reused(key: &str, id: u64, robot: &str, time: f64, f: &NewFrame) -> StoreError {
    StoreError::KeyReused(format!(
        "idempotency key '{key}' stored frame {id} of robot '{robot}' at {time}; this write is of robot '{}' at {}",
        f.robot_id, f.timestamp
    ))
}
