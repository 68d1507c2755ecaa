//! The evaluation protocol (docs/evaluation.md): best match per query, threshold sweep,
//! recall at 100% precision, recall@1, average precision.
use super::gt::GroundTruth;
use serde::Serialize;

/// A query frame's best candidate (reference index, score), if it had any candidate.
#[derive(Clone, Copy, Debug)]
pub struct QueryResult {
    pub query: usize,
    pub best: Option<(usize, f32)>,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct PrPoint {
    pub threshold: f32,
    pub precision: f64,
    pub recall: f64,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Report {
    pub queries: usize,
    /// Queries with at least one loop in the ground truth (the recall denominator).
    pub positives: usize,
    pub recall_at_100_precision: f64,
    /// Lowest threshold that keeps precision at 100% (None: even the best-scoring match is wrong).
    pub threshold_at_100_precision: Option<f32>,
    pub recall_at_1: f64,
    pub average_precision: f64,
    pub pr_curve: Vec<PrPoint>,
}

pub fn evaluate(results: &[QueryResult], gt: &GroundTruth, tolerance: usize) -> Report {
    let positives = results.iter().filter(|r| gt.has_loop(r.query)).count();
    let denom = positives.max(1) as f64;
    // Every query's best match is a candidate loop; a threshold accepts those scoring >= it.
    let mut accepted: Vec<(f32, bool)> = results
        .iter()
        .filter_map(|r| r.best.map(|(reference, score)| (score, gt.is_match(r.query, reference, tolerance))))
        .collect();
    accepted.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1))); // on ties, wrong ones first
    let (mut tp, mut fp, mut ap) = (0usize, 0usize, 0f64);
    let mut curve = Vec::new();
    let (mut r100, mut t100) = (0f64, None);
    let mut i = 0;
    while i < accepted.len() {
        // All matches with the same score are accepted together.
        let score = accepted[i].0;
        while i < accepted.len() && accepted[i].0 == score {
            if accepted[i].1 {
                tp += 1;
                ap += tp as f64 / (tp + fp) as f64;
            } else {
                fp += 1;
            }
            i += 1;
        }
        let (precision, recall) = (tp as f64 / (tp + fp) as f64, tp as f64 / denom);
        if fp == 0 {
            r100 = recall;
            t100 = Some(score);
        }
        curve.push(PrPoint { threshold: score, precision, recall });
    }
    let correct_at_1 = results
        .iter()
        .filter(|r| {
            gt.has_loop(r.query) && r.best.is_some_and(|(reference, _)| gt.is_match(r.query, reference, tolerance))
        })
        .count();
    Report {
        queries: results.len(),
        positives,
        recall_at_100_precision: r100,
        threshold_at_100_precision: t100,
        recall_at_1: correct_at_1 as f64 / denom,
        average_precision: ap / denom,
        pr_curve: curve,
    }
}

/// One bin of a reliability diagram: candidates whose confidence fell in [lo, hi).
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct ReliabilityBin {
    pub lo: f32,
    pub hi: f32,
    pub count: usize,
    pub mean_confidence: f64,
    /// The share of them that were true loops.
    pub frequency: f64,
}

/// The protocol swept over the calibrated confidence of each query's first candidate, and how
/// well the confidence is calibrated (docs/evaluation.md).
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct ConfidenceReport {
    pub recall_at_100_precision: f64,
    /// The lowest confidence that keeps precision at 100%.
    pub threshold_at_100_precision: Option<f32>,
    pub recall_at_99_precision: f64,
    /// The confidence of the most confident wrong first candidate: below it precision is no
    /// longer 1 (None: no first candidate was wrong).
    pub first_false_confidence: Option<f32>,
    pub average_precision: f64,
    /// At the calibrator's loop confidence: (threshold, precision, recall).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub at_loop_confidence: Option<(f32, f64, f64)>,
    /// Expected calibration error over every answered candidate (10 equal bins).
    pub expected_calibration_error: f64,
    pub reliability: Vec<ReliabilityBin>,
}

