//! loopd's integration tests: one binary (built and linked once), one module per area, each
//! against the real parts (the server on loopback, sled, PostgreSQL, real images from
//! `../shared/data`). `scripts/dev test` runs them: everything but the tests that must run
//! alone first, then those alone (see `ALONE` there), and the cluster area through
//! `scripts/pg-replicated` (its tests are `#[ignore]`d: they need that database).
//!
//! * `api`: both transports of a running server (gRPC, HTTP, TLS, tenants, kept loops, inspector)
//! * `cluster`: the frame log on a replicated PostgreSQL, cluster nodes, failover
//! * `eval`: ground-truth files
//! * `model`: the network against PyTorch, the batching engine, bad images
//! * `reliability`: shutdown, overload, kill -9 cycles, a full disk
//! * `store`: sessions on sled, search, the search pool
//! * `train`: training steps against PyTorch, shipped heads
//! * `verify`: features, geometric and sequence verification, through the server
//! * `common`: builders and helpers the areas share
mod api;
mod cluster;
mod common;
mod eval;
mod model;
mod reliability;
mod store;
mod train;
mod verify;
