//! Where sequence jobs' records are kept: on one node in sled (durable with the next group
//! commit), in a cluster in the log (`pg_jobs.rs`), so any node answers a job's status and no two
//! nodes give the same job id.

/// How often a running job's record is rewritten at most (`api::jobs` saves every 2 s).
pub(super) const JOB_REWRITE: std::time::Duration = std::time::Duration::from_secs(2);

/// A job's record from the cluster's log, and whether its runner may still be running it.
pub struct LoggedJob {
    pub record: Vec<u8>,
    /// False when the node that ran it is this process's predecessor, or is no longer a member
    /// and has not written the record lately: a record that still says running is then an
    /// interrupted job.
    pub runner_alive: bool,
}
