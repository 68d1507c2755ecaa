//! Reopening the database after a storage failure (a full disk), once it takes writes again,
//! without a restart: the in-memory indexes stay; disk is brought back to what they hold.
use super::disk::Disk;
use super::record::key_frame;
use super::{trees_of, Session, Store, StoreError, Trees};
use std::collections::HashSet;
use std::sync::Arc;
use std::time::Instant;

impl Store {
    /// Drops every handle on the database, opens it again, takes off disk whatever the indexes
    /// do not hold (writes never acknowledged), and proves with a durable write that the disk
    /// takes writes; only then are writes accepted again. Blocking: run it off the executor.
    pub fn reopen(&self) -> Result<(), StoreError> {
        let _admin = self.admin.lock();
        let t = Instant::now();
        let mut disk = self.disk.write();
        let sessions: Vec<Arc<Session>> = self.sessions.read().values().cloned().collect();
        let mut slots: Vec<_> = sessions.iter().map(|s| s.trees.write()).collect();
        slots.iter_mut().for_each(|slot| drop(slot.take()));
        // Joins the flusher: writers still waiting learn that their flush failed.
        drop(disk.take());
        let reopened = Disk::open(&self.dir, self.health.clone()).and_then(|new| {
            let mut dropped = 0;
            for (s, slot) in sessions.iter().zip(slots.iter_mut()) {
                let trees = Trees::open(&new.db, &s.meta.id)?;
                dropped += trees.keep_only_indexed(s)?;
                **slot = Some(trees);
            }
            dropped += self.reconcile_sessions(&new, &sessions)?;
            new.probe()?;
            Ok((new, dropped))
        });
        match reopened {
            Ok((new, dropped)) => {
                *disk = Some(new);
                self.health.clear();
                tracing::info!(dropped, elapsed_ms = t.elapsed().as_millis() as u64, "store reopened");
                Ok(())
            }
            Err(e) => {
                // Every handle on the failed attempt goes, so the next one can open the directory.
                slots.iter_mut().for_each(|slot| drop(slot.take()));
                self.health.fail(&e.to_string());
                Err(e)
            }
        }
    }

    /// Sessions on disk that the store does not hold (a create never acknowledged) are dropped;
    /// sessions it holds get their record back if it is missing. Returns how many were dropped.
    fn reconcile_sessions(&self, disk: &Disk, held: &[Arc<Session>]) -> Result<usize, StoreError> {
        let ids: HashSet<&str> = held.iter().map(|s| s.meta.id.as_str()).collect();
        let mut dropped = 0;
        for key in disk.sessions.iter().keys() {
            let key = key?;
            let id = String::from_utf8_lossy(&key).to_string();
            if !ids.contains(id.as_str()) {
                disk.sessions.remove(&key)?;
                for tree in trees_of(&id) {
                    disk.db.drop_tree(tree)?;
                }
                dropped += 1;
            }
        }
        for s in held {
            if !disk.sessions.contains_key(s.meta.id.as_bytes())? {
                let meta = serde_json::to_vec(&s.meta).map_err(|e| StoreError::Storage(e.to_string()))?;
                disk.sessions.insert(s.meta.id.as_bytes(), meta)?;
            }
        }
        Ok(dropped)
    }
}

impl Trees {
    /// Removes frames (and features, and loops kept for them) the session's index does not
    /// hold: they were written but never acknowledged. Returns how many frames.
    fn keep_only_indexed(&self, s: &Session) -> Result<usize, StoreError> {
        let index = s.index.read();
        let mut dropped = 0;
        for tree in [&self.frames, &self.features, &self.loops] {
            for key in tree.iter().keys() {
                let key = key?;
                // Loop keys begin with their query frame's key.
                if !key.get(..8).and_then(key_frame).is_some_and(|id| index.contains(id)) {
                    tree.remove(&key)?;
                    dropped += usize::from(std::ptr::eq(tree, &self.frames));
                }
            }
        }
        Ok(dropped)
    }
}
