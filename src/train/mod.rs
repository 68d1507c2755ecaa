//! Training the paper's attention and fusion heads (and learned whitening) on real data.
pub mod augment;
pub mod checkpoint;
pub mod data;
pub mod loss;
pub mod run;
pub mod sampler;
pub mod spec;
pub mod validate;
pub mod whiten;
