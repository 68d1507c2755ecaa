//! Group commit: a write is acknowledged once a flush that started after it has finished.
//!
//! Writers insert into sled, then wait here. One flusher thread takes every waiter queued
//! so far and runs a single `flush()` (one fsync) for all of them, so N robots writing at
//! once cost about one fsync per flush interval instead of N.
use std::sync::mpsc;
use tokio::sync::oneshot;

type Waiter = oneshot::Sender<Result<(), String>>;

pub struct GroupCommit {
    tx: Option<mpsc::Sender<Waiter>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl GroupCommit {
    pub fn start(db: sled::Db) -> Self {
        let (tx, rx) = mpsc::channel::<Waiter>();
        let thread = std::thread::Builder::new()
            .name("loopd-flush".into())
            .spawn(move || {
                while let Ok(first) = rx.recv() {
                    let mut waiters = vec![first];
                    waiters.extend(rx.try_iter());
                    // Every waiter's insert happened before it queued, so this flush covers it.
                    let result = db.flush().map(|_| ()).map_err(|e| e.to_string());
                    for w in waiters {
                        let _ = w.send(result.clone());
                    }
                }
            })
            .expect("spawning the flush thread");
        Self { tx: Some(tx), thread: Some(thread) }
    }

    /// Resolves once everything written before the call is on disk.
    pub async fn durable(&self) -> Result<(), String> {
        let (tx, rx) = oneshot::channel();
        let sender = self.tx.as_ref().ok_or_else(|| "flush thread stopped".to_string())?;
        sender.send(tx).map_err(|_| "flush thread stopped".to_string())?;
        rx.await.map_err(|_| "flush thread stopped".to_string())?
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
