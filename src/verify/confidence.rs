//! One calibrated confidence per answered candidate: an estimate of P(true loop) from what the
//! server knows when it answers (the cosine, its margin over the best candidate elsewhere on the
//! map, the geometric check's inliers and inlier ratio, the sequence check's margin, and which
//! checks ran), so that one threshold means the same thing from one query to the next.
//!
//! The model is a logistic regression on [`Evidence::features`], fitted on candidates of training
//! sets only (`loopd eval --samples-out`, then `loopd calibrate`), with every weight on a piece of
//! evidence for a loop held non-negative: more inliers, a larger margin or a higher cosine never
//! lower the confidence (monotone), and a check that ran and found nothing lowers it through its
//! own intercept. Why logistic and not isotonic regression: a handful of features, few positives
//! per set, and the need to carry across sets; isotonic regression on one combined score would
//! need that score first and overfits its steps to the training sets (docs/evaluation.md).
//!
//! Calibrators are kept per descriptor space (`models/calibration.json`): a calibrator fitted for
//! one model is never applied to another's descriptors.
use serde::{Deserialize, Serialize};
use std::path::Path;

/// What a candidate's confidence is computed from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Evidence {
    /// Cosine similarity of the descriptors.
    pub cosine: f32,
    /// The cosine minus the best cosine of the candidates elsewhere on the map (another robot, or
    /// more than [`super::SEQUENCE_WINDOW`] positions away on the trajectory); when every candidate
    /// is at one place, minus the lowest candidate's (a lower bound on the margin).
    pub margin: f32,
    /// Geometric verification ran on both frames' features: (inliers, inlier ratio).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub geometric: Option<(u32, f32)>,
    /// Sequence verification ran: (margin, frames compared / L).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sequence: Option<(f32, f32)>,
}

/// One answered candidate of a training set, with its ground truth (`loopd eval --samples-out`
/// writes them, one JSON line each).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    #[serde(flatten)]
    pub evidence: Evidence,
    /// The ground truth says this candidate closes a loop with the query.
    pub truth: bool,
    /// The query's first candidate (what a loop detector answers; R@100P counts these).
    pub best: bool,
}

/// Length of [`Evidence::features`].
pub const FEATURES: usize = 7;

/// The features' names, in order (reports and the calibration file).
pub const FEATURE_NAMES: [&str; FEATURES] = [
    "cosine",
    "margin",
    "geometric_ran",
    "ln_1p_inliers",
    "inlier_ratio",
    "sequence_margin",
    "sequence_margin_x_coverage",
];

/// Features whose weight is held >= 0 (evidence for a loop); the other is an intercept: a
/// geometric check that ran and found nothing is evidence against. Sequence checks have no
/// intercept of their own: it would learn the training sets' share of right answers among
/// sequence-checked queries (a base rate, not evidence), and carry it to every other set.
const MONOTONE: [bool; FEATURES] = [true, true, false, true, true, true, true];

impl Evidence {
    pub fn features(&self) -> [f64; FEATURES] {
        let (g, inliers, ratio) = match self.geometric {
            Some((i, r)) => (1.0, (i as f64).ln_1p(), r as f64),
            None => (0.0, 0.0, 0.0),
        };
        let (margin, covered) = match self.sequence {
            Some((m, c)) => (m as f64, (m as f64) * (c as f64).clamp(0.0, 1.0)),
            None => (0.0, 0.0),
        };
        [self.cosine as f64, self.margin as f64, g, inliers, ratio, margin, covered]
    }
}

/// The best cosine among `others` that are not at the candidate's place, for [`Evidence::margin`]:
/// `near(i, j)` says whether candidates i and j are one place.
pub fn cosine_margins(cosines: &[f32], near: impl Fn(usize, usize) -> bool) -> Vec<f32> {
    let lowest = cosines.iter().copied().fold(f32::INFINITY, f32::min);
    (0..cosines.len())
        .map(|i| {
            let rival = (0..cosines.len())
                .filter(|&j| j != i && !near(i, j))
                .map(|j| cosines[j])
                .fold(f32::NEG_INFINITY, f32::max);
            let rival = if rival.is_finite() { rival } else { lowest.min(cosines[i]) };
            cosines[i] - rival
        })
        .collect()
}

