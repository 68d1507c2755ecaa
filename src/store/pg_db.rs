//! The cluster log's connections: the pool and its deadline, which primary they reach and whether
//! its commits wait for a synchronous standby (the check of every new connection), how database
//! errors read as store errors, and the names and rows of a session's tables. `pg.rs` (the log's
//! reads and sessions) and `pg_writer.rs` (its write path) both stand on it.
use super::loops::LoopRecord;
use super::StoreError;
use deadpool_postgres::{Object, Pool};
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering::SeqCst};
use tokio_postgres::error::SqlState;

/// Whether the server must make each commit wait for a synchronous standby.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Replication {
    Synchronous,
    /// Tests and single-host trials only: an acknowledged frame may be lost with the primary.
    NotRequired,
}

/// How a node reaches the log: its connections, whether commits must wait for a synchronous
/// standby, and the deadline of every wait on the database.
#[derive(Clone, Copy, Debug)]
pub struct LogConfig {
    pub connections: usize,
    pub replication: Replication,
    /// The longest a call waits on the database: a connection taken or opened, a statement,
    /// a write's whole transaction up to its COMMIT. Past it the call answers Unavailable and its
    /// connection is dropped (the next call opens one, which finds the primary of now).
    pub deadline: std::time::Duration,
}

impl LogConfig {
    /// `connections` to the log, with the default deadline of 10 s.
    pub fn new(connections: usize, replication: Replication) -> Self {
        Self { connections, replication, deadline: std::time::Duration::from_secs(10) }
    }
}

/// The connections, and what the log knows of the primary behind them.
pub(super) struct Db {
    pub(super) pool: Pool,
    pub(super) replication: Replication,
    /// See [`LogConfig::deadline`].
    pub(super) deadline: std::time::Duration,
    /// The primary new connections last reached: its address, port and start time.
    pub(super) primary: parking_lot::Mutex<Option<String>>,
    /// Counts changes of primary (a failover, or a restart): frames read from an earlier primary
    /// may be missing from this one (visible there before a standby had them), so nodes drop
    /// what they applied before the change (`epoch`).
    pub(super) epoch: AtomicU64,
    /// When the last change of primary was seen: pooled connections opened before it lead to
    /// the old primary (perhaps frozen: a statement there would wait for ever) and are closed
    /// instead of being handed out.
    pub(super) changed_at: parking_lot::Mutex<Option<std::time::Instant>>,
    /// Why writes are refused now: the primary does not wait for a synchronous standby.
    pub(super) unreplicated: parking_lot::Mutex<Option<Unreplicated>>,
    /// The newest timeline a primary answered with here. A primary on an older one was replaced
    /// by a promotion (an old primary cut off, or started again, still taking writes): this
    /// node neither reads nor writes through it (fencing, issue #34).
    pub(super) timeline: AtomicI64,
}

/// Why the primary is not writable for loopd, and whether waiting can change it (a standby
/// coming back) or only a configuration can.
#[derive(Clone, Debug)]
pub(super) struct Unreplicated {
    pub(super) why: String,
    pub(super) transient: bool,
}

/// A batch as committed: the frames' ids in order, and the session's version after it.
#[derive(Clone, Debug, PartialEq)]
pub struct Appended {
    pub ids: Vec<u64>,
    pub version: i64,
    /// Nothing was stored: the batch's idempotency key names a frame an earlier write stored
    /// (`ids` is that frame; `version` is at least the one it was committed in).
    pub replayed: bool,
}

/// Transient: the database cannot be reached or is switching primaries; retry later. A commit
/// whose answer was lost may or may not have happened: frames with ids make the retry exact
/// (a stored one answers already-exists).
pub(super) fn unavailable(e: &tokio_postgres::Error) -> StoreError {
    StoreError::Unavailable(format!("the cluster database is unavailable ({e}); retry later"))
}

pub(super) fn pg_error(e: tokio_postgres::Error) -> StoreError {
    match e.as_db_error() {
        // A server that is read-only (a standby), shutting down, crashed, starting or out of
        // connections: another primary or a retry will answer.
        Some(db)
            if *db.code() == SqlState::READ_ONLY_SQL_TRANSACTION
                || ["08", "53", "57"].iter().any(|class| db.code().code().starts_with(class)) =>
        {
            unavailable(&e)
        }
        // Other server-side errors are answers: the statement ran and was refused.
        Some(db) => StoreError::Storage(format!("database: {}", db.message())),
        None => unavailable(&e),
    }
}

/// A call that ran past the log's deadline (a cut-off or frozen primary, a commit waiting for a
/// standby that does not answer).
pub(super) fn late(deadline: std::time::Duration, what: &str) -> StoreError {
    StoreError::Unavailable(format!("the cluster database did not answer within {deadline:?} ({what}); retry later"))
}

