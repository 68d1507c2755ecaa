//! `loopd serve --cluster`: sessions and frames live in the replicated PostgreSQL log (`pg.rs`),
//! and this node's sled folder is only its cache of them (dropped at start-up). Any node takes
//! any request: a session is loaded from the log on first use, and brought up to the log's
//! version before each use, so a request through one node sees every frame acknowledged through
//! any other before it arrived (read-after-ack, one round trip, no push between nodes). A frame is
//! acknowledged once its commit reached a synchronous standby, then applied here.
//!
//! Tenants, kept loops (with verdicts) and sequence jobs' records are in the log as well.
use super::cluster_jobs::LoggedJob;
use super::keys::KeyGuard;
use super::loops::{KeptLoops, LoopRecord, Verdict};
use super::operations::Operations;
use super::owners::{owners, ClusterView, HeldSession, Membership};
use super::pg::{Appended, Head, LogConfig, PgLog};
use super::record::{encode_frame, frame_key, FrameHeader, SessionMeta};
use super::{NewFrame, Session, SessionInfo, Store, StoreError};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;

/// Frames one read of a session's tail brings at most.
const TAIL_PAGE: i64 = 512;

/// The cluster backend: the replicated log, its last probe and this node's membership.
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

impl Cluster {
    /// Connects to the cluster's log (`url`: a multi-host PostgreSQL URL with
    /// `target_session_attrs=read-write`), refusing a primary whose commits do not wait for a
    /// synchronous standby unless `replication` says otherwise; with the log's tenants.
    pub(super) async fn connect(url: &str, config: LogConfig) -> Result<(Self, Vec<(String, Vec<u8>)>), StoreError> {
        let log = PgLog::connect(url, config).await?;
        let tenants = log.tenants().await?;
        Ok((Cluster { log, not_writable: Default::default(), members: Default::default() }, tenants))
    }
}

impl Cluster {
    /// Unavailable at once while the last probe found no writable primary (a node cut off from
    /// the database, a failover under way): a write would only wait out the log's deadline, and
    /// this session's later writes behind it. The balancer has stopped sending writes here by
    /// then (readiness); a client that reached this node directly gets the reason.
    fn writable(&self) -> Result<(), StoreError> {
        match self.not_writable.lock().clone() {
            None => Ok(()),
            Some(why) => Err(StoreError::Unavailable(format!("not ready: {why}"))),
        }
    }
}

impl Store {
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
}

/// Marks the request being answered as stale (see [`tracking_staleness`]).
fn mark_stale() {
    let _ = STALE.try_with(|s| s.set(true));
}

impl Operations for Cluster {
    fn sled_is_cache(&self) -> bool {
        true
    }

    async fn create_session(&self, store: &Store, meta: SessionMeta) -> Result<SessionMeta, StoreError> {
        self.writable()?;
        let tbl = self.log.create_session(&meta).await?;
        self.cached(store, Head { meta: meta.clone(), tbl, version: 0 })?;
        Ok(meta)
    }

    async fn delete_session(&self, store: &Store, id: &str) -> Result<(), StoreError> {
        self.writable()?;
        let deleted = self.log.delete_session(id).await;
        if matches!(deleted, Ok(()) | Err(StoreError::SessionNotFound(_))) {
            store.remove_local(id)?;
        }
        deleted
    }

    /// Appends to the log (acknowledged once on a synchronous standby, the loops in the same
    /// transaction), then applies here.
    async fn add_frames(
        &self,
        store: &Store,
        s: &Arc<Session>,
        frames: Vec<NewFrame>,
        loops: KeptLoops,
        key: Option<KeyGuard>,
    ) -> Result<Vec<u64>, StoreError> {
        self.writable()?;
        let appended = self.log.append_keeping(&s.meta, &frames, loops).await?;
        if appended.replayed {
            // An earlier write stored it (through this node or another): brought here, not again.
            if let Err(e) = self.catch_up(store, s, appended.version).await {
                tracing::warn!(session = %s.meta.id, error = %e, "a replayed frame is in the cluster, not yet here");
            }
            return Ok(appended.ids);
        }
        // Acknowledged from here on: a failure below leaves the frames to the next catch-up.
        if let Err(e) = self.apply_own(store, s, &frames, &appended).await {
            tracing::warn!(session = %s.meta.id, error = %e, "frames stored in the cluster, not yet applied here");
        }
        // The key goes once its frame is applied here (its key noted with it) or left to catch-up.
        drop(key);
        Ok(appended.ids)
    }

