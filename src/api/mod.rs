//! Network APIs over the engine and the store: gRPC and HTTP, one shared service.
pub mod conn;
pub mod error;
pub mod grpc;
pub mod grpc_admin;
pub mod grpc_loops;
pub mod http;
pub mod http_inspect;
pub mod http_loops;
pub mod inspect;
pub mod jobs;
pub mod loops;
pub mod server;
pub mod service;
pub mod tenancy;
pub mod tls;
