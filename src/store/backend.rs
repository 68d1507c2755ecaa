//! Where the truth of sessions, frames, kept loops, tenants and jobs lives, chosen once when the
//! store opens: [`Backend`] holds the one chosen, sled on this node (`embedded.rs`) or the cluster's
//! replicated PostgreSQL log with this node's sled folder as its cache (`cluster.rs`), and
//! dispatches the operations whose truth differs (`operations.rs`) to it: the shape of qdrant's
//! `Shard` and `ShardOperation`. The store's own methods never ask which backend they run on.
use super::cluster::Cluster;
use super::cluster_jobs::LoggedJob;
use super::embedded::Sled;
use super::loops::{LoopRecord, Verdict};
use super::owners::{ClusterView, Membership};
use super::pg::LogConfig;
use super::{SearchConfig, Session, SessionInfo, Store, StoreError};
use std::path::Path;
use std::sync::Arc;

/// The backend a store was opened with.
pub(super) enum Backend {
    Sled(Sled),
    Cluster(Box<Cluster>),
}

/// Calls an `Operations` method on the backend chosen at start (`dispatch!(self, op(args))`,
/// `.await` added for async ones with `dispatch!(async self, ...)`).
macro_rules! dispatch {
    (async $store:ident, $op:ident($($arg:expr),*)) => {
        match &$store.backend {
            $crate::store::backend::Backend::Sled(b) => $crate::store::operations::Operations::$op(b, $($arg),*).await,
            $crate::store::backend::Backend::Cluster(b) => {
                $crate::store::operations::Operations::$op(&**b, $($arg),*).await
            }
        }
    };
    ($store:ident, $op:ident($($arg:expr),*)) => {
        match &$store.backend {
            $crate::store::backend::Backend::Sled(b) => $crate::store::operations::Operations::$op(b, $($arg),*),
            $crate::store::backend::Backend::Cluster(b) => $crate::store::operations::Operations::$op(&**b, $($arg),*),
        }
    };
}
pub(super) use dispatch;

impl Store {
    /// Opens `dir` as this node's cache and connects to the cluster's log (`url`: a multi-host
    /// PostgreSQL URL with `target_session_attrs=read-write`), refusing a primary whose commits
    /// do not wait for a synchronous standby unless `replication` says otherwise.
    pub async fn open_cluster(dir: &Path, url: &str, log: LogConfig, search: SearchConfig) -> Result<Self, StoreError> {
        let (cluster, tenants) = Cluster::connect(url, log).await?;
        let dir = dir.to_path_buf();
        // sled opens and drops its cache with blocking I/O.
        let store =
            tokio::task::spawn_blocking(move || Self::open_dir(&dir, search, Backend::Cluster(Box::new(cluster))))
                .await
                .map_err(|e| StoreError::Storage(format!("opening the cache failed: {e}")))??;
        // The log's tenants replace this node's copy, which `Auth` reads at start.
        store.replace_tenants(&tenants)?;
        Ok(store)
    }
}

/// The store's operations that depend on where the truth is: each asks the backend chosen at
/// open.
impl Store {
    /// Keeps the candidates answered for a stored frame; durable when this returns.
    pub async fn keep_loops(&self, s: &Arc<Session>, loops: Vec<LoopRecord>) -> Result<(), StoreError> {
        if loops.is_empty() {
            return Ok(());
        }
        dispatch!(async self, keep_loops(self, s, loops))
    }

    /// Records a client's verdict on a kept loop; the loop as it now is, once durable.
    pub async fn set_verdict(
        &self,
        s: &Arc<Session>,
        query: u64,
        matched: u64,
        verdict: Verdict,
    ) -> Result<LoopRecord, StoreError> {
        if let Some(c) = &verdict.covariance {
            if c.len() != 36 || c.iter().any(|v| !v.is_finite()) {
                return Err(StoreError::InvalidArgument(
                    "covariance must be 36 finite numbers (6x6, row-major)".into(),
                ));
            }
        }
        dispatch!(async self, set_verdict(self, s, query, matched, verdict))
    }

