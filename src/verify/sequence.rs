//! Sequence (temporal) verification: a candidate is scored by the frames that led up to it. The
//! querying robot's last L frames (the query last) are compared with the L frames that led up to
//! the candidate in its own robot's trajectory, pair by pair along the diagonal (causal: only
//! the past), each similarity z-scored by its history frame's similarities to the map (a frame
//! that looks like everything says little), and the candidate must stand out from candidates
//! elsewhere on the map. Cost: O(K·L) dot products per query and O(L·256) for the history
//! frames' statistics (`index::ROW_SAMPLE` frames of the map), never a scan of the map per history
//! frame.
use serde::Serialize;

/// Best matches a frame keeps as its votes for later sequence checks.
pub const VOTES: usize = 5;

/// Candidates fetched by descriptor for sequence verification (besides the voted ones), so that
/// candidates elsewhere on the map are there to measure the uniqueness margin against.
pub const POOL: usize = 20;

/// The outcome for one candidate.
#[derive(Clone, Debug, PartialEq, Serialize, utoipa::ToSchema)]
pub struct SequenceCheck {
    /// Mean z-scored similarity along the diagonal (each history frame's similarity to the
    /// candidate's aligned frame, in units of its own similarities to the map).
    pub score: f32,
    /// `score` minus the best score of the candidates more than `window` frames away in the
    /// trajectory (0 when there is none to compare with).
    pub margin: f32,
    /// Frame pairs compared (shorter than L while a trajectory is young).
    pub length: usize,
    /// `margin` reached the query's `min_sequence_margin`.
    pub verified: bool,
}

fn dot(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// A candidate's place for the uniqueness test: its robot and its position in that robot's
/// trajectory.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Place {
    pub robot: u32,
    pub position: usize,
}

/// Checks every candidate: `trails[i]` is candidate i's trajectory up to it (oldest first),
/// `places[i]` where it is, `stats[j]` history frame j's (mean, std) of similarities to the map.
/// Candidates within `window` positions of each other on one robot's trajectory are one place
/// and do not compete.
pub fn check(
    history: &[Vec<f32>],
    stats: &[(f32, f32)],
    trails: &[Vec<Vec<f32>>],
    places: &[Place],
    window: usize,
    min_margin: f32,
) -> Vec<Option<SequenceCheck>> {
    let scored = normalized_scores(history, stats, trails);
    scored
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let (score, length) = (*s)?;
            let rival = scored
                .iter()
                .enumerate()
                .filter(|&(j, _)| {
                    let (a, b) = (places[i], places[j]);
                    a.robot != b.robot || a.position.abs_diff(b.position) > window
                })
                .filter_map(|(_, s)| s.map(|(s, _)| s))
                .fold(None, |m: Option<f32>, s| Some(m.map_or(s, |m| m.max(s))));
            let margin = rival.map_or(0.0, |r| score - r);
            Some(SequenceCheck { score, margin, length, verified: rival.is_some() && margin >= min_margin })
        })
        .collect()
}

/// Each candidate's mean along the diagonal of z-scored similarities: history frame j's
/// similarity to the candidate's frame j steps back, minus that history frame's mean similarity
/// to the map, over its standard deviation (`stats[j]`).
fn normalized_scores(
    history: &[Vec<f32>],
    stats: &[(f32, f32)],
    trails: &[Vec<Vec<f32>>],
) -> Vec<Option<(f32, usize)>> {
    let steps = history.len().min(stats.len());
    trails
        .iter()
        .map(|t| {
            let z: Vec<f32> = (0..steps)
                .map_while(|j| {
                    let h = steps - 1 - j;
                    let c = t.get(t.len().checked_sub(1 + j)?)?;
                    let (mean, sd) = stats[h];
                    Some((dot(&history[h], c) - mean) / sd)
                })
                .collect();
            (!z.is_empty()).then(|| (z.iter().sum::<f32>() / z.len() as f32, z.len()))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(v: &[f32]) -> Vec<f32> {
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.iter().map(|x| x / n).collect()
    }

    #[test]
    fn the_candidate_whose_past_matches_wins_by_a_margin() {
        let a = unit(&[1.0, 0.0, 0.0]);
        let b = unit(&[0.0, 1.0, 0.0]);
        let c = unit(&[0.0, 0.0, 1.0]);
        // The query's past: a, b, then the query c.
        let history = vec![a.clone(), b.clone(), c.clone()];
        // Candidate 0 has the same past; candidate 1 looks the same now but came from elsewhere.
        let trails = vec![vec![a.clone(), b.clone(), c.clone()], vec![b.clone(), a.clone(), c.clone()]];
        let places = [Place { robot: 0, position: 10 }, Place { robot: 0, position: 50 }];
        // Each history frame's similarities to the map: mean 0.5, std 0.25.
        let stats = [(0.5, 0.25); 3];
        let out = check(&history, &stats, &trails, &places, 5, 0.2);
        let (good, bad) = (out[0].clone().unwrap(), out[1].clone().unwrap());
        // z = (1 - 0.5) / 0.25 = 2 on every step for the good one; (0, 0, 1) for the bad one.
        assert!((good.score - 2.0).abs() < 1e-6 && (bad.score - (-2.0 - 2.0 + 2.0) / 3.0).abs() < 1e-6);
        assert!((good.margin - (good.score - bad.score)).abs() < 1e-6 && good.verified);
        assert!(!bad.verified && bad.margin < 0.0);
        // Neighbours on the same trajectory do not compete: no rival, no verdict.
        let near = [Place { robot: 0, position: 10 }, Place { robot: 0, position: 12 }];
        assert!(check(&history, &stats, &trails, &near, 5, 0.2).iter().all(|c| !c.as_ref().unwrap().verified));
        // A young trajectory compares what it has.
        let short = check(&history[2..], &stats[2..], &trails, &places, 5, 0.2);
        assert_eq!(short[0].as_ref().unwrap().length, 1);
        assert!(check(&[], &[], &trails, &places, 5, 0.2).iter().all(Option::is_none));
    }
}
