//! The log's write path: each session's writer task takes every `append` waiting and commits
//! them as one transaction under the session row's lock, each request all or none under its own
//! savepoint, within the log's deadline (`LogConfig::deadline`).
use super::loops::LoopRecord;
use super::pg_db::{frames_table, loop_row, loops_table, pg_error, Appended, Db};
use super::record::encode_frame;
use super::{NewFrame, StoreError};
use crate::index::Storage;
use deadpool_postgres::Object;
use std::collections::HashMap;
use std::sync::Arc;
use tokio_postgres::error::SqlState;
use tokio_postgres::types::ToSql;

/// One `append` call waiting for its group's commit.
pub(super) struct Request {
    pub(super) frames: Vec<NewFrame>,
    /// Loops kept with the frames, by the position of their query frame in `frames`.
    pub(super) loops: Vec<(usize, LoopRecord)>,
    pub(super) storage: Storage,
    pub(super) done: tokio::sync::oneshot::Sender<Result<Appended, StoreError>>,
}

/// The frame of a request that carries an idempotency key, and the key.
fn keyed(r: &Request) -> Option<(&NewFrame, &str)> {
    r.frames.iter().find_map(|f| f.idempotency_key.as_deref().map(|k| (f, k)))
}

/// Frames one transaction takes at most (requests beyond wait for the next one).
const MAX_GROUP_FRAMES: usize = 512;

/// A session's writer: takes every request waiting and commits them in one transaction, until
/// the session's queue is dropped (the session was deleted or the log closed).
pub(super) async fn write_session(
    db: Arc<Db>,
    session: String,
    mut queue: tokio::sync::mpsc::UnboundedReceiver<Request>,
) {
    while let Some(first) = queue.recv().await {
        let mut group = vec![first];
        let mut frames = group[0].frames.len();
        while frames < MAX_GROUP_FRAMES {
            match queue.try_recv() {
                Ok(r) => {
                    frames += r.frames.len();
                    group.push(r);
                }
                Err(_) => break,
            }
        }
        let (answers, committed) = match commit_group(&db, &session, &group).await {
            Ok(answers) => (answers, None),
            Err(e) => (Vec::new(), Some(e)),
        };
        for (i, r) in group.into_iter().enumerate() {
            let answer = match &committed {
                Some(e) => Err(e.clone()),
                None => answers[i].clone(),
            };
            let _ = r.done.send(answer);
        }
    }
}

/// One transaction for a group of requests, each all or none under its savepoint; what each
/// request is answered once the commit returned.
///
/// The whole of it, the connection included, has the log's deadline: a commit that has not
/// returned by then (a primary cut off or frozen, or waiting for a standby that does not answer)
/// is answered Unavailable and its connection dropped, so this session's later writes are not
/// held behind it. Whether such a transaction committed is unknown to the client: frames with
/// ids make the retry exact (a stored one answers already-exists).
async fn commit_group(
    db: &Db,
    session: &str,
    group: &[Request],
) -> Result<Vec<Result<Appended, StoreError>>, StoreError> {
    db.within("a write", async {
        let mut held = db.for_write().await?;
        let answers = commit_on(held.conn(), session, group).await;
        held.release();
        answers
    })
    .await
}

