//! The operations whose truth differs between the backends (`backend.rs` chooses one at open):
//! sled on this node (`embedded.rs`), or the cluster's replicated log with this node's sled folder
//! as its cache (`cluster.rs`). Both keep the session's index and this node's sled trees; what
//! differs is where a write is acknowledged (sled's group commit, or the log's synchronous
//! standby) and whether a read first catches up with other nodes.
use super::cluster_jobs::LoggedJob;
use super::keys::KeyGuard;
use super::loops::{KeptLoops, LoopRecord, Verdict};
use super::owners::{ClusterView, Membership};
use super::record::SessionMeta;
use super::{NewFrame, Session, SessionInfo, Store, StoreError};
use std::sync::Arc;

/// The operations whose truth differs between the backends. `store` is the store the backend
/// serves: its sessions, indexes and sled trees.
pub(super) trait Operations {
    /// Whether this node's sled folder only caches what lives elsewhere (dropped at start).
    fn sled_is_cache(&self) -> bool;

    async fn create_session(&self, store: &Store, meta: SessionMeta) -> Result<SessionMeta, StoreError>;

    async fn delete_session(&self, store: &Store, id: &str) -> Result<(), StoreError>;

    /// Adds checked, normalised frames, all or none, with the loops answered for them (each by
    /// its query frame's position in `frames`); acknowledged once durable, ids in order.
    async fn add_frames(
        &self,
        store: &Store,
        s: &Arc<Session>,
        frames: Vec<NewFrame>,
        loops: KeptLoops,
        key: Option<KeyGuard>,
    ) -> Result<Vec<u64>, StoreError>;

    async fn keep_loops(&self, store: &Store, s: &Arc<Session>, loops: Vec<LoopRecord>) -> Result<(), StoreError>;

    async fn set_verdict(
        &self,
        store: &Store,
        s: &Arc<Session>,
        query: u64,
        matched: u64,
        verdict: Verdict,
    ) -> Result<LoopRecord, StoreError>;

    /// The session as of now (every frame acknowledged through any node applied here).
    async fn fresh(&self, store: &Store, id: &str) -> Result<Arc<Session>, StoreError>;

    /// Every session as of now.
    async fn list_fresh(&self, store: &Store) -> Result<Vec<SessionInfo>, StoreError>;

    /// Every session's id and frame count, those this node does not hold included.
    async fn frame_counts(&self, store: &Store) -> Result<Vec<(String, u64)>, StoreError>;

    /// This node's copy of a session's kept loops brought up to date.
    async fn fresh_loops(&self, store: &Store, id: &str) -> Result<(), StoreError>;

    /// Keeps a tenant's record where the truth is, before this node's copy is written.
    async fn put_tenant(&self, name: &str, record: &[u8]) -> Result<(), StoreError>;

    /// Every tenant's record as of now.
    async fn tenants_fresh(&self, store: &Store) -> Result<Vec<(String, Vec<u8>)>, StoreError>;

    /// A job number no node has given, where nodes share the numbering (None: this node numbers
    /// its own).
    async fn job_number(&self) -> Result<Option<u64>, StoreError>;

    async fn keep_job(&self, store: &Store, id: &str, n: u64, record: &[u8], kept: usize) -> Result<(), StoreError>;

    /// A job as the shared log holds it (None where there is none).
    async fn logged_job(&self, id: &str) -> Result<Option<LoggedJob>, StoreError>;

    /// Marks the jobs this node ran before it started again as interrupted, where other nodes
    /// would read them.
    async fn interrupt_logged_jobs(&self);

    /// Why writes cannot reach the truth now, as of the last probe.
    fn not_writable(&self) -> Option<String>;

    /// Asks whether writes reach the truth now, waiting at most `within`.
    async fn probe(&self, within: std::time::Duration);

    fn join_members(&self, me: Membership);

    /// One round of membership: heartbeat, members, owned sessions loaded, idle ones evicted.
    async fn follow_members(&self, store: &Store) -> Result<(), StoreError>;

    fn cluster_view(&self, store: &Store) -> Option<ClusterView>;

    async fn leave_members(&self);
}
