//! The open sled database and whether it can take writes.
//!
//! sled keeps the first I/O error it meets (a full disk, say) and fails every later write with it
//! until the database is opened again; `Store::reopen` does that once space is back, and
//! [`Health`] is what readiness and the write paths read meanwhile.
use super::durability::GroupCommit;
use super::StoreError;
use parking_lot::Mutex;
use std::path::Path;
use std::sync::Arc;

/// Everything that holds the database open: a reopen drops all of it first (sled locks its
/// directory while any handle lives).
pub(crate) struct Disk {
    pub db: sled::Db,
    pub sessions: sled::Tree,
    pub jobs: sled::Tree,
    pub tenants: sled::Tree,
    pub commit: GroupCommit,
}

impl Disk {
    pub fn open(dir: &Path, health: Arc<Health>) -> Result<Self, StoreError> {
        let db = sled::Config::new().path(dir.join("sled")).open()?;
        let sessions = db.open_tree("sessions")?;
        let jobs = db.open_tree("jobs")?;
        let tenants = db.open_tree("tenants")?;
        let commit = GroupCommit::start(db.clone(), health);
        Ok(Self { db, sessions, jobs, tenants, commit })
    }

    /// One small write made durable: whether the disk takes writes now (a flush with nothing
    /// new to write would succeed on a full disk).
    pub fn probe(&self) -> Result<(), StoreError> {
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        self.db.insert(b"loopd/probe", &now.as_nanos().to_le_bytes()[..])?;
        self.db.flush()?;
        Ok(())
    }
}

/// A sled error as a person reads it ("No space left on device (os error 28)", not sled's Debug
/// form of the I/O error).
pub fn describe(e: &sled::Error) -> String {
    match e {
        sled::Error::Io(io) => format!("I/O error: {io}"),
        e => e.to_string(),
    }
}

/// The storage failure writes are refused for, if any (set by the flusher or a failed write,
/// cleared by a successful reopen).
#[derive(Default)]
pub struct Health {
    failure: Mutex<Option<String>>,
}

impl Health {
    pub fn fail(&self, error: &str) {
        let mut f = self.failure.lock();
        if f.is_none() {
            tracing::error!(error, "storage failed: writes are refused until the store is reopened");
        }
        *f = Some(error.to_string());
    }

    pub fn clear(&self) {
        if self.failure.lock().take().is_some() {
            tracing::info!("storage recovered: writes accepted again");
        }
    }

    pub fn failure(&self) -> Option<String> {
        self.failure.lock().clone()
    }

    /// Ok while writes can succeed; else the error a write gets at once (without touching a
    /// database that would fail it anyway).
    pub fn writable(&self) -> Result<(), StoreError> {
        match self.failure() {
            None => Ok(()),
            Some(e) => Err(StoreError::Unavailable(format!(
                "storage failed ({e}); writes are refused until it recovers (retry later)"
            ))),
        }
    }
}
