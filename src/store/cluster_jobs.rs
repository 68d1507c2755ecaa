//! Where sequence jobs' records are kept: on one node in sled (durable with the next group
//! commit), in a cluster in the log (`pg_jobs.rs`), so any node answers a job's status and no two
//! nodes give the same job id.
use super::{Store, StoreError};

/// How often a running job's record is rewritten at most (`api::jobs` saves every 2 s).
const JOB_REWRITE: std::time::Duration = std::time::Duration::from_secs(2);

/// A job's record from the cluster's log, and whether its runner may still be running it.
pub struct LoggedJob {
    pub record: Vec<u8>,
    /// False when the node that ran it is this process's predecessor, or is no longer a member
    /// and has not written the record lately: a record that still says running is then an
    /// interrupted job.
    pub runner_alive: bool,
}

impl Store {
    /// In a cluster, a job number no node has given (None with sled: the node numbers its own).
    pub async fn cluster_job_number(&self) -> Result<Option<u64>, StoreError> {
        match &self.cluster {
            Some(c) => c.log.next_job_number().await.map(Some),
            None => Ok(None),
        }
    }

    /// Keeps job `id`'s record (number `n`): in a cluster in the log under this node's name (a new
    /// job there drops the oldest finished beyond `kept`); with sled here, durable with the next
    /// group commit.
    pub async fn keep_job(&self, id: &str, n: u64, record: &[u8], kept: usize) -> Result<(), StoreError> {
        match &self.cluster {
            Some(c) => c.log.put_job(id, n, &self.node_name(), record, kept).await,
            None => self.put_job(id, record),
        }
    }

    /// Job `id` as the cluster's log holds it (None with sled, or when the log has no such job).
    pub async fn logged_job(&self, id: &str) -> Result<Option<LoggedJob>, StoreError> {
        let Some(c) = &self.cluster else { return Ok(None) };
        let me = c.members.me();
        // A runner rewrites a running job's record every few seconds: one written within the
        // member ttl (and twice the rewrite period) is alive even if a late heartbeat dropped
        // its node from this node's view for a round. "Interrupted" is final; it must not flap.
        let ttl = me.as_ref().map_or(std::time::Duration::from_secs(5), |m| m.ttl);
        let Some(job) = c.log.job(id, ttl.max(JOB_REWRITE * 2)).await? else { return Ok(None) };
        let live = c.members.live();
        let predecessor = me.is_some_and(|m| m.node == job.node);
        // Before the first members round the list is empty: the runner is not known to be gone.
        let member = live.is_empty() || live.contains(&job.node);
        let runner_alive = !predecessor && (member || job.recent);
        Ok(Some(LoggedJob { record: job.record, runner_alive }))
    }

    /// Marks the jobs this node ran before it started again as interrupted, as sled's records are
    /// at start; a failure is logged (their status then says interrupted through this node only).
    pub async fn interrupt_logged_jobs(&self) {
        let Some(c) = &self.cluster else { return };
        match c.log.interrupt_jobs(&self.node_name()).await {
            Ok(0) => {}
            Ok(n) => tracing::warn!(jobs = n, "jobs interrupted by this node's restart"),
            Err(e) => tracing::warn!(error = %e, "jobs of this node's earlier run not marked interrupted"),
        }
    }
}