    /// Asks whether writes reach the truth now (the cluster's log), waiting at most `within`;
    /// readiness reports the answer until the next probe. Nothing to ask with sled.
    pub async fn probe_log(&self, within: std::time::Duration) {
        dispatch!(async self, probe(within))
    }

    /// Why this node should not take calls now: its storage refuses writes, or (in a cluster)
    /// the log did not take writes at the last probe.
    pub fn readiness(&self) -> Option<String> {
        if let Some(e) = self.failure() {
            return Some(format!("storage failed ({e})"));
        }
        dispatch!(self, not_writable())
    }

    /// Keeps a tenant's record: in a cluster, in the log (then here); else durable in sled.
    pub async fn put_tenant_durable(&self, name: &str, record: &[u8]) -> Result<(), StoreError> {
        dispatch!(async self, put_tenant(name, record))?;
        self.put_tenant(name, record)?;
        self.durable_records().await
    }

    /// Every tenant's record as of now: in a cluster, the log's (kept here too).
    pub async fn tenants_fresh(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        dispatch!(async self, tenants_fresh(self))
    }

    /// The session as of now. In a cluster: loaded on first use, brought up to the log's version
    /// (read-after-ack across nodes), and forgotten here once deleted through another node.
    pub async fn fresh(&self, id: &str) -> Result<Arc<Session>, StoreError> {
        dispatch!(async self, fresh(self, id))
    }

    /// Every session as of now (see [`Store::fresh`]); with sled, [`Store::list`].
    pub async fn list_fresh(&self) -> Result<Vec<SessionInfo>, StoreError> {
        dispatch!(async self, list_fresh(self))
    }

    /// Every session's id and frame count: in a cluster the log's, sessions this node has not
    /// loaded included (a tenant's frame limit counts them all); with sled, this node's.
    pub async fn frame_counts(&self) -> Result<Vec<(String, u64)>, StoreError> {
        dispatch!(async self, frame_counts(self))
    }

    /// In a cluster, this node's copy of a session's kept loops becomes the log's (before a
    /// listing or an export); nothing to do with sled.
    pub async fn fresh_loops(&self, id: &str) -> Result<(), StoreError> {
        dispatch!(async self, fresh_loops(self, id))
    }

    /// In a cluster, a job number no node has given (None with sled: the node numbers its own).
    pub async fn cluster_job_number(&self) -> Result<Option<u64>, StoreError> {
        dispatch!(async self, job_number())
    }

    /// Keeps job `id`'s record (number `n`): in a cluster in the log under this node's name (a new
    /// job there drops the oldest finished beyond `kept`); with sled here, durable with the next
    /// group commit.
    pub async fn keep_job(&self, id: &str, n: u64, record: &[u8], kept: usize) -> Result<(), StoreError> {
        dispatch!(async self, keep_job(self, id, n, record, kept))
    }

    /// Job `id` as the cluster's log holds it (None with sled, or when the log has no such job).
    pub async fn logged_job(&self, id: &str) -> Result<Option<LoggedJob>, StoreError> {
        dispatch!(async self, logged_job(id))
    }

    /// Marks the jobs this node ran before it started again as interrupted, as sled's records are
    /// at start; a failure is logged (their status then says interrupted through this node only).
    pub async fn interrupt_logged_jobs(&self) {
        dispatch!(async self, interrupt_logged_jobs())
    }

    /// Joins the cluster's membership as `me` (the first heartbeat is the next
    /// [`Store::follow_members`]). No effect with sled.
    pub fn join_members(&self, me: Membership) {
        dispatch!(self, join_members(me))
    }

    /// One round: heartbeat, read the live members, load and catch up the sessions this node
    /// owns, and drop the ones it neither owns nor used within `evict_idle`. Nothing with sled.
    pub async fn follow_members(&self) -> Result<(), StoreError> {
        dispatch!(async self, follow_members(self))
    }

    /// This node's view of the cluster (None with sled).
    pub fn cluster_view(&self) -> Option<ClusterView> {
        dispatch!(self, cluster_view(self))
    }

    /// Leaves the membership (a clean shutdown): the others own this node's sessions at once.
    pub async fn leave_members(&self) {
        dispatch!(async self, leave_members())
    }
}
