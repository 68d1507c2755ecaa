//! The durable frame log on PostgreSQL with synchronous replication: the cluster's
//! copy of every session and frame, beside which loopd nodes keep their in-memory exact indexes
//! (`SessionIndex`), rebuilt from it. `serve --cluster` uses it through `cluster.rs`; members
//! (`pg_members.rs`) and sequence jobs (`pg_jobs.rs`) have their tables beside it, and the write
//! path (`pg_writer.rs`: grouped commits per session) its own file (docs/cluster.md).
//!
//! Schema: `loopd_sessions(id, tbl, meta, version, next_frame_id)` and one table per session,
//! `loopd_frames_<tbl>(frame_id, seq, write_id, record, features, thumb)`, so deleting a session
//! is a DROP TABLE as it is a dropped tree in sled. `record` is the sled frame record
//! (`record.rs`: header JSON and the descriptor in the session's storage); features and the
//! thumbnail are the opaque bytes sled keeps beside it. Each session also has
//! `loopd_loops_<tbl>(query_frame, match_frame, record)` (its kept loops, `loops.rs` records as
//! JSON), and `loopd_tenants(name, record)` holds the tenants. A batch is one transaction under the session row's lock:
//! `seq` follows commit order per session, and `version` is the highest `seq` committed, so a
//! node that has applied every `seq <= v` holds every frame acknowledged up to `v`.
//!
//! A batch is acknowledged only when its COMMIT returned, and the connection refuses a server
//! whose commits do not wait for a synchronous standby (`synchronous_commit` on or stronger and
//! `synchronous_standby_names` set), unless it is opened with `Replication::NotRequired`.
use super::loops::{LoopRecord, Verdict};
use super::pg_db::{frames_table, loop_row, loops_table, pg_error, Db};
pub use super::pg_db::{Appended, LogConfig, Replication};
use super::pg_writer::{write_session, Request};
use super::record::{decode_frame, FrameHeader, SessionMeta};
use super::{NewFrame, StoreError};
use deadpool_postgres::{Manager, ManagerConfig, Object, Pool, RecyclingMethod};
use std::sync::atomic::{AtomicU64, Ordering::SeqCst};
use std::sync::Arc;
use tokio_postgres::error::SqlState;
use tokio_postgres::types::ToSql;

pub struct PgLog {
    db: Arc<Db>,
    /// Each session's writer queue (see `pg_writer::write_session`).
    writers: parking_lot::Mutex<std::collections::HashMap<String, tokio::sync::mpsc::UnboundedSender<Request>>>,
}

/// A frame read back from the log.
#[derive(Debug)]
pub struct LoggedFrame {
    pub seq: i64,
    pub frame_id: u64,
    pub header: FrameHeader,
    pub descriptor: Vec<f32>,
    /// The record as stored (the sled frame record of `header` and `descriptor`).
    pub record: Vec<u8>,
    pub features: Option<Vec<u8>>,
    pub thumbnail: Option<Vec<u8>>,
}

/// A session as the log holds it now: its metadata, its table (an identity never reused, so a
/// session deleted and created again under the same id is told apart) and its version.
#[derive(Clone, Debug)]
pub struct Head {
    pub meta: SessionMeta,
    pub tbl: i64,
    pub version: i64,
}

/// The advisory lock key the schema is created under (any constant: "loopd" in ASCII).
const SCHEMA_LOCK: i64 = 0x6c6f6f7064;

const SCHEMA: &str = "CREATE TABLE IF NOT EXISTS loopd_sessions (
    id text PRIMARY KEY,
    tbl bigint GENERATED ALWAYS AS IDENTITY UNIQUE,
    meta jsonb NOT NULL,
    version bigint NOT NULL DEFAULT 0,
    next_frame_id bigint NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS loopd_tenants (name text PRIMARY KEY, record jsonb NOT NULL);
CREATE TABLE IF NOT EXISTS loopd_members (node text PRIMARY KEY, seen timestamptz NOT NULL, since timestamptz NOT NULL);
CREATE TABLE IF NOT EXISTS loopd_jobs (id text PRIMARY KEY, n bigint NOT NULL, node text NOT NULL, record jsonb NOT NULL, \
    updated timestamptz NOT NULL DEFAULT now());
CREATE SEQUENCE IF NOT EXISTS loopd_job_numbers;
CREATE TABLE IF NOT EXISTS loopd_frame_keys (tbl bigint NOT NULL, key text NOT NULL, frame_id bigint NOT NULL, \
    robot_id text NOT NULL, stamp double precision NOT NULL, PRIMARY KEY (tbl, key))";