/// A pool error as a store error; a timeout (waiting for, creating or recycling a connection)
/// reads as every other call past the deadline.
fn pool_error(e: deadpool_postgres::PoolError, deadline: std::time::Duration) -> StoreError {
    match e {
        deadpool_postgres::PoolError::Backend(e) => pg_error(e),
        deadpool_postgres::PoolError::Timeout(_) => late(deadline, "a connection"),
        other => StoreError::Unavailable(format!("the cluster database is unavailable ({other}); retry later")),
    }
}

impl Db {
    /// A pooled connection; a new one first says which primary it reached (a change bumps the
    /// epoch) and whether its commits wait for a synchronous standby.
    pub(super) async fn client(&self) -> Result<Object, StoreError> {
        let client = loop {
            let client = self.pool.get().await.map_err(|e| pool_error(e, self.deadline))?;
            let changed = *self.changed_at.lock();
            if changed.is_some_and(|at| Object::metrics(&client).created < at) {
                let _ = Object::take(client);
                continue;
            }
            break client;
        };
        if Object::metrics(&client).recycle_count > 0 {
            return Ok(client);
        }
        let checked = tokio::time::timeout(self.deadline, self.check(&client))
            .await
            .unwrap_or_else(|_| Err(late(self.deadline, "checking a new connection")));
        match checked {
            Ok(()) => Ok(client),
            Err(e) => {
                // Never back into the pool unchecked.
                let _ = Object::take(client);
                Err(e)
            }
        }
    }

    pub(super) async fn check(&self, client: &Object) -> Result<(), StoreError> {
        // The standbys that really are there: streaming and synchronous (pg_stat_replication),
        // not only named in the setting (Patroni's strict mode names '*' with none left).
        let sql = "SELECT pg_postmaster_start_time()::text || ' ' || coalesce(host(inet_server_addr()), 'socket') \
                   || ':' || coalesce(inet_server_port(), 0)::text, current_setting('synchronous_commit'), \
                   current_setting('synchronous_standby_names'), pg_is_in_recovery(), \
                   (SELECT count(*) FROM pg_stat_replication \
                    WHERE state = 'streaming' AND sync_state IN ('sync', 'quorum')), \
                   pg_has_role(current_user, 'pg_read_all_stats', 'USAGE'), \
                   CASE WHEN pg_is_in_recovery() THEN 0 \
                   ELSE ('x' || substr(pg_walfile_name(pg_current_wal_lsn()), 1, 8))::bit(32)::int END";
        let row = client.query_one(sql, &[]).await.map_err(pg_error)?;
        let (primary, commit, standbys, recovering, streaming, sees): (String, String, String, bool, i64, bool) =
            (row.get(0), row.get(1), row.get(2), row.get(3), row.get(4), row.get(5));
        if recovering {
            return Err(StoreError::Unavailable(format!("{primary} is a standby, not the primary; retry later")));
        }
        // Its timeline (the first 8 hex digits of its current WAL file's name): a promotion
        // starts a new one, so an older one than seen before is a primary since replaced.
        let timeline = i64::from(row.get::<_, i32>(6));
        let newest = self.timeline.fetch_max(timeline, SeqCst).max(timeline);
        if timeline < newest {
            tracing::warn!(%primary, timeline, newest, "refused a replaced primary (an older timeline than seen before)");
            return Err(StoreError::Unavailable(format!(
                "{primary} is on timeline {timeline}, older than timeline {newest} seen before: a primary that was \
                 replaced (cut off from the cluster or started again), not used; retry later"
            )));
        }
        let configured =
            !standbys.trim().is_empty() && matches!(commit.as_str(), "on" | "remote_write" | "remote_apply");
        *self.unreplicated.lock() = match self.replication {
            Replication::NotRequired => None,
            Replication::Synchronous if !configured => Some(Unreplicated {
                why: format!(
                    "the cluster database does not wait for a synchronous standby (synchronous_commit = {commit}, \
                     synchronous_standby_names = '{standbys}'): an acknowledged frame could be lost with the primary"
                ),
                transient: false,
            }),
            Replication::Synchronous if !sees => Some(Unreplicated {
                why: "loopd's database role cannot read pg_stat_replication, so it cannot tell whether a \
                      synchronous standby is streaming (GRANT pg_monitor to it)"
                    .into(),
                transient: false,
            }),
            Replication::Synchronous if streaming == 0 => Some(Unreplicated {
                why: format!(
                    "no synchronous standby is streaming from the primary (pg_stat_replication; \
                     synchronous_standby_names = '{standbys}'): a commit would wait until one is back"
                ),
                transient: true,
            }),
            Replication::Synchronous => None,
        };
        let mut known = self.primary.lock();
        if known.as_ref().is_some_and(|p| *p != primary) {
            let epoch = self.epoch.fetch_add(1, SeqCst) + 1;
            // Connections opened before now lead to the old primary: none is handed out again.
            let now = std::time::Instant::now();
            *self.changed_at.lock() = Some(now);
            self.pool.retain(|_, m| m.created >= now);
            tracing::warn!(%primary, epoch, "the cluster database has another primary: cached sessions are reloaded");
        }
        *known = Some(primary);
        Ok(())
    }

