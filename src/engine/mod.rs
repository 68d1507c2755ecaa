//! The inference engine: one thread owns the model; requests queue up and run in batches.
mod batcher;

pub use batcher::{Engine, EngineConfig, EngineError};