fn loop_record(v: serde_json::Value) -> Result<LoopRecord, StoreError> {
    serde_json::from_value(v).map_err(|e| StoreError::Storage(format!("loop record: {e}")))
}

impl PgLog {
    /// Connects (a multi-host URL with `target_session_attrs=read-write` finds the primary),
    /// creates the schema if missing and checks that commits wait for a synchronous standby.
    pub async fn connect(url: &str, config: LogConfig) -> Result<Self, StoreError> {
        let LogConfig { connections: max_connections, replication, deadline } = config;
        let mut config: tokio_postgres::Config =
            url.parse().map_err(|e| StoreError::InvalidArgument(format!("cluster URL: {e}")))?;
        // A host that does not answer (cut off, not refusing) must not hold a request for long.
        if config.get_connect_timeout().is_none() {
            config.connect_timeout(std::time::Duration::from_secs(5));
        }
        // Nor may a connection whose server was cut off mid-statement: unacknowledged data for
        // 5 s closes it (the statement fails UNAVAILABLE), and idle ones are probed by keepalives
        // (on by default) after 5 s rather than the default 2 hours.
        if config.get_tcp_user_timeout().is_none() {
            config.tcp_user_timeout(std::time::Duration::from_secs(5));
        }
        if config.get_keepalives_idle() == std::time::Duration::from_secs(2 * 60 * 60) {
            config.keepalives_idle(std::time::Duration::from_secs(5));
            // An idle connection to a host that went away is closed after 5 + 3 x 1 s.
            config.keepalives_interval(std::time::Duration::from_secs(1));
            config.keepalives_retries(3);
        }
        // Each host of the URL in turn, each opening bounded as a whole (pg_connect.rs): a frozen
        // primary must not hold up the hosts after it.
        let hosts = super::pg_connect::PerHost::new(&config);
        let manager = Manager::from_connect(config, hosts, ManagerConfig { recycling_method: RecyclingMethod::Fast });
        let pool = Pool::builder(manager)
            .max_size(max_connections.max(1))
            // Waiting for a free connection, opening one (each host of the URL in turn) and
            // recycling one are bounded too.
            .runtime(deadpool_postgres::Runtime::Tokio1)
            .wait_timeout(Some(deadline))
            .create_timeout(Some(deadline))
            .recycle_timeout(Some(deadline))
            .build()
            .map_err(|e| StoreError::InvalidArgument(format!("cluster pool: {e}")))?;
        let db = Db {
            pool,
            replication,
            deadline,
            primary: Default::default(),
            epoch: AtomicU64::new(0),
            changed_at: Default::default(),
            timeline: Default::default(),
            unreplicated: Default::default(),
        };
        let log = Self { db: Arc::new(db), writers: Default::default() };
        let client = log.client().await?;
        // Nodes starting together would race in CREATE TABLE IF NOT EXISTS (a unique violation in
        // the catalog): one at a time, under a transaction-scoped advisory lock.
        let schema = format!("BEGIN; SELECT pg_advisory_xact_lock({SCHEMA_LOCK}); {SCHEMA}; COMMIT");
        client.batch_execute(&schema).await.map_err(pg_error)?;
        // A setting that never waits is a configuration to fix; a standby not streaming yet (the
        // whole cluster starting) is waited for by the caller.
        if let Some(u) = log.db.unreplicated.lock().clone() {
            return Err(match u.transient {
                true => StoreError::Unavailable(u.why),
                false => StoreError::InvalidArgument(u.why),
            });
        }
        Ok(log)
    }

    pub(super) async fn client(&self) -> Result<Object, StoreError> {
        self.db.client().await
    }

    /// The connections (the members' and jobs' tables write through them too).
    pub(super) fn db(&self) -> &Db {
        &self.db
    }

    /// Whether the log takes writes now: a connection to a writable primary whose commits wait
    /// for a synchronous standby (checked again on that connection: settings change live).
    pub async fn probe(&self) -> Result<(), StoreError> {
        let client = self.client().await?;
        tokio::time::timeout(self.db.deadline, self.db.check(&client))
            .await
            .unwrap_or_else(|_| Err(super::pg_db::late(self.db.deadline, "the readiness probe")))?;
        self.db.writable()
    }

