//! Network APIs over the engine and the store: gRPC and HTTP, one shared service.
pub mod conn;
pub mod error;
pub mod grpc;
pub mod grpc_admin;
pub mod http;
pub mod jobs;
pub mod server;
pub mod service;
pub mod tenancy;
pub mod tls;
