//! Training the paper's attention and fusion heads (and learned whitening) on real data.
pub mod augment;
pub mod data;
pub mod loss;
pub mod run;
pub mod sampler;
pub mod whiten;