    /// How many times the primary has changed since connecting (see `Db::epoch`).
    pub fn epoch(&self) -> u64 {
        self.db.epoch.load(SeqCst)
    }

    /// Creates a session and its frames table, in one transaction; returns its table's number.
    pub async fn create_session(&self, meta: &SessionMeta) -> Result<i64, StoreError> {
        let json = serde_json::to_value(meta).map_err(|e| StoreError::Storage(e.to_string()))?;
        self.db
            .within("creating a session", async {
                let mut held = self.db.for_write().await?;
                let tx = held.conn().transaction().await.map_err(pg_error)?;
                let sql = "INSERT INTO loopd_sessions (id, meta) VALUES ($1, $2) ON CONFLICT DO NOTHING RETURNING tbl";
                let Some(row) = tx.query_opt(sql, &[&meta.id, &json]).await.map_err(pg_error)? else {
                    return Err(StoreError::SessionExists(meta.id.clone()));
                };
                let tbl: i64 = row.get(0);
                let table = frames_table(tbl);
                // Descriptors are incompressible: EXTERNAL keeps them out of line without trying.
                let ddl = format!(
                    "CREATE TABLE {table} (frame_id bigint PRIMARY KEY, seq bigint NOT NULL UNIQUE, \
                     write_id bigint NOT NULL, record bytea NOT NULL, features bytea, thumb bytea); \
                     ALTER TABLE {table} ALTER COLUMN record SET STORAGE EXTERNAL; \
                     CREATE TABLE {} (query_frame bigint, match_frame bigint, record jsonb NOT NULL, \
                     PRIMARY KEY (query_frame, match_frame))",
                    loops_table(tbl)
                );
                tx.batch_execute(&ddl).await.map_err(pg_error)?;
                tx.commit().await.map_err(pg_error)?;
                held.release();
                Ok(tbl)
            })
            .await
    }

    /// Every session's metadata and version.
    pub async fn sessions(&self) -> Result<Vec<(SessionMeta, i64)>, StoreError> {
        Ok(self.heads().await?.into_iter().map(|h| (h.meta, h.version)).collect())
    }

    /// Every session as the log holds it now.
    pub async fn heads(&self) -> Result<Vec<Head>, StoreError> {
        let sql = "SELECT meta, tbl, version FROM loopd_sessions ORDER BY id";
        let rows = self.db.query("listing sessions", sql, &[]).await?.map_err(pg_error)?;
        rows.iter().map(head).collect()
    }

    /// One session as the log holds it now (one round trip).
    pub async fn head(&self, session: &str) -> Result<Head, StoreError> {
        let sql = "SELECT meta, tbl, version FROM loopd_sessions WHERE id = $1";
        let row = self.db.query_opt("reading a session", sql, &[&session]).await?;
        head(&row.ok_or_else(|| StoreError::SessionNotFound(session.into()))?)
    }

    /// The session's version: the `seq` of its last committed frame (0: none).
    pub async fn version(&self, session: &str) -> Result<i64, StoreError> {
        let sql = "SELECT version FROM loopd_sessions WHERE id = $1";
        let row = self.db.query_opt("reading a session's version", sql, &[&session]).await?;
        row.map(|r| r.get(0)).ok_or_else(|| StoreError::SessionNotFound(session.into()))
    }

    /// Drops a session and its frames, in one transaction.
    pub async fn delete_session(&self, session: &str) -> Result<(), StoreError> {
        self.db
            .within("deleting a session", async {
                let mut held = self.db.for_write().await?;
                let tx = held.conn().transaction().await.map_err(pg_error)?;
                let row = tx.query_opt("DELETE FROM loopd_sessions WHERE id = $1 RETURNING tbl", &[&session]).await;
                let tbl: i64 =
                    row.map_err(pg_error)?.ok_or_else(|| StoreError::SessionNotFound(session.into()))?.get(0);
                let drop = format!(
                    "DROP TABLE {}, {}; DELETE FROM loopd_frame_keys WHERE tbl = {tbl}",
                    frames_table(tbl),
                    loops_table(tbl)
                );
                tx.batch_execute(&drop).await.map_err(pg_error)?;
                tx.commit().await.map_err(pg_error)?;
                held.release();
                Ok(())
            })
            .await?;
        // Its writer ends once the requests already queued are answered (SessionNotFound).
        self.writers.lock().remove(session);
        Ok(())
    }

