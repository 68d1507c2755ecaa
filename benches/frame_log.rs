//! Durable frames per second: the cluster's frame log (PostgreSQL 15, one synchronous standby on
//! loopback, `src/store/pg.rs`) against one sled node (`Store::add_frames`, group commit), side by
//! side, with the same 2,048-d f16 descriptors, from 16 concurrent writers each sending batches
//! of 1 or 16 frames. Run through `scripts/pg-replicated bench` (it starts the database and sets
//! LOOPD_PG_URL).
//!
//! env: LOOPD_BENCH_FRAMES (per case, default 4000)
mod common;
use common::{frame, meta, new_session, WRITERS};
use loopd::store::pg::{LogConfig, PgLog, Replication};
use loopd::store::{NewFrame, Store};
use std::sync::Arc;
use std::time::Instant;

/// Frames/s of `n` frames written by WRITERS tasks in batches of `batch`.
async fn run<F, Fut>(n: usize, batch: usize, write: F) -> f64
where
    F: Fn(Vec<NewFrame>) -> Fut + Clone + Send + 'static,
    Fut: std::future::Future<Output = ()> + Send,
{
    let t = Instant::now();
    let tasks: Vec<_> = (0..WRITERS)
        .map(|w| {
            let write = write.clone();
            tokio::spawn(async move {
                let mine: Vec<usize> = (w..n).step_by(WRITERS).collect();
                for chunk in mine.chunks(batch) {
                    write(chunk.iter().map(|&i| frame(i)).collect()).await;
                }
            })
        })
        .collect();
    for t in tasks {
        t.await.expect("writer");
    }
    n as f64 / t.elapsed().as_secs_f64()
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let n: usize = std::env::var("LOOPD_BENCH_FRAMES").ok().and_then(|v| v.parse().ok()).unwrap_or(4000);
    let url = std::env::var("LOOPD_PG_URL").map_err(|_| anyhow::anyhow!("run through scripts/pg-replicated bench"))?;
    let log = Arc::new(PgLog::connect(&url, LogConfig::new(WRITERS, Replication::Synchronous)).await?);
    let dir = tempfile::tempdir()?;
    let store = Arc::new(Store::open(dir.path())?);
    println!("| writers x batch | frames | PostgreSQL + sync standby frames/s | sled frames/s | PostgreSQL / sled |");
    println!("|---|---:|---:|---:|---:|");
    for batch in [1usize, 16] {
        let id = format!("bench{batch}");
        let m = meta(&id);
        log.create_session(&m).await?;
        store.create_session(Some(id.clone()), new_session(&id)).await?;
        let pg = {
            let (log, m) = (log.clone(), m.clone());
            run(n, batch, move |frames| {
                let (log, m) = (log.clone(), m.clone());
                async move {
                    log.append(&m, &frames).await.expect("append");
                }
            })
            .await
        };
        let session = store.session(&id)?;
        let sled = {
            let store = store.clone();
            run(n, batch, move |frames| {
                let (store, session) = (store.clone(), session.clone());
                async move {
                    store.add_frames(&session, frames).await.expect("add_frames");
                }
            })
            .await
        };
        assert_eq!(log.version(&id).await?, n as i64, "every frame in the log");
        println!("| {WRITERS} x {batch} | {n} | {pg:.0} | {sled:.0} | {:.2} |", pg / sled);
        log.delete_session(&id).await?;
    }
    Ok(())
}
