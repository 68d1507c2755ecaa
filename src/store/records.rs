//! Small JSON records kept in sled beside the sessions: offline sequence jobs (so a job answers
//! after a restart) and tenants (a key's hash, never the key). Durable with the next group commit.
use super::disk::Disk;
use super::{Store, StoreError};

impl Store {
    fn put_record(&self, tree: fn(&Disk) -> &sled::Tree, key: &str, record: &[u8]) -> Result<(), StoreError> {
        let r = tree(&*self.disk()?).insert(key.as_bytes(), record).map(drop);
        self.note(r)
    }

    fn records(&self, tree: fn(&Disk) -> &sled::Tree) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        let disk = self.disk()?;
        tree(&disk)
            .iter()
            .map(|kv| {
                let (k, v) = kv?;
                Ok((String::from_utf8_lossy(&k).to_string(), v.to_vec()))
            })
            .collect()
    }

    pub fn put_job(&self, id: &str, record: &[u8]) -> Result<(), StoreError> {
        self.put_record(|d| &d.jobs, id, record)
    }

    /// Every job record, by id.
    pub fn jobs(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        self.records(|d| &d.jobs)
    }

    pub fn remove_job(&self, id: &str) -> Result<(), StoreError> {
        let r = self.disk()?.jobs.remove(id.as_bytes()).map(drop);
        self.note(r)
    }

    pub fn put_tenant(&self, name: &str, record: &[u8]) -> Result<(), StoreError> {
        self.put_record(|d| &d.tenants, name, record)
    }

    /// This node's tenant records become exactly `records` (a cluster's, from its log).
    pub(super) fn replace_tenants(&self, records: &[(String, Vec<u8>)]) -> Result<(), StoreError> {
        let disk = self.disk()?;
        let mut batch = sled::Batch::default();
        for key in disk.tenants.iter().keys() {
            batch.remove(key?);
        }
        for (name, record) in records {
            batch.insert(name.as_bytes(), record.as_slice());
        }
        let r = disk.tenants.apply_batch(batch);
        self.note(r)
    }

    /// Every tenant record, by name.
    pub fn tenants(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        self.records(|d| &d.tenants)
    }

    /// Everything written before, job and tenant records included, is on disk.
    pub async fn durable_records(&self) -> Result<(), StoreError> {
        self.durable().await
    }
}