    /// Stores a tenant's record (its key's hash, limits, revoked or not), replacing the one
    /// before: acknowledged once on a synchronous standby, like frames.
    pub async fn put_tenant(&self, name: &str, record: &[u8]) -> Result<(), StoreError> {
        let record: serde_json::Value =
            serde_json::from_slice(record).map_err(|e| StoreError::InvalidArgument(format!("tenant record: {e}")))?;
        self.db
            .within("storing a tenant", async {
                let mut held = self.db.for_write().await?;
                let sql = "INSERT INTO loopd_tenants (name, record) VALUES ($1, $2) \
                           ON CONFLICT (name) DO UPDATE SET record = EXCLUDED.record";
                held.conn().execute(sql, &[&name, &record]).await.map_err(pg_error)?;
                held.release();
                Ok(())
            })
            .await
    }

    /// Every session's id and frame count (its version: one `seq` per frame, and frames are only
    /// ever deleted with their session).
    pub async fn frame_counts(&self) -> Result<Vec<(String, u64)>, StoreError> {
        let sql = "SELECT id, version FROM loopd_sessions";
        let rows = self.db.query("counting frames", sql, &[]).await?.map_err(pg_error)?;
        Ok(rows.iter().map(|r| (r.get(0), r.get::<_, i64>(1).max(0) as u64)).collect())
    }

    /// Every tenant's record, by name.
    pub async fn tenants(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        let sql = "SELECT name, record FROM loopd_tenants";
        let rows = self.db.query("reading tenants", sql, &[]).await?.map_err(pg_error)?;
        rows.iter()
            .map(|r| {
                let record: serde_json::Value = r.get(1);
                Ok((r.get(0), serde_json::to_vec(&record).map_err(|e| StoreError::Storage(e.to_string()))?))
            })
            .collect()
    }

    /// Appends a batch of frames (descriptors already normalised), all or none: a frame id
    /// already stored, in the session or twice in the batch, refuses the whole batch with
    /// `FrameExists`. Returns once the commit has reached a synchronous standby. Batches sent to
    /// a session at the same time share one transaction (each under its own savepoint), so a
    /// session's throughput is not one commit round trip per batch.
    pub async fn append(&self, meta: &SessionMeta, frames: &[NewFrame]) -> Result<Appended, StoreError> {
        self.append_keeping(meta, frames, Vec::new()).await
    }

    /// As [`PgLog::append`], with the loops answered for the frames committed in the same
    /// transaction. Each is given with the position of its query frame in `frames`: the writer
    /// sets its `query_frame` to that frame's id.
    pub async fn append_keeping(
        &self,
        meta: &SessionMeta,
        frames: &[NewFrame],
        loops: Vec<(usize, LoopRecord)>,
    ) -> Result<Appended, StoreError> {
        if frames.is_empty() {
            return Ok(Appended { ids: Vec::new(), version: self.version(&meta.id).await?, replayed: false });
        }
        if loops.iter().any(|(i, _)| *i >= frames.len()) {
            return Err(StoreError::InvalidArgument("a kept loop names no frame of the batch".into()));
        }
        let (done, answer) = tokio::sync::oneshot::channel();
        let request = Request { frames: frames.to_vec(), loops, storage: meta.storage, done };
        let queue = {
            let mut writers = self.writers.lock();
            writers
                .entry(meta.id.clone())
                .or_insert_with(|| {
                    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
                    tokio::spawn(write_session(self.db.clone(), meta.id.clone(), rx));
                    tx
                })
                .clone()
        };
        queue.send(request).map_err(|_| StoreError::Unavailable("the session's writer stopped; retry".into()))?;
        answer.await.map_err(|_| StoreError::Unavailable("the session's writer stopped; retry".into()))?
    }

    /// Keeps loops answered again for stored frames; a verdict already given stays.
    pub async fn keep_loops(&self, tbl: i64, loops: &[LoopRecord]) -> Result<(), StoreError> {
        let sql = format!(
            "INSERT INTO {} AS t (query_frame, match_frame, record) VALUES ($1, $2, $3) \
             ON CONFLICT (query_frame, match_frame) DO UPDATE SET record = CASE WHEN t.record ? 'verdict' \
             THEN EXCLUDED.record || jsonb_build_object('verdict', t.record->'verdict') ELSE EXCLUDED.record END",
            loops_table(tbl)
        );
        let rows = loops.iter().map(|l| loop_row(l.query_frame, l)).collect::<Result<Vec<_>, _>>()?;
        let params: Vec<[&(dyn ToSql + Sync); 3]> =
            rows.iter().map(|(q, m, r)| [q as &(dyn ToSql + Sync), m, r]).collect();
        self.db
            .within("keeping loops", async {
                let mut held = self.db.for_write().await?;
                let client = held.conn();
                let statement = client.prepare(&sql).await.map_err(pg_error)?;
                let writes = params.iter().map(|p| client.execute(&statement, p));
                for w in futures::future::join_all(writes).await {
                    w.map_err(pg_error)?;
                }
                held.release();
                Ok(())
            })
            .await
    }

