//! Tenants' records (JSON; a key's hash, never the key), kept in sled beside the sessions.
use super::{Store, StoreError};

impl Store {
    pub fn put_tenant(&self, name: &str, record: &[u8]) -> Result<(), StoreError> {
        let r = self.disk()?.tenants.insert(name.as_bytes(), record).map(drop);
        self.note(r)
    }

    /// Every tenant record, by name.
    pub fn tenants(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        let disk = self.disk()?;
        disk.tenants
            .iter()
            .map(|kv| {
                let (k, v) = kv?;
                Ok((String::from_utf8_lossy(&k).to_string(), v.to_vec()))
            })
            .collect()
    }
}
