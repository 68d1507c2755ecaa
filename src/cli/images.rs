//! Reading image files for the CLI, one error per bad file without stopping the rest.
use crate::model::config::Preprocess;
use crate::model::preprocess::{prepare, ImageLimits};
use anyhow::Result;
use std::path::Path;
use tch::Tensor;

/// Preprocessed input of one file, or why it could not be read.
pub fn load(path: &Path, p: &Preprocess) -> Result<Tensor> {
    let bytes = std::fs::read(path)?;
    Ok(prepare(&bytes, &ImageLimits::default(), p)?)
}
