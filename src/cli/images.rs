//! Reading image files for the CLI, one error per bad file without stopping the rest.
use crate::model::config::Preprocess;
use crate::model::preprocess::{prepare, ImageLimits};
use anyhow::Result;
use std::path::{Path, PathBuf};
use tch::Tensor;

/// Preprocessed input of one file, or why it could not be read.
pub fn load(path: &Path, p: &Preprocess) -> Result<Tensor> {
    let bytes = std::fs::read(path)?;
    Ok(prepare(&bytes, &ImageLimits::default(), p)?)
}

/// Consecutive runs of same-size inputs, at most `max` long (one forward pass each).
pub fn same_size_runs(items: &[(PathBuf, Tensor)], max: usize) -> Vec<std::ops::Range<usize>> {
    let mut runs = Vec::new();
    let mut start = 0;
    for i in 1..=items.len() {
        if i == items.len() || i - start == max || items[i].1.size() != items[start].1.size() {
            runs.push(start..i);
            start = i;
        }
    }
    runs.retain(|r| !r.is_empty());
    runs
}
