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
    /// Plain-Rust scan over u64 words with `count_ones` (default); two words at 112 bits.
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

/// Bytes both sets keep of each descriptor: they are matched on these tests only.
fn common_bytes(q: &Features, c: &Features) -> usize {
    q.descriptor_bytes.min(c.descriptor_bytes).clamp(1, DESCRIPTOR_BYTES)
}

/// Each descriptor's first `bytes` bytes as N little-endian u64 words (zero beyond `bytes`).
fn as_words<const N: usize>(f: &Features, bytes: usize) -> Vec<[u64; N]> {
    f.descriptors
        .iter()
        .map(|d| {
            let mut w = [0u64; N];
            for (k, word) in w.iter_mut().enumerate() {
                let mut b = [0u8; 8];
                let end = (8 * k + 8).min(bytes);
                if end > 8 * k {
                    b[..end - 8 * k].copy_from_slice(&d[8 * k..end]);
                }
                *word = u64::from_le_bytes(b);
            }
            w
        })
        .collect()
}

/// Exhaustive Hamming 2-NN; same result as BFMatcher(NORM_HAMMING).knnMatch(k=2), ties included.
fn knn2_scan(q: &Features, c: &Features) -> Vec<Knn2> {
    let bytes = common_bytes(q, c);
    match bytes.div_ceil(8) {
        1 => knn2_words::<1>(q, c, bytes),
        2 => knn2_words::<2>(q, c, bytes),
        3 => knn2_words::<3>(q, c, bytes),
        _ => knn2_words::<4>(q, c, bytes),
    }
}

fn knn2_words<const N: usize>(q: &Features, c: &Features, bytes: usize) -> Vec<Knn2> {
    let (qw, cw) = (as_words::<N>(q, bytes), as_words::<N>(c, bytes));
    qw.iter()
        .enumerate()
        .map(|(qi, a)| {
            let mut m = Knn2 { query: qi, train: 0, best: u32::MAX, second: u32::MAX };
            for (ci, b) in cw.iter().enumerate() {
                let d: u32 = (0..N).map(|k| (a[k] ^ b[k]).count_ones()).sum();
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

/// The descriptors' first `bytes` bytes, one row each (what BFMatcher takes).
fn descriptor_mat(f: &Features, bytes: usize) -> opencv::Result<Mat> {
    let rows: Vec<u8> = f.descriptors.iter().flat_map(|d| d[..bytes].iter().copied()).collect();
    Mat::new_rows_cols_with_data(f.len() as i32, bytes as i32, &rows)?.try_clone()
}

fn knn2_opencv(q: &Features, c: &Features) -> opencv::Result<Vec<Knn2>> {
    let bytes = common_bytes(q, c);
    let qd = descriptor_mat(q, bytes)?;
    let cd = descriptor_mat(c, bytes)?;
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
