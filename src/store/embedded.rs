//! The sled backend: sessions, frames and records in this node's sled database, acknowledged by
//! its group commit.
use super::cluster_jobs::LoggedJob;
use super::keys::KeyGuard;
use super::loops::{KeptLoops, LoopRecord, Verdict};
use super::operations::Operations;
use super::owners::{ClusterView, Membership};
use super::record::SessionMeta;
use super::{durability, NewFrame, Session, SessionInfo, Store, StoreError};
use std::sync::Arc;

pub(super) struct Sled;

impl Operations for Sled {
    fn sled_is_cache(&self) -> bool {
        false
    }

    async fn create_session(&self, store: &Store, meta: SessionMeta) -> Result<SessionMeta, StoreError> {
        {
            let _admin = store.admin.lock();
            let disk = store.disk()?;
            if store.sessions.read().contains_key(&meta.id) {
                return Err(StoreError::SessionExists(meta.id));
            }
            let session = Session::load(
                &disk.db,
                meta.clone(),
                store.search,
                &store.graph_dir(),
                &store.rows_dir(),
                super::Keep::Fresh,
            )?;
            store
                .note(disk.sessions.insert(meta.id.as_bytes(), serde_json::to_vec(&meta).expect("meta serialises")))?;
            store.sessions.write().insert(meta.id.clone(), Arc::new(session));
        }
        if let Err(e) = store.durable().await {
            // Not acknowledged: the session goes (a reopen also drops it from disk if it is there).
            store.sessions.write().remove(&meta.id);
            if let Ok(disk) = store.disk() {
                let _ = disk.sessions.remove(meta.id.as_bytes());
            }
            return Err(e);
        }
        Ok(meta)
    }

    async fn delete_session(&self, store: &Store, id: &str) -> Result<(), StoreError> {
        if !store.remove_local(id)? {
            return Err(StoreError::SessionNotFound(id.into()));
        }
        store.durable().await
    }

    async fn add_frames(
        &self,
        store: &Store,
        s: &Arc<Session>,
        prepared: Vec<NewFrame>,
        loops: KeptLoops,
        key: Option<KeyGuard>,
    ) -> Result<Vec<u64>, StoreError> {
        let written = store.note(Store::write_frames(s, &prepared));
        let (written, sizes) = written?;
        if let Err(e) = store.note(s.write_loops(&super::loops::with_ids(loops, &written))) {
            for &id in &written {
                let _ = s.remove(id);
            }
            s.settle(&written);
            return Err(e);
        }
        // No await between the inserts and this: the publish is queued with them.
        let (session, ids) = (s.clone(), written.clone());
        let publish: durability::AfterFlush = Box::new(move |flushed| match flushed {
            Ok(()) => {
                // Searchable once durable: a match never points at a frame that could still vanish.
                let mut index = session.index.write();
                session.publish(&mut index, &prepared, &ids, &sizes);
                drop(index);
                let mut keys = session.keys.lock();
                for (f, &id) in prepared.iter().zip(&ids) {
                    if let Some(k) = &f.idempotency_key {
                        keys.stored(k.clone(), id);
                    }
                }
                drop(keys);
                // The key goes once its frame is searchable (here) or known not stored (below),
                // even when the request waiting for it was dropped.
                drop(key);
            }
            Err(_) => {
                // Not acknowledged: take the frames back so they do not reappear after a restart
                // (if the database fails this too, a reopen drops what the index does not hold).
                for &id in &ids {
                    let _ = session.remove(id);
                }
                session.settle(&ids);
                drop(key);
            }
        });
        let flushed = store.disk()?.commit.durable_then(Some(publish));
        flushed.await.map_err(super::not_durable)?;
        Ok(written)
    }

    async fn keep_loops(&self, store: &Store, s: &Arc<Session>, loops: Vec<LoopRecord>) -> Result<(), StoreError> {
        store.health.writable()?;
        store.keep_loops_here(s, loops)?;
        store.durable().await
    }

    async fn set_verdict(
        &self,
        store: &Store,
        s: &Arc<Session>,
        query: u64,
        matched: u64,
        verdict: Verdict,
    ) -> Result<LoopRecord, StoreError> {
        store.health.writable()?;
        let record = store.set_verdict_here(s, query, matched, verdict)?;
        store.durable().await?;
        Ok(record)
    }

    async fn fresh(&self, store: &Store, id: &str) -> Result<Arc<Session>, StoreError> {
        store.session(id)
    }

    async fn list_fresh(&self, store: &Store) -> Result<Vec<SessionInfo>, StoreError> {
        Ok(store.list())
    }

    async fn frame_counts(&self, store: &Store) -> Result<Vec<(String, u64)>, StoreError> {
        Ok(store.list().into_iter().map(|s| (s.meta.id, s.frames as u64)).collect())
    }

    async fn fresh_loops(&self, _: &Store, _: &str) -> Result<(), StoreError> {
        Ok(())
    }

    async fn put_tenant(&self, _: &str, _: &[u8]) -> Result<(), StoreError> {
        // This node's copy is the record.
        Ok(())
    }

    async fn tenants_fresh(&self, store: &Store) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        store.tenants()
    }

    async fn job_number(&self) -> Result<Option<u64>, StoreError> {
        Ok(None)
    }

    async fn keep_job(&self, store: &Store, id: &str, _: u64, record: &[u8], _: usize) -> Result<(), StoreError> {
        store.put_job(id, record)
    }

    async fn logged_job(&self, _: &str) -> Result<Option<LoggedJob>, StoreError> {
        Ok(None)
    }

    async fn interrupt_logged_jobs(&self) {}

    fn not_writable(&self) -> Option<String> {
        None
    }

    async fn probe(&self, _: std::time::Duration) {}

    fn join_members(&self, _: Membership) {}

    async fn follow_members(&self, _: &Store) -> Result<(), StoreError> {
        Ok(())
    }

    fn cluster_view(&self, _: &Store) -> Option<ClusterView> {
        None
    }

    async fn leave_members(&self) {}
}
