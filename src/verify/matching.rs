//! ORB descriptors matched between a query and a candidate: exhaustive Hamming 2-NN (a plain
//! scan, or OpenCV's BFMatcher) and Lowe's ratio test, one match per candidate keypoint. What
//! [`super::geometric`] runs RANSAC on.
use super::error::VerifyError;
use super::features::{Features, DESCRIPTOR_BYTES};
use opencv::core::{self, DMatch, Mat, Vector};
use opencv::features2d::BFMatcher;
use opencv::prelude::*;

/// Both are exhaustive Hamming 2-NN. Debian's OpenCV 4.6 is built with an SSE2 baseline and
/// does not dispatch the Hamming kernel, so BFMatcher is ~4x slower than the plain scan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Matcher {
    /// Plain-Rust scan over u64 words with `count_ones` (default).
    Scan,
    /// OpenCV `BFMatcher(NORM_HAMMING).knnMatch(k = 2)`.
    OpenCv,
}

/// Nearest and second-nearest neighbour of one query descriptor in the candidate set.
#[derive(Clone, Copy)]
struct Knn2 {
    query: usize,
    train: usize,
    best: u32,
    second: u32,
}

/// Returns (query index, candidate index) pairs that pass the ratio test, one per candidate keypoint.
pub(super) fn ratio_matches(
    q: &Features,
    c: &Features,
    ratio: f32,
    matcher: Matcher,
) -> Result<Vec<(usize, usize)>, VerifyError> {
    let knn = match matcher {
        Matcher::Scan => knn2_scan(q, c),
        Matcher::OpenCv => knn2_opencv(q, c).map_err(|e| VerifyError::Failed(format!("BFMatcher failed: {e}")))?,
    };
    // Best query match per candidate keypoint: duplicates would inflate the inlier count.
    let mut best: Vec<Option<(usize, u32)>> = vec![None; c.len()];
    for m in knn {
        if m.query >= q.len() || m.train >= c.len() || (m.best as f32) >= ratio * (m.second as f32) {
            continue;
        }
        if best[m.train].is_none_or(|(_, d)| m.best < d) {
            best[m.train] = Some((m.query, m.best));
        }
    }
    Ok(best.iter().enumerate().filter_map(|(ci, b)| b.map(|(qi, _)| (qi, ci))).collect())
}

fn as_words(f: &Features) -> Vec<[u64; 4]> {
    f.descriptors
        .iter()
        .map(|d| {
            let w = |k: usize| {
                let mut b = [0u8; 8];
                b.copy_from_slice(&d[8 * k..8 * k + 8]);
                u64::from_le_bytes(b)
            };
            [w(0), w(1), w(2), w(3)]
        })
        .collect()
}

/// Exhaustive Hamming 2-NN; same result as BFMatcher(NORM_HAMMING).knnMatch(k=2), ties included.
fn knn2_scan(q: &Features, c: &Features) -> Vec<Knn2> {
    let (qw, cw) = (as_words(q), as_words(c));
    qw.iter()
        .enumerate()
        .map(|(qi, a)| {
            let mut m = Knn2 { query: qi, train: 0, best: u32::MAX, second: u32::MAX };
            for (ci, b) in cw.iter().enumerate() {
                let d = (a[0] ^ b[0]).count_ones()
                    + (a[1] ^ b[1]).count_ones()
                    + (a[2] ^ b[2]).count_ones()
                    + (a[3] ^ b[3]).count_ones();
                if d < m.best {
                    m.second = m.best;
                    m.best = d;
                    m.train = ci;
                } else if d < m.second {
                    m.second = d;
                }
            }
            m
        })
        .collect()
}

fn descriptor_mat(f: &Features) -> opencv::Result<opencv::boxed_ref::BoxedRef<'_, Mat>> {
    Mat::new_rows_cols_with_data(f.len() as i32, DESCRIPTOR_BYTES as i32, f.descriptors.as_flattened())
}

fn knn2_opencv(q: &Features, c: &Features) -> opencv::Result<Vec<Knn2>> {
    let qd = descriptor_mat(q)?;
    let cd = descriptor_mat(c)?;
    let matcher = BFMatcher::create(core::NORM_HAMMING, false)?;
    let mut knn = Vector::<Vector<DMatch>>::new();
    matcher.knn_train_match(&qd, &cd, &mut knn, 2, &core::no_array(), false)?;
    let mut out = Vec::with_capacity(knn.len());
    for pair in knn.iter() {
        // Fewer than 2 neighbours (candidate has 1 descriptor): no ratio test possible.
        if pair.len() < 2 {
            continue;
        }
        let (m0, m1) = (pair.get(0)?, pair.get(1)?);
        out.push(Knn2 {
            query: m0.query_idx.max(0) as usize,
            train: m0.train_idx.max(0) as usize,
            // Hamming distances are integers stored as f32.
            best: m0.distance as u32,
            second: m1.distance as u32,
        });
    }
    Ok(out)
}
