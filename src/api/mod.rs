//! Network APIs over the engine (HTTP now; gRPC joins here).
pub mod error;
pub mod http;