    async fn keep_loops(&self, _: &Store, s: &Arc<Session>, loops: Vec<LoopRecord>) -> Result<(), StoreError> {
        self.writable()?;
        self.log.keep_loops(s.tbl, &loops).await
    }

    async fn set_verdict(
        &self,
        _: &Store,
        s: &Arc<Session>,
        query: u64,
        matched: u64,
        verdict: Verdict,
    ) -> Result<LoopRecord, StoreError> {
        self.writable()?;
        self.log.set_verdict((&s.meta.id, s.tbl), query, matched, &verdict).await
    }

    /// Loaded on first use, brought up to the log's version (read-after-ack across nodes), and
    /// forgotten here once deleted through another node.
    async fn fresh(&self, store: &Store, id: &str) -> Result<Arc<Session>, StoreError> {
        let head = match self.log.head(id).await {
            Err(StoreError::SessionNotFound(_)) => {
                store.remove_local(id)?;
                return Err(StoreError::SessionNotFound(id.into()));
            }
            // No writable primary: answer from what this node holds (it may lack the frames
            // acknowledged last); writes fail on their own.
            Err(StoreError::Unavailable(why)) => {
                let held = store.session(id).map_err(|_| StoreError::Unavailable(why.clone()))?;
                tracing::warn!(session = id, error = %why, "cluster log unavailable: answering from this node's index");
                mark_stale();
                return Ok(held);
            }
            head => head?,
        };
        let version = head.version;
        let s = self.cached(store, head)?;
        Store::touch(&s);
        self.catch_up(store, &s, version).await?;
        Ok(s)
    }

    async fn list_fresh(&self, store: &Store) -> Result<Vec<SessionInfo>, StoreError> {
        let heads = self.log.heads().await?;
        store.drop_deleted(&heads)?;
        for head in heads {
            let version = head.version;
            let s = self.cached(store, head)?;
            match self.catch_up(store, &s, version).await {
                // Deleted since the listing was read.
                Err(StoreError::SessionNotFound(_)) => {}
                r => r?,
            }
        }
        Ok(store.list())
    }

    /// The log's counts: sessions this node has not loaded included (a tenant's frame limit
    /// counts them all).
    async fn frame_counts(&self, _: &Store) -> Result<Vec<(String, u64)>, StoreError> {
        self.log.frame_counts().await
    }

    /// This node's copy of a session's kept loops becomes the log's (before a listing or an
    /// export).
    async fn fresh_loops(&self, store: &Store, id: &str) -> Result<(), StoreError> {
        let s = store.session(id)?;
        match self.log.loops(&s.meta.id, s.tbl).await {
            Ok(loops) => store.note(s.replace_loops(&loops)),
            // No writable primary: the copy held here answers, flagged stale.
            Err(StoreError::Unavailable(why)) => {
                tracing::warn!(session = id, error = %why, "cluster log unavailable: listing this node's copy of the loops");
                mark_stale();
                Ok(())
            }
            Err(e) => Err(e),
        }
    }

    async fn put_tenant(&self, name: &str, record: &[u8]) -> Result<(), StoreError> {
        self.writable()?;
        self.log.put_tenant(name, record).await
    }

