//! loopd: loop-closure detection as a service.
//!
//! # Layout
//!
//! One folder per layer; each imports only the layers below it (checked with the import graph of
//! `src/`: no circle, no arrow running back up).
//!
//! - `cli/`: one file per subcommand; the top. `serve` wires the server, the rest are offline
//!   tools or remote clients.
//! - `client/`: the one client of the remote subcommands (export, ingest, tenant, eval
//!   --server): address, key, CA, client certificate; HTTP and gRPC. Reads the wire types of
//!   `api::wire` and `pb`, nothing else of the server.
//! - `ros2/`: `loopd ros2`, the ROS 2 bridge node (ros2-client): camera topics in, keyframes to a
//!   server through `client/`'s gRPC client, loop closures out; decodes pixels with `bags/`.
//! - `train/`: the paper's attention and fusion heads and learned whitening on real data; uses
//!   `eval` for its validation.
//! - `eval/`: `loopd eval` (recall at 100% precision, recall@1, AP, the confidence sweep, plots);
//!   runs the same search and checks as the server (`index`, `verify::check`).
//! - `api/`: the network service. `service/` is what both transports do, written once;
//!   `http/` (axum: handlers by resource, each carrying its part of the OpenAPI document, and the
//!   router built from them) and `grpc/` (tonic) only translate, and neither
//!   imports the other; `wire.rs` holds what both read alike; `tenancy.rs` scopes every call to
//!   the caller's tenant; `jobs.rs` runs offline sequence jobs (owned by the server, calling the
//!   service); `kept.rs` and `loops.rs` the kept loop candidates; `server.rs` the wiring and
//!   `watch.rs` what runs beside the calls.
//! - `engine/`: the inference engine, every frame's way to the one model thread.
//! - `verify/`: local features, geometric and sequence checks, the one decision rule and the
//!   calibrated confidence; reads `index`'s matches and `store`'s records, never the reverse.
//! - `auth/`: API keys, tenants, quotas and the admin key.
//! - `export/`: a session's loop graph as files a SLAM back end reads.
//! - `inspect/`: thumbnails, the similarity matrix and the loop inspector page.
//! - `store/`: persistence: sessions on sled (or the PostgreSQL cluster's log, sled its cache),
//!   their frames, features, thumbnails and kept loops; fills each session's index from its
//!   records, and its approximate index in the background (`indexer.rs`, which also saves it).
//! - `index/`: search: a session's rows in memory, exact scores (host SIMD kernels or a libtorch
//!   device) or the approximate index's candidates re-scored exactly (`graph.rs`, `approx.rs`),
//!   the query options and matches, the sequence trails and votes; imports no other layer.
//! - `model/`: the descriptor network, weights, preprocessing.
//! - `bags/`: ROS 1 and rosbag2 bags to frames.
//! - `files.rs`, `pb.rs`: image file listings; the generated gRPC types.
pub mod api;
pub mod auth;
pub mod bags;
pub mod cli;
pub mod client;
pub mod engine;
pub mod eval;
pub mod export;
pub mod files;
pub mod index;
pub mod inspect;
pub mod model;
pub mod pb;
pub mod ros2;
pub mod store;
pub mod train;
pub mod verify;
