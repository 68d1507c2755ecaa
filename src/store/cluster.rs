//! `loopd serve --cluster`: sessions and frames live in the replicated PostgreSQL log (`pg.rs`),
//! and this node's sled folder is only its cache of them (dropped at start-up). Any node takes
//! any request: a session is loaded from the log on first use, and brought up to the log's
//! version before each use, so a request through one node sees every frame acknowledged through
//! any other before it arrived (read-after-ack, one round trip, no push between nodes). A frame is
//! acknowledged once its commit reached a synchronous standby, then applied here.
//!
//! Tenants, kept loops (with verdicts) and sequence jobs' records are in the log as well.
use super::loops::LoopRecord;
use super::pg::{Appended, Head, PgLog, Replication};
use super::record::{encode_frame, frame_key, FrameHeader, SessionMeta};
use super::{NewFrame, SearchConfig, Session, SessionInfo, Store, StoreError};
use std::path::Path;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;

/// Frames one read of a session's tail brings at most.
const TAIL_PAGE: i64 = 512;

pub(super) struct Cluster {
    pub(super) log: PgLog,
    /// Why the log did not take writes at the last probe (`Store::probe_log`); None when it did.
    not_writable: parking_lot::Mutex<Option<String>>,
    /// This node's membership and the live members (`owners.rs`).
    pub(super) members: super::owners::Members,
}

tokio::task_local! {
    /// Set when a request was answered from this node's index without confirming the log's
    /// version (see [`tracking_staleness`]).
    static STALE: std::cell::Cell<bool>;
}

/// Runs a request's future and says whether any session it used could not be brought up to the
/// log's version (no writable primary): the APIs flag such answers as stale.
pub async fn tracking_staleness<F: std::future::Future>(request: F) -> (F::Output, bool) {
    let stale = std::cell::Cell::new(false);
    STALE
        .scope(stale, async move {
            let out = request.await;
            (out, STALE.with(|s| s.get()))
        })
        .await
}

impl Store {
    /// Opens `dir` as this node's cache and connects to the cluster's log (`url`: a multi-host
    /// PostgreSQL URL with `target_session_attrs=read-write`), refusing a primary whose commits
    /// do not wait for a synchronous standby unless `replication` says otherwise.
    pub async fn open_cluster(
        dir: &Path,
        url: &str,
        connections: usize,
        replication: Replication,
        search: SearchConfig,
    ) -> Result<Self, StoreError> {
        let log = PgLog::connect(url, connections, replication).await?;
        let tenants = log.tenants().await?;
        let dir = dir.to_path_buf();
        // sled opens and drops its cache with blocking I/O.
        let store = tokio::task::spawn_blocking(move || {
            Self::open_dir(
                &dir,
                search,
                Some(Cluster { log, not_writable: Default::default(), members: Default::default() }),
            )
        })
        .await
        .map_err(|e| StoreError::Storage(format!("opening the cache failed: {e}")))??;
        // The log's tenants replace this node's copy, which `Auth` reads at start.
        store.replace_tenants(&tenants)?;
        Ok(store)
    }

    /// Asks the log whether it takes writes now, waiting at most `within`; readiness reports the
    /// answer until the next probe (the balancer then sends calls to nodes that can write).
    pub async fn probe_log(&self, within: std::time::Duration) {
        let Some(c) = &self.cluster else { return };
        let answer = match tokio::time::timeout(within, c.log.probe()).await {
            Ok(Ok(())) => None,
            Ok(Err(e)) => Some(e.to_string()),
            Err(_) => Some(format!("the cluster database did not answer within {within:?}")),
        };
        *c.not_writable.lock() = answer;
    }

    /// Why this node should not take calls now: its storage refuses writes, or (in a cluster)
    /// the log did not take writes at the last probe.
    pub fn readiness(&self) -> Option<String> {
        if let Some(e) = self.failure() {
            return Some(format!("storage failed ({e})"));
        }
        self.cluster.as_ref()?.not_writable.lock().clone()
    }

    /// Keeps a tenant's record: in a cluster, in the log (then here); else durable in sled.
    pub async fn put_tenant_durable(&self, name: &str, record: &[u8]) -> Result<(), StoreError> {
        if let Some(c) = &self.cluster {
            c.log.put_tenant(name, record).await?;
        }
        self.put_tenant(name, record)?;
        self.durable_records().await
    }

    /// Every tenant's record as of now: in a cluster, the log's (kept here too).
    pub async fn tenants_fresh(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        let Some(c) = &self.cluster else { return self.tenants() };
        let tenants = c.log.tenants().await?;
        self.replace_tenants(&tenants)?;
        Ok(tenants)
    }