/// A fitted confidence for one descriptor space.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Calibrator {
    /// The descriptor space it was fitted on (a session's `descriptor_id`).
    pub descriptor_id: String,
    /// One weight per feature ([`FEATURE_NAMES`]), then the bias.
    pub weights: Vec<f64>,
    pub bias: f64,
    /// The lowest confidence at which every training query's first candidate at or above it was
    /// a true loop, rounded up to 0.01: what jobs, the loop inspector and exports accept by default.
    pub loop_confidence: f32,
    /// The training sets (names) and their candidates.
    pub trained_on: Vec<String>,
    pub samples: usize,
    pub positives: usize,
}

/// `models/calibration.json`: the calibrators loopd ships, one per descriptor space.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CalibrationFile {
    pub format: String,
    pub features: Vec<String>,
    pub calibrators: Vec<Calibrator>,
}

pub const FORMAT: &str = "loopd-calibration/1";

/// The calibration file loopd ships (docs/evaluation.md: how it was fitted).
pub const SHIPPED: &str = "models/calibration.json";

/// Where a server or `loopd eval` takes its calibrator from (`--calibration`).
#[derive(Clone, Debug, PartialEq)]
pub enum Calibration {
    /// No confidence at all (`none`).
    Off,
    /// The shipped file: a model it has no calibrator for (another input size, say) answers
    /// without confidence, with a warning.
    Shipped(std::path::PathBuf),
    /// A file given on purpose: it must hold a calibrator for this model.
    File(std::path::PathBuf),
}

impl Calibration {
    pub fn parse(s: &str) -> Self {
        match s {
            "none" | "" => Self::Off,
            s if s == SHIPPED => Self::Shipped(s.into()),
            s => Self::File(s.into()),
        }
    }

    /// The calibrator for `descriptor_id` (a model's descriptor space), if any.
    pub fn resolve(&self, descriptor_id: &str) -> Result<Option<Calibrator>, CalibrationError> {
        match self {
            Self::Off => Ok(None),
            Self::File(p) => Ok(Some(CalibrationFile::read(p)?.for_descriptors(p, descriptor_id)?)),
            Self::Shipped(p) => match CalibrationFile::read(p).and_then(|f| f.for_descriptors(p, descriptor_id)) {
                Ok(c) => Ok(Some(c)),
                Err(e) => {
                    tracing::warn!(error = %e, "no calibrated confidence: answers carry none");
                    Ok(None)
                }
            },
        }
    }
}

impl Calibration {
    /// The calibrator for another served model's descriptor space (`serve --models`): the same
    /// file's, when it holds one; otherwise none, said once in the log (the file is the default
    /// model's, and need not cover every other model).
    pub fn resolve_other(&self, model: &str, descriptor_id: &str) -> Option<Calibrator> {
        let path = match self {
            Self::Off => return None,
            Self::File(p) | Self::Shipped(p) => p,
        };
        match CalibrationFile::read(path).and_then(|f| f.for_descriptors(path, descriptor_id)) {
            Ok(c) => Some(c),
            Err(e) => {
                tracing::info!(model, descriptor_id, reason = %e, "no calibrated confidence for this model: its answers carry none");
                None
            }
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    #[error("reading {0}: {1}")]
    Read(String, std::io::Error),
    #[error("{0} is not a calibration file ({FORMAT}): {1}")]
    Parse(String, String),
    #[error(
        "{file} holds calibrators for {have:?}, none for this server's descriptors ({want}): fit one with \
         `loopd calibrate` or start with --calibration none (answers then carry no confidence)"
    )]
    OtherModel { file: String, have: Vec<String>, want: String },
}

impl Calibrator {
    /// P(true loop) for this evidence.
    pub fn confidence(&self, e: &Evidence) -> f32 {
        let x = e.features();
        let z = self.bias + x.iter().zip(&self.weights).map(|(a, w)| a * w).sum::<f64>();
        (1.0 / (1.0 + (-z).exp())) as f32
    }

