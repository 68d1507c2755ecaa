//! Evaluation on image sequences with loop ground truth: `loopd eval`.
pub mod gt;
pub mod matfile;
pub mod metrics;
pub mod plots;
pub mod remote;
pub mod run;
