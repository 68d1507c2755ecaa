//! Network APIs over the engine and the store: gRPC and HTTP, one shared service.
pub mod conn;
pub mod error;
pub mod grpc;
pub mod http;
pub mod inspect;
pub mod jobs;
pub mod kept;
pub mod loops;
pub mod metrics;
pub mod server;
pub mod service;
pub mod tenancy;
pub mod tls;
mod watch;
pub mod wire;
