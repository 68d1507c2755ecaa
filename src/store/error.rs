//! What the store answers when it cannot: one error type for both backends, with what each
//! lower layer's failure becomes.
use super::health;
use crate::index::query;

#[derive(Clone, Debug, thiserror::Error, PartialEq)]
pub enum StoreError {
    #[error("session '{0}' not found")]
    SessionNotFound(String),
    #[error("frame {1} not found in session '{0}'")]
    FrameNotFound(String, u64),
    #[error("session '{0}' already exists")]
    SessionExists(String),
    #[error("frame {1} already exists in session '{0}'")]
    FrameExists(String, u64),
    /// An idempotency key sent again with another frame.
    #[error("{0}")]
    KeyReused(String),
    #[error("{0}")]
    LoopNotFound(String),
    #[error("{0}")]
    InvalidArgument(String),
    #[error("storage failure: {0}")]
    Storage(String),
    #[error("search pool stopped")]
    Stopped,
    /// Writes cannot succeed now (a storage failure not yet recovered, or a reopen under way).
    #[error("{0}")]
    Unavailable(String),
}

impl From<query::InvalidQuery> for StoreError {
    fn from(e: query::InvalidQuery) -> Self {
        StoreError::InvalidArgument(e.0)
    }
}

impl From<crate::index::InvalidDescriptor> for StoreError {
    fn from(e: crate::index::InvalidDescriptor) -> Self {
        StoreError::InvalidArgument(e.0.into())
    }
}

impl From<sled::Error> for StoreError {
    fn from(e: sled::Error) -> Self {
        StoreError::Storage(health::describe(&e))
    }
}
