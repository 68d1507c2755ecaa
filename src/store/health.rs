//! Whether the store can take writes: the storage failure they are refused for, and sled's
//! errors as a person reads them.
use super::StoreError;
use parking_lot::Mutex;

/// A sled error as a person reads it ("No space left on device (os error 28)", not sled's Debug
/// form of the I/O error).
pub fn describe(e: &sled::Error) -> String {
    match e {
        sled::Error::Io(io) => format!("I/O error: {io}"),
        e => e.to_string(),
    }
}

/// The storage failure writes are refused for, if any (set by the flusher or a failed write,
/// cleared by a successful reopen).
#[derive(Default)]
pub struct Health {
    failure: Mutex<Option<String>>,
}

impl Health {
    pub fn fail(&self, error: &str) {
        let mut f = self.failure.lock();
        if f.is_none() {
            tracing::error!(error, "storage failed: writes are refused until the store is reopened");
        }
        *f = Some(error.to_string());
    }

    pub fn clear(&self) {
        if self.failure.lock().take().is_some() {
            tracing::info!("storage recovered: writes accepted again");
        }
    }

    pub fn failure(&self) -> Option<String> {
        self.failure.lock().clone()
    }

    /// Ok while writes can succeed; else the error a write gets at once (without touching a
    /// database that would fail it anyway).
    pub fn writable(&self) -> Result<(), StoreError> {
        match self.failure() {
            None => Ok(()),
            Some(e) => Err(StoreError::Unavailable(format!(
                "storage failed ({e}); writes are refused until it recovers (retry later)"
            ))),
        }
    }
}