/// `first`: each query's first candidate with its confidence as the score; `candidates`: every
/// answered candidate's (confidence, true loop).
pub fn evaluate_confidence(
    first: &[QueryResult],
    gt: &GroundTruth,
    tolerance: usize,
    candidates: &[(f32, bool)],
    loop_confidence: Option<f32>,
) -> ConfidenceReport {
    let r = evaluate(first, gt, tolerance);
    let r99 = r.pr_curve.iter().filter(|p| p.precision >= 0.99).map(|p| p.recall).fold(0f64, f64::max);
    let first_false = first
        .iter()
        .filter_map(|q| q.best.filter(|&(reference, _)| !gt.is_match(q.query, reference, tolerance)).map(|b| b.1))
        .fold(None, |m: Option<f32>, s| Some(m.map_or(s, |m| m.max(s))));
    let at_loop = loop_confidence.map(|t| {
        let accepted: Vec<bool> = first
            .iter()
            .filter_map(|q| {
                q.best.filter(|b| b.1 >= t).map(|(reference, _)| gt.is_match(q.query, reference, tolerance))
            })
            .collect();
        let tp = accepted.iter().filter(|&&x| x).count();
        let precision = if accepted.is_empty() { 1.0 } else { tp as f64 / accepted.len() as f64 };
        (t, precision, tp as f64 / r.positives.max(1) as f64)
    });
    let mut bins: Vec<ReliabilityBin> = (0..10)
        .map(|b| ReliabilityBin {
            lo: b as f32 / 10.0,
            hi: (b + 1) as f32 / 10.0,
            count: 0,
            mean_confidence: 0.0,
            frequency: 0.0,
        })
        .collect();
    for &(c, truth) in candidates {
        let b = &mut bins[((c * 10.0) as usize).min(9)];
        b.count += 1;
        b.mean_confidence += c as f64;
        b.frequency += truth as u8 as f64;
    }
    let total = candidates.len().max(1) as f64;
    let mut ece = 0.0;
    for b in bins.iter_mut().filter(|b| b.count > 0) {
        b.mean_confidence /= b.count as f64;
        b.frequency /= b.count as f64;
        ece += b.count as f64 / total * (b.mean_confidence - b.frequency).abs();
    }
    ConfidenceReport {
        recall_at_100_precision: r.recall_at_100_precision,
        threshold_at_100_precision: r.threshold_at_100_precision,
        recall_at_99_precision: r99,
        first_false_confidence: first_false,
        average_precision: r.average_precision,
        at_loop_confidence: at_loop,
        expected_calibration_error: ece,
        reliability: bins,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gt(pairs: &[(usize, usize)]) -> GroundTruth {
        let mut g = GroundTruth::default();
        for &(q, r) in pairs {
            g.loops.entry(q).or_default().insert(r);
        }
        g
    }

    fn q(query: usize, reference: usize, score: f32) -> QueryResult {
        QueryResult { query, best: Some((reference, score)) }
    }

    #[test]
    fn hand_worked_case() {
        // Queries 10..=14; loops in the ground truth for 10, 11, 12, 13 (P = 4).
        // Ranked: 0.95 q10 right, 0.90 q11 right, 0.80 q14 wrong (no loop), 0.70 q12 right, 0.60 q13 wrong.
        let g = gt(&[(10, 1), (11, 2), (12, 3), (13, 4)]);
        let r = [q(10, 1, 0.95), q(11, 2, 0.90), q(14, 5, 0.80), q(12, 3, 0.70), q(13, 9, 0.60)];
        let rep = evaluate(&r, &g, 0);
        assert_eq!(rep.positives, 4);
        assert_eq!(rep.recall_at_100_precision, 0.5); // 2 of 4 before the first false loop
        assert_eq!(rep.threshold_at_100_precision, Some(0.90));
        assert_eq!(rep.recall_at_1, 0.75); // q10, q11, q12 right
                                           // AP = (1/1 + 2/2 + 3/4) / 4
        assert!((rep.average_precision - 2.75 / 4.0).abs() < 1e-12);
        assert_eq!(rep.pr_curve.len(), 5);
        assert_eq!(rep.pr_curve[4], PrPoint { threshold: 0.60, precision: 0.6, recall: 0.75 });
    }

    #[test]
    fn false_loop_on_top_gives_zero_and_ties_count_together() {
        let g = gt(&[(5, 1), (6, 2)]);
        let rep = evaluate(&[q(5, 3, 0.99), q(6, 2, 0.5)], &g, 0);
        assert_eq!((rep.recall_at_100_precision, rep.threshold_at_100_precision), (0.0, None));
        // A right and a wrong match with the same score are accepted together: no 100% point there.
        let rep = evaluate(&[q(5, 1, 0.8), q(6, 9, 0.8)], &g, 0);
        assert_eq!(rep.recall_at_100_precision, 0.0);
        assert_eq!(rep.pr_curve, vec![PrPoint { threshold: 0.8, precision: 0.5, recall: 0.5 }]);
    }

    #[test]
    fn the_confidence_sweep_and_its_calibration() {
        let g = gt(&[(10, 1), (11, 2), (12, 3), (13, 4)]);
        let r = [q(10, 1, 0.95), q(11, 2, 0.90), q(14, 5, 0.80), q(12, 3, 0.70), q(13, 9, 0.60)];
        let cands = [(0.95, true), (0.92, true), (0.85, false), (0.75, true), (0.65, false), (0.05, false)];
        let c = evaluate_confidence(&r, &g, 0, &cands, Some(0.85));
        assert_eq!((c.recall_at_100_precision, c.first_false_confidence), (0.5, Some(0.80)));
        assert_eq!(c.at_loop_confidence, Some((0.85, 1.0, 0.5)));
        // Bins: 0.0 (0.05 false), 0.6 (0.65 false), 0.7 (0.75 true), 0.8 (0.85 false), 0.9 (0.92, 0.95 true).
        let ece = (0.05 + 0.65 + 0.25 + 0.85 + (1.0 - 0.935) * 2.0) / 6.0;
        assert!((c.expected_calibration_error - ece).abs() < 1e-6, "{}", c.expected_calibration_error);
        assert_eq!(c.reliability.iter().map(|b| b.count).sum::<usize>(), 6);
    }

    #[test]
    fn tolerance_and_queries_without_candidates() {
        let g = gt(&[(7, 20)]);
        let r = [q(7, 22, 0.9), QueryResult { query: 8, best: None }];
        assert_eq!(evaluate(&r, &g, 1).recall_at_100_precision, 0.0);
        let rep = evaluate(&r, &g, 2);
        assert_eq!((rep.recall_at_100_precision, rep.recall_at_1, rep.queries), (1.0, 1.0, 2));
    }
}