async fn commit_on(
    client: &mut Object,
    session: &str,
    group: &[Request],
) -> Result<Vec<Result<Appended, StoreError>>, StoreError> {
    let tx = client.transaction().await.map_err(pg_error)?;
    // The session row's lock orders the groups of a session: seq follows commit order.
    let row = tx
        .query_opt("SELECT tbl, version, next_frame_id FROM loopd_sessions WHERE id = $1 FOR UPDATE", &[&session])
        .await
        .map_err(pg_error)?
        .ok_or_else(|| StoreError::SessionNotFound(session.into()))?;
    let (tbl, mut version, mut next): (i64, i64, i64) = (row.get(0), row.get(1), row.get(2));
    let sql = format!(
        "INSERT INTO {} (frame_id, seq, write_id, record, features, thumb) VALUES ($1, $2, $3, $4, $5, $6)",
        frames_table(tbl)
    );
    let insert = tx.prepare(&sql).await.map_err(pg_error)?;
    let sql = format!("INSERT INTO {} (query_frame, match_frame, record) VALUES ($1, $2, $3)", loops_table(tbl));
    let insert_loop = tx.prepare(&sql).await.map_err(pg_error)?;
    // Idempotency keys (`keys.rs`), looked up under the session row's lock: a write sent again
    // through any node, or after a commit whose answer was lost, finds the first one.
    let group_keys: Vec<&str> = group.iter().filter_map(|r| keyed(r).map(|(_, k)| k)).collect();
    let mut known: HashMap<String, (i64, String, f64)> = HashMap::new();
    let insert_key = match group_keys.is_empty() {
        true => None,
        false => {
            let sql = "SELECT key, frame_id, robot_id, stamp FROM loopd_frame_keys WHERE tbl = $1 AND key = ANY($2)";
            for row in tx.query(sql, &[&tbl, &group_keys]).await.map_err(pg_error)? {
                known.insert(row.get(0), (row.get(1), row.get(2), row.get(3)));
            }
            let sql = "INSERT INTO loopd_frame_keys (tbl, key, frame_id, robot_id, stamp) VALUES ($1, $2, $3, $4, $5)";
            Some(tx.prepare(sql).await.map_err(pg_error)?)
        }
    };
    let write_id: i64 = rand::random();
    let mut answers = Vec::with_capacity(group.len());
    for r in group {
        let (version_before, next_before) = (version, next);
        let key = keyed(r);
        if let Some((f, key)) = key {
            if let Some((id, robot, stamp)) = known.get(key) {
                // Stored before (or earlier in this transaction): its id, nothing stored.
                answers.push(match *robot == f.robot_id && stamp.to_bits() == f.timestamp.to_bits() {
                    true => Ok(Appended { ids: vec![*id as u64], version, replayed: true }),
                    false => Err(super::keys::reused(key, *id as u64, robot, *stamp, f)),
                });
                continue;
            }
        }
        tx.batch_execute("SAVEPOINT request").await.map_err(pg_error)?;
        // Rows first (ids, seqs, records), then their INSERTs pipelined on the connection.
        let mut rows = Vec::with_capacity(r.frames.len());
        let mut refused = None;
        for f in &r.frames {
            let Ok(id) = f.frame_id.map_or(Ok(next), i64::try_from) else {
                refused = Some(StoreError::InvalidArgument("frame id is above 2^63 - 1".into()));
                break;
            };
            next = next.max(id.saturating_add(1));
            version += 1;
            let header = f.header();
            rows.push((id, version, encode_frame(&header, &f.descriptor, r.storage), f));
        }
        let mut ids = Vec::with_capacity(rows.len());
        if refused.is_none() {
            let params: Vec<[&(dyn ToSql + Sync); 6]> = rows
                .iter()
                .map(|(id, seq, record, f)| {
                    [id as &(dyn ToSql + Sync), seq, &write_id, record, &f.features, &f.thumbnail]
                })
                .collect();
            let inserts = params.iter().map(|p| tx.execute(&insert, p));
            for (result, (id, _, _, _)) in futures::future::join_all(inserts).await.into_iter().zip(&rows) {
                match result {
                    Ok(_) => ids.push(*id as u64),
                    Err(e) if e.code() == Some(&SqlState::UNIQUE_VIOLATION) => {
                        refused.get_or_insert(StoreError::FrameExists(session.into(), *id as u64));
                    }
                    // The statements after a refused one fail as the transaction is aborted.
                    Err(e) if e.code() == Some(&SqlState::IN_FAILED_SQL_TRANSACTION) && refused.is_some() => {}
                    Err(e) => return Err(pg_error(e)),
                }
            }
        }
        if let (None, Some((f, key)), Some(insert_key), Some(&id)) = (&refused, key, &insert_key, ids.first()) {
            let id = id as i64;
            tx.execute(insert_key, &[&tbl, &key, &id, &f.robot_id, &f.timestamp]).await.map_err(pg_error)?;
            known.insert(key.to_string(), (id, f.robot_id.clone(), f.timestamp));
        }
        if refused.is_none() && !r.loops.is_empty() {
            // The loops answered for these frames, in the same savepoint: kept exactly when they are.
            let rows = r.loops.iter().map(|(at, l)| loop_row(ids[*at], l)).collect::<Result<Vec<_>, _>>()?;
            let params: Vec<[&(dyn ToSql + Sync); 3]> =
                rows.iter().map(|(q, m, json)| [q as &(dyn ToSql + Sync), m, json]).collect();
            let inserts = params.iter().map(|p| tx.execute(&insert_loop, p));
            for result in futures::future::join_all(inserts).await {
                result.map_err(pg_error)?;
            }
        }
        match refused {
            // This request's frames go; the others' stay.
            Some(e) => {
                tx.batch_execute("ROLLBACK TO SAVEPOINT request").await.map_err(pg_error)?;
                (version, next) = (version_before, next_before);
                answers.push(Err(e));
            }
            None => {
                tx.batch_execute("RELEASE SAVEPOINT request").await.map_err(pg_error)?;
                answers.push(Ok(Appended { ids, version, replayed: false }));
            }
        }
    }
    tx.execute(
        "UPDATE loopd_sessions SET version = $2, next_frame_id = $3 WHERE id = $1",
        &[&session, &version, &next],
    )
    .await
    .map_err(pg_error)?;
    tx.commit().await.map_err(pg_error)?;
    Ok(answers)
}
