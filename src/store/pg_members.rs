//! Cluster membership in the log: each node writes a heartbeat row, and the live members are
//! those seen within a time-to-live by the database's clock (no clock agreement between nodes).
//! A wrong view costs only a cold load, never a wrong answer, so there is no fencing.
use super::pg::PgLog;
use super::pg_db::pg_error;
use super::StoreError;
use std::time::Duration;

impl PgLog {
    /// Says that `node` is alive now (its row's `seen` becomes the database's now). Committed
    /// locally, without waiting for a standby: a heartbeat lost with the primary costs nothing,
    /// and members must not stall while no synchronous standby answers.
    pub async fn heartbeat(&self, node: &str) -> Result<(), StoreError> {
        let sql = "INSERT INTO loopd_members (node, seen, since) VALUES ($1, now(), now()) \
                   ON CONFLICT (node) DO UPDATE SET seen = now()";
        self.db()
            .within("a heartbeat", async {
                let mut held = self.db().held().await?;
                let tx = held.conn().transaction().await.map_err(pg_error)?;
                tx.batch_execute("SET LOCAL synchronous_commit = local").await.map_err(pg_error)?;
                tx.execute(sql, &[&node]).await.map_err(pg_error)?;
                tx.commit().await.map_err(pg_error)?;
                held.release();
                Ok(())
            })
            .await
    }

    /// The nodes seen within `ttl`, by name.
    pub async fn members(&self, ttl: Duration) -> Result<Vec<String>, StoreError> {
        let sql = "SELECT node FROM loopd_members WHERE seen > now() - make_interval(secs => $1) ORDER BY node";
        let rows = self.db().query("reading members", sql, &[&ttl.as_secs_f64()]).await?.map_err(pg_error)?;
        Ok(rows.iter().map(|r| r.get(0)).collect())
    }

    /// Removes `node` (a clean shutdown: the others take its sessions at once, not after the
    /// ttl); committed locally, as heartbeats are.
    pub async fn leave(&self, node: &str) -> Result<(), StoreError> {
        self.db()
            .within("leaving the members", async {
                let mut held = self.db().held().await?;
                let tx = held.conn().transaction().await.map_err(pg_error)?;
                tx.batch_execute("SET LOCAL synchronous_commit = local").await.map_err(pg_error)?;
                tx.execute("DELETE FROM loopd_members WHERE node = $1", &[&node]).await.map_err(pg_error)?;
                tx.commit().await.map_err(pg_error)?;
                held.release();
                Ok(())
            })
            .await
    }
}