    /// Logistic regression by Newton's method (a tiny ridge, 1e-6 per sample, keeps the solve
    /// well posed), the weights of evidence features projected onto >= 0 after each step;
    /// `loop_confidence` from the fitted scores.
    pub fn fit(
        descriptor_id: &str,
        samples: &[Sample],
        trained_on: Vec<String>,
    ) -> Result<Self, super::error::VerifyError> {
        let positives = samples.iter().filter(|s| s.truth).count();
        if positives == 0 || positives == samples.len() {
            return Err(super::error::VerifyError::Invalid(format!(
                "{} samples, {positives} positive: a fit needs both kinds",
                samples.len()
            )));
        }
        const D: usize = FEATURES + 1;
        let rows: Vec<([f64; D], f64)> = samples
            .iter()
            .map(|s| {
                let f = s.evidence.features();
                let mut x = [1.0; D];
                x[..FEATURES].copy_from_slice(&f);
                (x, if s.truth { 1.0 } else { 0.0 })
            })
            .collect();
        let mut w = [0f64; D];
        let ridge = 1e-6 * rows.len() as f64;
        let mut free = [true; D];
        for _ in 0..100 {
            let mut grad = [0f64; D];
            let mut hess = [[0f64; D]; D];
            for (x, y) in &rows {
                let z: f64 = x.iter().zip(&w).map(|(a, b)| a * b).sum();
                let p = 1.0 / (1.0 + (-z).exp());
                for i in 0..D {
                    grad[i] += (p - y) * x[i];
                    for j in 0..D {
                        hess[i][j] += p * (1.0 - p) * x[i] * x[j];
                    }
                }
            }
            for i in 0..FEATURES {
                grad[i] += ridge * w[i];
                hess[i][i] += ridge;
            }
            // Active set: a monotone weight at 0 whose gradient pushes it below 0 stays at 0.
            for i in 0..FEATURES {
                free[i] = !(MONOTONE[i] && w[i] <= 0.0 && grad[i] > 0.0);
            }
            let idx: Vec<usize> = (0..D).filter(|&i| free[i]).collect();
            let n = idx.len();
            let mut a = nalgebra::DMatrix::<f64>::zeros(n, n);
            let mut b = nalgebra::DVector::<f64>::zeros(n);
            for (r, &i) in idx.iter().enumerate() {
                b[r] = grad[i];
                for (c, &j) in idx.iter().enumerate() {
                    a[(r, c)] = hess[i][j];
                }
                a[(r, r)] += 1e-9;
            }
            let step = a
                .cholesky()
                .ok_or_else(|| super::error::VerifyError::Failed("the fit's Hessian is singular".into()))?
                .solve(&b);
            let mut change = 0f64;
            for (r, &i) in idx.iter().enumerate() {
                let mut next = w[i] - step[r];
                if i < FEATURES && MONOTONE[i] && next < 0.0 {
                    next = 0.0;
                }
                change = change.max((next - w[i]).abs());
                w[i] = next;
            }
            if change < 1e-9 {
                break;
            }
        }
        let mut c = Calibrator {
            descriptor_id: descriptor_id.to_string(),
            weights: w[..FEATURES].to_vec(),
            bias: w[FEATURES],
            loop_confidence: 1.0,
            trained_on,
            samples: samples.len(),
            positives,
        };
        // The lowest threshold with no false first candidate at or above it.
        let top_false =
            samples.iter().filter(|s| s.best && !s.truth).map(|s| c.confidence(&s.evidence)).fold(0f32, f32::max);
        c.loop_confidence = ((top_false * 100.0).floor() + 1.0).min(100.0) / 100.0;
        Ok(c)
    }
}