    async fn tenants_fresh(&self, store: &Store) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        let tenants = self.log.tenants().await?;
        store.replace_tenants(&tenants)?;
        Ok(tenants)
    }

    async fn job_number(&self) -> Result<Option<u64>, StoreError> {
        self.log.next_job_number().await.map(Some)
    }

    /// In the log under this node's name (a new job there drops the oldest finished beyond
    /// `kept`).
    async fn keep_job(&self, _: &Store, id: &str, n: u64, record: &[u8], kept: usize) -> Result<(), StoreError> {
        self.log.put_job(id, n, &self.node_name(), record, kept).await
    }

    async fn logged_job(&self, id: &str) -> Result<Option<LoggedJob>, StoreError> {
        self.logged(id).await
    }

    async fn interrupt_logged_jobs(&self) {
        match self.log.interrupt_jobs(&self.node_name()).await {
            Ok(0) => {}
            Ok(n) => tracing::warn!(jobs = n, "jobs interrupted by this node's restart"),
            Err(e) => tracing::warn!(error = %e, "jobs of this node's earlier run not marked interrupted"),
        }
    }

    fn not_writable(&self) -> Option<String> {
        self.not_writable.lock().clone()
    }

    /// Readiness reports the answer until the next probe (the balancer then sends calls to
    /// nodes that can write).
    async fn probe(&self, within: std::time::Duration) {
        let answer = match tokio::time::timeout(within, self.log.probe()).await {
            Ok(Ok(())) => None,
            Ok(Err(e)) => Some(e.to_string()),
            Err(_) => Some(format!("the cluster database did not answer within {within:?}")),
        };
        *self.not_writable.lock() = answer;
    }

    fn join_members(&self, me: Membership) {
        self.members.join(me);
    }

    async fn follow_members(&self, store: &Store) -> Result<(), StoreError> {
        self.follow(store).await
    }

    fn cluster_view(&self, store: &Store) -> Option<ClusterView> {
        self.view(store)
    }

    async fn leave_members(&self) {
        let Some(me) = self.members.me() else { return };
        if let Err(e) = self.log.leave(&me.node).await {
            tracing::warn!(error = %e, "could not leave the cluster's members (they drop this node after the ttl)");
        }
    }
}

impl Cluster {
    /// One round: heartbeat, read the live members, load and catch up the sessions this node
    /// owns, and drop the ones it neither owns nor used within `evict_idle`.
    pub(super) async fn follow(&self, store: &Store) -> Result<(), StoreError> {
        let Some(me) = self.members.me() else { return Ok(()) };
        self.log.heartbeat(&me.node).await?;
        let live = self.log.members(me.ttl).await?;
        self.members.set_live(live.clone());
        let heads = self.log.heads().await?;
        let owned = |id: &str| owners(id, &live, me.owners).contains(&me.node.as_str());
        for head in heads.iter().filter(|h| owned(&h.meta.id)) {
            let (id, version) = (head.meta.id.clone(), head.version);
            let s = self.cached(store, Head { meta: head.meta.clone(), tbl: head.tbl, version })?;
            match self.catch_up(store, &s, version).await {
                Ok(()) | Err(StoreError::SessionNotFound(_)) => {}
                Err(e) => tracing::warn!(session = %id, error = %e, "an owned session not brought up to date"),
            }
        }
        store.drop_deleted(&heads)?;
        if let Some(idle) = me.evict_idle {
            let held: Vec<String> = store.sessions.read().keys().cloned().collect();
            for id in held.iter().filter(|id| !owned(id)) {
                store.evict_if_idle(id, idle)?;
            }
        }
        Ok(())
    }

    /// This node's view of the cluster.
    pub(super) fn view(&self, store: &Store) -> Option<ClusterView> {
        let me = self.members.me()?;
        let members = self.members.live();
        let mut held: Vec<HeldSession> = store
            .sessions
            .read()
            .values()
            .map(|s| HeldSession {
                session: s.meta.id.clone(),
                frames: s.index.read().len(),
                owner: owners(&s.meta.id, &members, me.owners).contains(&me.node.as_str()),
            })
            .collect();
        held.sort_by(|a, b| a.session.cmp(&b.session));
        Some(ClusterView { node: me.node, owners: me.owners, members, held })
    }

