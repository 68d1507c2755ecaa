//! The open sled database and whether it can take writes.
//!
//! sled keeps the first I/O error it meets (a full disk, say) and fails every later write with it
//! until the database is opened again; `Store::reopen` does that once space is back, and
//! [`super::health::Health`] is what readiness and the write paths read meanwhile.
use super::durability::GroupCommit;
use super::health::Health;
use super::StoreError;
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

/// How long an open waits for a lock still held by handles being dropped.
const LOCK_WAIT: std::time::Duration = std::time::Duration::from_secs(5);

/// Opens the database; while its file lock is still held (sled's background I/O of a database
/// this process just dropped can hold it for a moment), tries again for up to LOCK_WAIT. A lock
/// held longer, by another process, fails as before.
fn open_db(path: &Path) -> Result<sled::Db, StoreError> {
    let start = std::time::Instant::now();
    loop {
        match sled::Config::new().path(path).open() {
            // sled reports it as ErrorKind::Other with this text (sled 0.34, config.rs).
            Err(sled::Error::Io(e))
                if e.to_string().contains("could not acquire lock") && start.elapsed() < LOCK_WAIT =>
            {
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            other => return Ok(other?),
        }
    }
}

impl Disk {
    pub fn open(dir: &Path, health: Arc<Health>) -> Result<Self, StoreError> {
        let db = open_db(&dir.join("sled"))?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    #[test]
    fn an_open_waits_for_a_lock_being_released() {
        let dir = tempfile::tempdir().unwrap();
        let held = sled::Config::new().path(dir.path()).open().unwrap();
        let releaser = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(300));
            drop(held);
        });
        let start = Instant::now();
        let db = open_db(dir.path()).expect("opened once the lock was released");
        assert!(start.elapsed() >= Duration::from_millis(250), "it waited for the lock");
        releaser.join().unwrap();
        drop(db);
    }
}