    /// The session as of now. In a cluster: loaded on first use, brought up to the log's version
    /// (read-after-ack across nodes), and forgotten here once deleted through another node.
    pub async fn fresh(&self, id: &str) -> Result<Arc<Session>, StoreError> {
        let Some(c) = &self.cluster else { return self.session(id) };
        let head = match c.log.head(id).await {
            Err(StoreError::SessionNotFound(_)) => {
                self.remove_local(id)?;
                return Err(StoreError::SessionNotFound(id.into()));
            }
            // No writable primary: answer from what this node holds (it may lack the frames
            // acknowledged last); writes fail on their own.
            Err(StoreError::Unavailable(why)) => {
                let held = self.session(id).map_err(|_| StoreError::Unavailable(why.clone()))?;
                tracing::warn!(session = id, error = %why, "cluster log unavailable: answering from this node's index");
                let _ = STALE.try_with(|s| s.set(true));
                return Ok(held);
            }
            head => head?,
        };
        let version = head.version;
        let s = self.cached(c, head)?;
        Self::touch(&s);
        self.catch_up(c, &s, version).await?;
        Ok(s)
    }

    /// Every session as of now (see [`Store::fresh`]); with sled, [`Store::list`].
    pub async fn list_fresh(&self) -> Result<Vec<SessionInfo>, StoreError> {
        let Some(c) = &self.cluster else { return Ok(self.list()) };
        let heads = c.log.heads().await?;
        self.drop_deleted(&heads)?;
        for head in heads {
            let version = head.version;
            let s = self.cached(c, head)?;
            match self.catch_up(c, &s, version).await {
                // Deleted since the listing was read.
                Err(StoreError::SessionNotFound(_)) => {}
                r => r?,
            }
        }
        Ok(self.list())
    }

    /// Every session's id and frame count: in a cluster the log's, sessions this node has not
    /// loaded included (a tenant's frame limit counts them all); with sled, this node's.
    pub async fn frame_counts(&self) -> Result<Vec<(String, u64)>, StoreError> {
        match &self.cluster {
            Some(c) => c.log.frame_counts().await,
            None => Ok(self.list().into_iter().map(|s| (s.meta.id, s.frames as u64)).collect()),
        }
    }

    /// Forgets the sessions held here that the log's `heads` lack (deleted through another node).
    pub(super) fn drop_deleted(&self, heads: &[Head]) -> Result<(), StoreError> {
        let gone: Vec<String> = {
            let held = self.sessions.read();
            held.keys().filter(|id| !heads.iter().any(|h| &h.meta.id == *id)).cloned().collect()
        };
        for id in gone {
            self.remove_local(&id)?;
        }
        Ok(())
    }

    /// In a cluster, this node's copy of a session's kept loops becomes the log's (before a
    /// listing or an export); nothing to do with sled.
    pub async fn fresh_loops(&self, id: &str) -> Result<(), StoreError> {
        let Some(c) = &self.cluster else { return Ok(()) };
        let s = self.session(id)?;
        match c.log.loops(&s.meta.id, s.tbl).await {
            Ok(loops) => self.note(s.replace_loops(&loops)),
            // No writable primary: the copy held here answers, flagged stale.
            Err(StoreError::Unavailable(why)) => {
                tracing::warn!(session = id, error = %why, "cluster log unavailable: listing this node's copy of the loops");
                let _ = STALE.try_with(|s| s.set(true));
                Ok(())
            }
            Err(e) => Err(e),
        }
    }

    pub(super) async fn create_in_cluster(&self, c: &Cluster, meta: SessionMeta) -> Result<SessionMeta, StoreError> {
        let tbl = c.log.create_session(&meta).await?;
        self.cached(c, Head { meta: meta.clone(), tbl, version: 0 })?;
        Ok(meta)
    }

    pub(super) async fn delete_in_cluster(&self, c: &Cluster, id: &str) -> Result<(), StoreError> {
        let deleted = c.log.delete_session(id).await;
        if matches!(deleted, Ok(()) | Err(StoreError::SessionNotFound(_))) {
            self.remove_local(id)?;
        }
        deleted
    }

    /// Appends to the log (acknowledged once on a synchronous standby), then applies here. The
    /// loops answered for the frames are kept on this node only.
    pub(super) async fn add_in_cluster(
        &self,
        c: &Cluster,
        s: &Arc<Session>,
        frames: Vec<NewFrame>,
        loops: impl FnOnce(&[u64]) -> Vec<LoopRecord>,
    ) -> Result<Vec<u64>, StoreError> {
        // The loops are made for the frames' positions (their ids are assigned in the log's
        // transaction, which keeps them with the frames).
        let positions: Vec<u64> = (0..frames.len() as u64).collect();
        let keep = loops(&positions).into_iter().map(|l| (l.query_frame as usize, l)).collect();
        let appended = c.log.append_keeping(&s.meta, &frames, keep).await?;
        // Acknowledged from here on: a failure below leaves the frames to the next catch-up.
        if let Err(e) = self.apply_own(c, s, &frames, &appended).await {
            tracing::warn!(session = %s.meta.id, error = %e, "frames stored in the cluster, not yet applied here");
        }
        Ok(appended.ids)
    }