    /// Job `id` as the log holds it, and whether its runner may still be running it.
    pub(super) async fn logged(&self, id: &str) -> Result<Option<LoggedJob>, StoreError> {
        let me = self.members.me();
        // A runner rewrites a running job's record every few seconds: one written within the
        // member ttl (and twice the rewrite period) is alive even if a late heartbeat dropped
        // its node from this node's view for a round. "Interrupted" is final; it must not flap.
        let ttl = me.as_ref().map_or(std::time::Duration::from_secs(5), |m| m.ttl);
        let Some(job) = self.log.job(id, ttl.max(super::cluster_jobs::JOB_REWRITE * 2)).await? else { return Ok(None) };
        let live = self.members.live();
        let predecessor = me.is_some_and(|m| m.node == job.node);
        // Before the first members round the list is empty: the runner is not known to be gone.
        let member = live.is_empty() || live.contains(&job.node);
        let runner_alive = !predecessor && (member || job.recent);
        Ok(Some(LoggedJob { record: job.record, runner_alive }))
    }

    /// This node's name among the members (empty before it joined).
    fn node_name(&self) -> String {
        self.members.me().map(|m| m.node).unwrap_or_default()
    }

    /// Applies a batch this node appended: from memory when it follows what is applied here,
    /// else by reading the log's tail (which holds it).
    async fn apply_own(
        &self,
        store: &Store,
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
                store.note(s.apply(id, &record, &header, &f.descriptor, extras))?;
            }
            *applied = appended.version;
            return Ok(());
        }
        drop(applied);
        self.catch_up(store, s, appended.version).await
    }

    /// Applies the log's frames after what this node holds, in `seq` order, until `version`.
    pub(super) async fn catch_up(&self, store: &Store, s: &Arc<Session>, version: i64) -> Result<(), StoreError> {
        let mut applied = s.applied.lock().await;
        if *applied >= version {
            return Ok(());
        }
        // Pages keep a cold load's memory bounded (features can be tens of KB a frame).
        while *applied < version {
            let frames = match self.log.tail(&s.meta.id, s.tbl, *applied, TAIL_PAGE).await {
                Err(StoreError::SessionNotFound(id)) => {
                    drop(applied);
                    store.remove_local(&id)?;
                    return Err(StoreError::SessionNotFound(id));
                }
                frames => frames?,
            };
            if frames.is_empty() {
                break;
            }
            for f in frames {
                let extras = (f.features.as_deref(), f.thumbnail.as_deref());
                store.note(s.apply(f.frame_id, &f.record, &f.header, &f.descriptor, extras))?;
                *applied = f.seq;
            }
        }
        Ok(())
    }

    /// The session held here for the log's `head`: the one already cached, or a new, empty one
    /// in place of a stale one (deleted and created again through another node, or read from a
    /// primary that has since been replaced: it may hold frames the new one lacks).
    pub(super) fn cached(&self, store: &Store, head: Head) -> Result<Arc<Session>, StoreError> {
        let epoch = self.log.epoch();
        let current = |store: &Store| {
            let held = store.sessions.read().get(&head.meta.id).cloned();
            held.filter(|s| s.tbl == head.tbl && s.epoch == epoch)
        };
        if let Some(s) = current(store) {
            return Ok(s);
        }
        let _admin = store.admin.lock();
        // Another request may have loaded it meanwhile.
        if let Some(s) = current(store) {
            return Ok(s);
        }
        store.remove_locked(&head.meta.id)?;
        let disk = store.disk()?;
        let mut session = Session::load(
            &disk.db,
            head.meta.clone(),
            store.search,
            &store.graph_dir(),
            &store.rows_dir(),
            super::Keep::No,
        )?;
        (session.tbl, session.epoch) = (head.tbl, epoch);
        let meta = serde_json::to_vec(&head.meta).map_err(|e| StoreError::Storage(e.to_string()))?;
        store.note(disk.sessions.insert(head.meta.id.as_bytes(), meta))?;
        let s = Arc::new(session);
        store.sessions.write().insert(head.meta.id.clone(), s.clone());
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
        if let Some(key) = &header.idempotency_key {
            self.keys.lock().stored(key.clone(), id);
        }
        self.next_id.fetch_max(id.saturating_add(1), Relaxed);
        self.bytes.fetch_add((8 + record.len()) as u64, Relaxed);
        Ok(())
    }
}