    /// A connection for a write, refused at once while the primary does not wait for a
    /// synchronous standby (as the last check of a connection found it).
    pub(super) async fn for_write(&self) -> Result<Held, StoreError> {
        self.writable()?;
        let client = self.client().await?;
        // A new connection's check may just have found the standby gone.
        self.writable()?;
        Ok(Held(Some(client)))
    }

    /// A write, its connection included ([`Db::for_write`] inside it), under the log's deadline:
    /// past it the write answers Unavailable and its connection is closed (dropped with the
    /// write), so a commit waiting for a standby that does not answer, or a primary cut off,
    /// holds no caller longer than the deadline.
    pub(super) async fn within<T>(
        &self,
        what: &str,
        write: impl std::future::Future<Output = Result<T, StoreError>>,
    ) -> Result<T, StoreError> {
        tokio::time::timeout(self.deadline, write)
            .await
            .unwrap_or_else(|_| Err(late(self.deadline, &format!("{what}, which may or may not have been committed"))))
    }

    /// A read (one statement) under the log's deadline: past it the read answers Unavailable and
    /// its connection is closed, never pooled (a primary frozen mid-statement acknowledges at the
    /// TCP level and never answers; neither keepalives nor the TCP user timeout end that wait).
    /// The outer error: no connection or no answer in time; the inner one: the statement's own.
    pub(super) async fn query(
        &self,
        what: &str,
        sql: &str,
        params: &[&(dyn tokio_postgres::types::ToSql + Sync)],
    ) -> Result<Result<Vec<tokio_postgres::Row>, tokio_postgres::Error>, StoreError> {
        let read = async {
            let mut held = Held(Some(self.client().await?));
            let rows = held.conn().query(sql, params).await;
            // Answered (rows or the server's refusal): the connection is sound.
            if rows.is_ok() || rows.as_ref().is_err_and(|e| e.as_db_error().is_some()) {
                held.release();
            }
            Ok(rows)
        };
        tokio::time::timeout(self.deadline, read).await.unwrap_or_else(|_| Err(late(self.deadline, what)))
    }

    /// A connection that is closed, not pooled, unless released (see [`Held`]); for statements
    /// run under [`Db::within`].
    pub(super) async fn held(&self) -> Result<Held, StoreError> {
        Ok(Held(Some(self.client().await?)))
    }

    /// [`Db::query`] for at most one row.
    pub(super) async fn query_opt(
        &self,
        what: &str,
        sql: &str,
        params: &[&(dyn tokio_postgres::types::ToSql + Sync)],
    ) -> Result<Option<tokio_postgres::Row>, StoreError> {
        Ok(self.query(what, sql, params).await?.map_err(pg_error)?.into_iter().next())
    }

    /// Unavailable while the primary does not wait for a synchronous standby.
    pub(super) fn writable(&self) -> Result<(), StoreError> {
        match self.unreplicated.lock().clone() {
            Some(u) => Err(StoreError::Unavailable(format!("writes refused: {}", u.why))),
            None => Ok(()),
        }
    }
}

/// A connection taken for a write: closed, not put back into the pool, unless released once the
/// write is answered, so that a write abandoned at its deadline (perhaps mid-transaction) never
/// hands its connection to the next caller.
pub(super) struct Held(Option<Object>);

impl Held {
    pub(super) fn conn(&mut self) -> &mut Object {
        self.0.as_mut().expect("a held connection is there until released")
    }

    /// Back into the pool: the write was answered.
    pub(super) fn release(mut self) {
        drop(self.0.take());
    }
}

impl Drop for Held {
    fn drop(&mut self) {
        if let Some(client) = self.0.take() {
            let _ = Object::take(client);
        }
    }
}

pub(super) fn frames_table(tbl: i64) -> String {
    format!("loopd_frames_{tbl}")
}

/// The session's kept loops (`loops.rs` records as JSON), by (query frame, match frame).
pub(super) fn loops_table(tbl: i64) -> String {
    format!("loopd_loops_{tbl}")
}

/// A loop table row: the loop as kept for the frame `query` (its key and its JSON).
pub(super) fn loop_row(query: u64, l: &LoopRecord) -> Result<(i64, i64, serde_json::Value), StoreError> {
    let json = serde_json::to_value(LoopRecord { query_frame: query, ..l.clone() })
        .map_err(|e| StoreError::Storage(e.to_string()))?;
    Ok((query as i64, l.match_frame as i64, json))
}
