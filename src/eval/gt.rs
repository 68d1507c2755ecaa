//! Loop-closure ground truth in the forms found in `../shared/data`.
use super::matfile::read_matrix;
use anyhow::{bail, Context, Result};
use std::collections::{BTreeSet, HashMap};
use std::path::Path;

/// For each query frame, the reference frames it truly matches.
/// One sequence: query and reference indices are frames of the same sequence (ref < query).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GroundTruth {
    pub loops: HashMap<usize, BTreeSet<usize>>,
}

impl GroundTruth {
    pub fn pairs(&self) -> usize {
        self.loops.values().map(BTreeSet::len).sum()
    }

    pub fn is_match(&self, query: usize, reference: usize, tolerance: usize) -> bool {
        self.loops.get(&query).is_some_and(|refs| {
            refs.range(reference.saturating_sub(tolerance)..=reference + tolerance).next().is_some()
        })
    }

    pub fn has_loop(&self, query: usize) -> bool {
        self.loops.get(&query).is_some_and(|r| !r.is_empty())
    }

    fn add(&mut self, q: usize, r: usize) {
        self.loops.entry(q).or_default().insert(r);
    }

    /// `gt[i][j] = 1` (i > j) of a MATLAB v5 matrix. `camera`: `Some(0|1)` keeps every second
    /// row and column starting there (New College's interleaved left/right images).
    pub fn from_mat(path: &Path, camera: Option<usize>) -> Result<Self> {
        let m = read_matrix(&std::fs::read(path).with_context(|| format!("reading {}", path.display()))?)
            .with_context(|| format!("parsing {}", path.display()))?;
        let mut gt = GroundTruth::default();
        for (i, j) in m.nonzero {
            if i <= j {
                continue; // only "frame i closes a loop with earlier frame j"
            }
            match camera {
                None => gt.add(i, j),
                Some(c) if i % 2 == c && j % 2 == c => gt.add(i / 2, j / 2),
                Some(_) => {}
            }
        }
        Ok(gt)
    }

    /// CSV: a header line, then `query,ref` pairs or `query,ref ref ref` lists (0-based).
    pub fn from_csv(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        Self::parse_csv(&text, path)
    }

    /// As [`GroundTruth::from_csv`], from the file's text (`path` names it in errors).
    pub fn parse_csv(text: &str, path: &Path) -> Result<Self> {
        let mut gt = GroundTruth::default();
        for (n, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || (n == 0 && !line.starts_with(|c: char| c.is_ascii_digit())) {
                continue;
            }
            let (q, refs) =
                line.split_once(',').with_context(|| format!("{}:{}: expected query,ref", path.display(), n + 1))?;
            let q: usize =
                q.trim().parse().with_context(|| format!("{}:{}: bad query index", path.display(), n + 1))?;
            for r in refs.split_whitespace() {
                gt.add(q, r.parse().with_context(|| format!("{}:{}: bad reference index", path.display(), n + 1))?);
            }
        }
        Ok(gt)
    }

    /// Two aligned traversals: query i matches reference i (tolerance applied at scoring).
    pub fn aligned(n: usize) -> Self {
        let mut gt = GroundTruth::default();
        (0..n).for_each(|i| gt.add(i, i));
        gt
    }

    /// The loops among frames `range` of both sequences, renumbered from 0.
    pub fn window(&self, range: &std::ops::Range<usize>) -> Self {
        let mut gt = GroundTruth::default();
        for (&q, refs) in &self.loops {
            for &r in refs {
                if range.contains(&q) && range.contains(&r) {
                    gt.add(q - range.start, r - range.start);
                }
            }
        }
        gt
    }

    pub fn load(spec: &str, camera: Option<usize>, frames: usize) -> Result<Self> {
        if spec == "aligned" {
            return Ok(Self::aligned(frames));
        }
        let p = Path::new(spec);
        match p.extension().and_then(|e| e.to_str()) {
            Some("mat") => Self::from_mat(p, camera),
            Some("csv") | Some("txt") => Self::from_csv(p),
            _ => bail!("ground truth '{spec}': expected a .mat or .csv file, or 'aligned'"),
        }
    }
}