impl CalibrationFile {
    pub fn read(path: &Path) -> Result<Self, CalibrationError> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| CalibrationError::Read(name.clone(), e))?;
        let f: CalibrationFile =
            serde_json::from_str(&text).map_err(|e| CalibrationError::Parse(name.clone(), e.to_string()))?;
        if f.format != FORMAT {
            return Err(CalibrationError::Parse(name, format!("format '{}'", f.format)));
        }
        if f.features != FEATURE_NAMES {
            return Err(CalibrationError::Parse(
                name,
                format!("features {:?}, this loopd has {FEATURE_NAMES:?}", f.features),
            ));
        }
        if let Some(c) = f.calibrators.iter().find(|c| c.weights.len() != FEATURES) {
            return Err(CalibrationError::Parse(name, format!("{} weights for {}", c.weights.len(), c.descriptor_id)));
        }
        Ok(f)
    }

    /// The calibrator of one descriptor space, or why there is none.
    pub fn for_descriptors(&self, path: &Path, descriptor_id: &str) -> Result<Calibrator, CalibrationError> {
        self.calibrators.iter().find(|c| c.descriptor_id == descriptor_id).cloned().ok_or_else(|| {
            CalibrationError::OtherModel {
                file: path.display().to_string(),
                have: self.calibrators.iter().map(|c| c.descriptor_id.clone()).collect(),
                want: descriptor_id.to_string(),
            }
        })
    }

    /// This file with `c` in place of the calibrator of its descriptor space (or added).
    pub fn with(mut self, c: Calibrator) -> Self {
        self.format = FORMAT.to_string();
        self.features = FEATURE_NAMES.iter().map(|s| s.to_string()).collect();
        self.calibrators.retain(|x| x.descriptor_id != c.descriptor_id);
        self.calibrators.push(c);
        self.calibrators.sort_by(|a, b| a.descriptor_id.cmp(&b.descriptor_id));
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn e(cosine: f32, inliers: Option<u32>) -> Evidence {
        Evidence { cosine, margin: 0.0, geometric: inliers.map(|i| (i, 0.5)), sequence: None }
    }

    fn s(evidence: Evidence, truth: bool) -> Sample {
        Sample { evidence, truth, best: true }
    }

    #[test]
    fn the_fit_is_monotone_and_separates_what_the_training_data_separates() {
        // Loops: high cosine and many inliers; non-loops: lower cosine, few inliers.
        let mut samples = Vec::new();
        for i in 0..40 {
            let t = i as f32 / 40.0;
            samples.push(s(e(0.8 + 0.1 * t, Some(60 + i)), true));
            samples.push(s(e(0.6 + 0.25 * t, Some(i % 12)), false));
            samples.push(s(e(0.5 + 0.3 * t, None), false));
        }
        let c = Calibrator::fit("d", &samples, vec!["s".into()]).unwrap();
        for (i, w) in c.weights.iter().enumerate() {
            assert!(!MONOTONE[i] || *w >= 0.0, "weight {} is {w}", FEATURE_NAMES[i]);
        }
        assert!(c.confidence(&e(0.85, Some(80))) > 0.9);
        assert!(c.confidence(&e(0.85, Some(3))) < 0.2);
        // More inliers never lowers the confidence.
        let mut last = 0.0;
        for inliers in [0, 5, 20, 40, 100] {
            let p = c.confidence(&e(0.8, Some(inliers)));
            assert!(p >= last);
            last = p;
        }
        assert!(c.loop_confidence > 0.0 && c.loop_confidence <= 1.0);
        assert!(samples.iter().filter(|x| !x.truth).all(|x| c.confidence(&x.evidence) < c.loop_confidence));
        assert!(Calibrator::fit("d", &samples[..1], vec![]).is_err());
    }

    #[test]
    fn margins_are_over_the_best_candidate_elsewhere() {
        let m = cosine_margins(&[0.9, 0.88, 0.7, 0.6], |i, j| (i < 2) == (j < 2));
        assert!((m[0] - 0.2).abs() < 1e-6 && (m[1] - 0.18).abs() < 1e-6);
        assert!((m[2] - (0.7 - 0.9)).abs() < 1e-6);
        // All at one place: over the lowest.
        let m = cosine_margins(&[0.9, 0.8], |_, _| true);
        assert!((m[0] - 0.1).abs() < 1e-6 && m[1].abs() < 1e-6);
    }
}
