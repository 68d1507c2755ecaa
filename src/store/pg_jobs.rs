//! Sequence jobs' records in the log, so a job started through one node is polled through any:
//! `loopd_jobs(id, n, node, record, updated)`, numbered by the log's sequence (unique across
//! nodes) and written by the node that runs the job.
use super::pg::PgLog;
use super::pg_db::pg_error;
use super::StoreError;

/// A job's record as the log holds it, and the node that runs (or ran) it.
pub struct JobRow {
    pub node: String,
    pub record: Vec<u8>,
    /// Whether the record was written within the `recent` asked for (by the database's clock).
    pub recent: bool,
}

impl PgLog {
    /// A job number that no node of the cluster has given (the log's sequence).
    pub async fn next_job_number(&self) -> Result<u64, StoreError> {
        let row = self.db().query_opt("numbering a job", "SELECT nextval('loopd_job_numbers')", &[]).await?;
        let row = row.ok_or_else(|| StoreError::Storage("nextval gave no row".into()))?;
        Ok(row.get::<_, i64>(0).max(0) as u64)
    }

    /// Keeps job `id` (number `n`) as `node` runs it, replacing its record; a new job drops the
    /// oldest finished ones beyond `kept` (bounded, as on one node).
    pub async fn put_job(&self, id: &str, n: u64, node: &str, record: &[u8], kept: usize) -> Result<(), StoreError> {
        let record: serde_json::Value =
            serde_json::from_slice(record).map_err(|e| StoreError::InvalidArgument(format!("job record: {e}")))?;
        let n = i64::try_from(n).map_err(|_| StoreError::InvalidArgument("job number above 2^63 - 1".into()))?;
        self.db()
            .within("keeping a job", async {
                let mut held = self.db().for_write().await?;
                let client = held.conn();
                let sql = "INSERT INTO loopd_jobs (id, n, node, record) VALUES ($1, $2, $3, $4) ON CONFLICT (id) \
                           DO UPDATE SET node = EXCLUDED.node, record = EXCLUDED.record, updated = now() \
                           RETURNING xmax = 0";
                let inserted: bool = client.query_one(sql, &[&id, &n, &node, &record]).await.map_err(pg_error)?.get(0);
                if inserted {
                    let sql = "DELETE FROM loopd_jobs WHERE id IN (SELECT id FROM loopd_jobs \
                               WHERE record->>'state' <> 'running' ORDER BY n DESC OFFSET $1)";
                    client.execute(sql, &[&(kept as i64)]).await.map_err(pg_error)?;
                }
                held.release();
                Ok(())
            })
            .await
    }

    /// Job `id`'s record, if the log holds it, and whether it was written within `recent`.
    pub async fn job(&self, id: &str, recent: std::time::Duration) -> Result<Option<JobRow>, StoreError> {
        let sql = "SELECT node, record, updated > now() - make_interval(secs => $2) FROM loopd_jobs WHERE id = $1";
        let row = self.db().query_opt("reading a job", sql, &[&id, &recent.as_secs_f64()]).await?;
        let Some(row) = row else { return Ok(None) };
        let record: serde_json::Value = row.get(1);
        let record = serde_json::to_vec(&record).map_err(|e| StoreError::Storage(format!("job record: {e}")))?;
        Ok(Some(JobRow { node: row.get(0), record, recent: row.get(2) }))
    }

    /// Marks the jobs `node` was running as interrupted (it starts again: they ran in its earlier
    /// life). The number of jobs marked.
    pub async fn interrupt_jobs(&self, node: &str) -> Result<u64, StoreError> {
        let sql = "UPDATE loopd_jobs SET record = jsonb_set(record, '{state}', '\"interrupted\"') \
                   WHERE node = $1 AND record->>'state' = 'running'";
        self.db()
            .within("marking jobs interrupted", async {
                let mut held = self.db().for_write().await?;
                let marked = held.conn().execute(sql, &[&node]).await.map_err(pg_error)?;
                held.release();
                Ok(marked)
            })
            .await
    }
}
