//! loopd: loop-closure detection as a service.
//!
//! Layers, dependencies pointing one way: `api` -> `engine` -> `model`, `store`; `verify` (local
//! features and geometry) is used by `api` and `eval`; `train` (heads, whitening) uses `eval`;
//! `export` (a session's loop graph as files) is used by `api`; `bags` (ROS bags to frames) by
//! `api` and `cli`; `inspect` (thumbnails, similarity matrix, the inspector page) by `api`.
pub mod api;
pub mod auth;
pub mod bags;
pub mod cli;
pub mod engine;
pub mod eval;
pub mod export;
pub mod files;
pub mod inspect;
pub mod model;
pub mod pb;
pub mod store;
pub mod train;
pub mod verify;
