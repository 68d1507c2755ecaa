//! Offline sequence jobs' records (their status as JSON), kept in sled beside the sessions so a
//! job still answers after a restart.
use super::{Store, StoreError};

impl Store {
    /// Keeps a job's record; durable with the next group commit (or `durable_jobs`).
    pub fn put_job(&self, id: &str, record: &[u8]) -> Result<(), StoreError> {
        let r = self.disk()?.jobs.insert(id.as_bytes(), record).map(drop);
        self.note(r)
    }

    /// Every job record, by id.
    pub fn jobs(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        let disk = self.disk()?;
        disk.jobs
            .iter()
            .map(|kv| {
                let (k, v) = kv?;
                Ok((String::from_utf8_lossy(&k).to_string(), v.to_vec()))
            })
            .collect()
    }

    pub fn remove_job(&self, id: &str) -> Result<(), StoreError> {
        let r = self.disk()?.jobs.remove(id.as_bytes()).map(drop);
        self.note(r)
    }

    /// Everything written before, job and tenant records included, is on disk.
    pub async fn durable_jobs(&self) -> Result<(), StoreError> {
        self.durable().await
    }
}