    /// Applies a batch this node appended: from memory when it follows what is applied here,
    /// else by reading the log's tail (which holds it).
    async fn apply_own(
        &self,
        c: &Cluster,
        s: &Arc<Session>,
        frames: &[NewFrame],
        appended: &Appended,
    ) -> Result<(), StoreError> {
        let mut applied = s.applied.lock().await;
        let first = appended.version - frames.len() as i64;
        if *applied == first {
            for (f, &id) in frames.iter().zip(&appended.ids) {
                let header = f.header();
                let record = encode_frame(&header, &f.descriptor, s.meta.storage);
                let extras = (f.features.as_deref(), f.thumbnail.as_deref());
                self.note(s.apply(id, &record, &header, &f.descriptor, extras))?;
            }
            *applied = appended.version;
            return Ok(());
        }
        drop(applied);
        self.catch_up(c, s, appended.version).await
    }

    /// Applies the log's frames after what this node holds, in `seq` order, until `version`.
    pub(super) async fn catch_up(&self, c: &Cluster, s: &Arc<Session>, version: i64) -> Result<(), StoreError> {
        let mut applied = s.applied.lock().await;
        if *applied >= version {
            return Ok(());
        }
        // Pages keep a cold load's memory bounded (features can be tens of KB a frame).
        while *applied < version {
            let frames = match c.log.tail(&s.meta.id, s.tbl, *applied, TAIL_PAGE).await {
                Err(StoreError::SessionNotFound(id)) => {
                    drop(applied);
                    self.remove_local(&id)?;
                    return Err(StoreError::SessionNotFound(id));
                }
                frames => frames?,
            };
            if frames.is_empty() {
                break;
            }
            for f in frames {
                let extras = (f.features.as_deref(), f.thumbnail.as_deref());
                self.note(s.apply(f.frame_id, &f.record, &f.header, &f.descriptor, extras))?;
                *applied = f.seq;
            }
        }
        Ok(())
    }

    /// The session held here for the log's `head`: the one already cached, or a new, empty one
    /// in place of a stale one (deleted and created again through another node, or read from a
    /// primary that has since been replaced: it may hold frames the new one lacks).
    pub(super) fn cached(&self, c: &Cluster, head: Head) -> Result<Arc<Session>, StoreError> {
        let epoch = c.log.epoch();
        let current = |store: &Self| {
            let held = store.sessions.read().get(&head.meta.id).cloned();
            held.filter(|s| s.tbl == head.tbl && s.epoch == epoch)
        };
        if let Some(s) = current(self) {
            return Ok(s);
        }
        let _admin = self.admin.lock();
        // Another request may have loaded it meanwhile.
        if let Some(s) = current(self) {
            return Ok(s);
        }
        self.remove_locked(&head.meta.id)?;
        let disk = self.disk()?;
        let mut session = Session::load(&disk.db, head.meta.clone(), self.search)?;
        (session.tbl, session.epoch) = (head.tbl, epoch);
        let meta = serde_json::to_vec(&head.meta).map_err(|e| StoreError::Storage(e.to_string()))?;
        self.note(disk.sessions.insert(head.meta.id.as_bytes(), meta))?;
        let s = Arc::new(session);
        self.sessions.write().insert(head.meta.id.clone(), s.clone());
        Ok(s)
    }
}

/// A frame's local features and thumbnail, if it has them.
type Extras<'a> = (Option<&'a [u8]>, Option<&'a [u8]>);

impl Session {
    /// Puts a frame from the log into this node's cache and index (not flushed: the log is the
    /// durable copy).
    /// `record` is the frame as sled stores it (the log keeps the same bytes).
    fn apply(
        &self,
        id: u64,
        record: &[u8],
        header: &FrameHeader,
        descriptor: &[f32],
        extras: Extras,
    ) -> Result<(), StoreError> {
        let (features, thumbnail) = extras;
        let trees = self.trees()?;
        trees.frames.insert(frame_key(id), record)?;
        if let Some(features) = features {
            trees.features.insert(frame_key(id), features)?;
        }
        if let Some(thumbnail) = thumbnail {
            trees.thumbs.insert(frame_key(id), thumbnail)?;
        }
        self.index.write().push(id, &header.robot_id, header.timestamp, header.pose, descriptor);
        self.next_id.fetch_max(id.saturating_add(1), Relaxed);
        self.bytes.fetch_add((8 + record.len()) as u64, Relaxed);
        Ok(())
    }
}
