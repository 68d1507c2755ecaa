//! Group commit: a write is acknowledged once a flush that started after it has finished.
//!
//! Writers insert into sled, then wait here. One flusher thread takes every waiter queued
//! so far and runs a single `flush()` (one fsync) for all of them, so N robots writing at
//! once cost about one fsync per flush interval instead of N.
use super::health::{describe, Health};
use std::sync::mpsc;
use std::sync::Arc;
use tokio::sync::oneshot;

/// What the flusher runs once a write's flush has finished, before it answers the writer.
pub type AfterFlush = Box<dyn FnOnce(&Result<(), String>) + Send>;

struct Waiter {
    reply: oneshot::Sender<Result<(), String>>,
    after: Option<AfterFlush>,
}

pub struct GroupCommit {
    tx: Option<mpsc::Sender<Waiter>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl GroupCommit {
    /// `health` learns of a failed flush: sled fails every write after one until a reopen.
    pub fn start(db: sled::Db, health: Arc<Health>) -> Self {
        let (tx, rx) = mpsc::channel::<Waiter>();
        let thread = std::thread::Builder::new()
            .name("loopd-flush".into())
            .spawn(move || {
                while let Ok(first) = rx.recv() {
                    let mut waiters = vec![first];
                    waiters.extend(rx.try_iter());
                    // Every waiter's insert happened before it queued, so this flush covers it.
                    let result = db.flush().map(|_| ()).map_err(|e| describe(&e));
                    if let Err(e) = &result {
                        health.fail(e);
                    }
                    for w in waiters {
                        if let Some(after) = w.after {
                            after(&result);
                        }
                        let _ = w.reply.send(result.clone());
                    }
                }
            })
            .expect("spawning the flush thread");
        Self { tx: Some(tx), thread: Some(thread) }
    }

    /// Resolves once everything written before the call is on disk; `after` runs on the flusher
    /// with the flush's result whether or not the caller is still waiting: a write and what must
    /// follow its flush (publishing it to the index) cannot be split by a dropped request.
    pub fn durable_then(&self, after: Option<AfterFlush>) -> impl std::future::Future<Output = Result<(), String>> {
        let (reply, rx) = oneshot::channel();
        // Queued now, not at the first poll: the caller's writes are already in sled.
        let stopped = || "flush thread stopped".to_string();
        let waiter = Waiter { reply, after };
        let queued = match self.tx.as_ref() {
            Some(tx) => tx.send(waiter).map_err(|mpsc::SendError(w)| w),
            None => Err(waiter),
        }
        .map_err(|w| {
            // No flush will come: the follow-up still learns that the write failed.
            if let Some(after) = w.after {
                after(&Err(stopped()));
            }
            stopped()
        });
        async move {
            queued?;
            rx.await.map_err(|_| stopped())?
        }
    }
}

impl Drop for GroupCommit {
    /// Stops the flusher and waits for it, so the database (and its file lock) is released
    /// by the time the store is dropped: a reopen right after must succeed.
    fn drop(&mut self) {
        self.tx.take();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
