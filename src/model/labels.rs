//! ImageNet class names from the weights package's labels.json ({"0": "tench", ...}).
use anyhow::{bail, Context, Result};
use std::collections::HashMap;
use std::path::Path;

pub fn load(path: &Path) -> Result<Vec<String>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading labels {}", path.display()))?;
    let map: HashMap<String, String> =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    let mut labels = vec![String::new(); map.len()];
    for (k, v) in map {
        let i: usize = k.parse().with_context(|| format!("label key '{k}' is not an index"))?;
        let Some(slot) = labels.get_mut(i) else { bail!("label index {i} out of range") };
        *slot = v;
    }
    if labels.iter().any(String::is_empty) {
        bail!("labels.json has gaps");
    }
    Ok(labels)
}