    /// Records a verdict on a kept loop; the loop as it now is.
    pub async fn set_verdict(
        &self,
        (session, tbl): (&str, i64),
        query: u64,
        matched: u64,
        verdict: &Verdict,
    ) -> Result<LoopRecord, StoreError> {
        let verdict = serde_json::to_value(verdict).map_err(|e| StoreError::Storage(e.to_string()))?;
        let sql = format!(
            "UPDATE {} SET record = record || jsonb_build_object('verdict', $3::jsonb) \
             WHERE query_frame = $1 AND match_frame = $2 RETURNING record",
            loops_table(tbl)
        );
        let row = self
            .db
            .within("recording a verdict", async {
                let mut held = self.db.for_write().await?;
                let params: [&(dyn ToSql + Sync); 3] = [&(query as i64), &(matched as i64), &verdict];
                let row = held.conn().query_opt(&sql, &params).await.map_err(pg_error)?;
                held.release();
                Ok(row)
            })
            .await?;
        let row = row
            .ok_or_else(|| StoreError::LoopNotFound(format!("no loop {query} -> {matched} in session '{session}'")))?;
        loop_record(row.get(0))
    }

    /// Every kept loop of the session whose table is `tbl`.
    pub async fn loops(&self, session: &str, tbl: i64) -> Result<Vec<LoopRecord>, StoreError> {
        let sql = format!("SELECT record FROM {} ORDER BY query_frame, match_frame", loops_table(tbl));
        let rows = match self.db.query("reading kept loops", &sql, &[]).await? {
            Err(e) if e.code() == Some(&SqlState::UNDEFINED_TABLE) => {
                return Err(StoreError::SessionNotFound(session.into()))
            }
            rows => rows.map_err(pg_error)?,
        };
        rows.into_iter().map(|r| loop_record(r.get(0))).collect()
    }

    /// The session's frames with `seq > after`, in `seq` order: a cold load (after 0) or the tail
    /// a node has not applied yet.
    pub async fn frames(&self, session: &str, after: i64) -> Result<Vec<LoggedFrame>, StoreError> {
        let tbl = self.head(session).await?.tbl;
        self.tail(session, tbl, after, i64::MAX).await
    }

    /// As [`PgLog::frames`], from the session's table `tbl` (SessionNotFound once it is
    /// dropped), at most `limit` frames: a node loads a large session page by page.
    pub async fn tail(&self, session: &str, tbl: i64, after: i64, limit: i64) -> Result<Vec<LoggedFrame>, StoreError> {
        let sql = format!(
            "SELECT seq, frame_id, record, features, thumb FROM {} WHERE seq > $1 ORDER BY seq LIMIT $2",
            frames_table(tbl)
        );
        let rows = match self.db.query("reading frames", &sql, &[&after, &limit]).await? {
            Err(e) if e.code() == Some(&SqlState::UNDEFINED_TABLE) => {
                return Err(StoreError::SessionNotFound(session.into()))
            }
            rows => rows.map_err(pg_error)?,
        };
        rows.iter()
            .map(|r| {
                let (seq, frame_id, record): (i64, i64, Vec<u8>) = (r.get(0), r.get(1), r.get(2));
                let (header, descriptor) = decode_frame(&record).map_err(StoreError::Storage)?;
                Ok(LoggedFrame {
                    seq,
                    frame_id: frame_id as u64,
                    header,
                    descriptor,
                    record,
                    features: r.get(3),
                    thumbnail: r.get(4),
                })
            })
            .collect()
    }
}

fn head(r: &tokio_postgres::Row) -> Result<Head, StoreError> {
    let meta: serde_json::Value = r.get(0);
    let meta = serde_json::from_value(meta).map_err(|e| StoreError::Storage(format!("session meta: {e}")))?;
    Ok(Head { meta, tbl: r.get(1), version: r.get(2) })
}
