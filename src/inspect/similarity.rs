//! A session's similarity matrix for people: the cosine similarity of up to `size` of its
//! frames, taken evenly along the frame ids, so a revisit shows as an off-diagonal streak.
use crate::store::{Session, StoreError};
use serde::Serialize;

/// Most frames a matrix spans (its cells grow with the square).
pub const MAX_SIZE: usize = 1024;

/// The cosine similarity matrix of frames spread evenly along the session.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct Similarity {
    /// The frames of the rows (and columns), in id order.
    pub frame_ids: Vec<u64>,
    /// Row-major cosine similarities, rounded to 3 decimals.
    pub values: Vec<f32>,
}

/// `count` indices spread evenly over `0..n` (all of them when n <= count).
fn spread(n: usize, count: usize) -> Vec<usize> {
    if n <= count {
        return (0..n).collect();
    }
    (0..count).map(|i| i * (n - 1) / (count - 1).max(1)).collect()
}

pub fn matrix(s: &Session, size: usize) -> Result<Similarity, StoreError> {
    if !(1..=MAX_SIZE).contains(&size) {
        return Err(StoreError::InvalidArgument(format!("size must be in 1..={MAX_SIZE}, got {size}")));
    }
    let ids = s.frame_ids();
    let frame_ids: Vec<u64> = spread(ids.len(), size).into_iter().map(|i| ids[i]).collect();
    let mut rows = Vec::with_capacity(frame_ids.len());
    for &id in &frame_ids {
        let mut d = s.descriptor(id)?;
        // Stored descriptors are unit length up to f16 rounding: renormalise for exact cosines.
        let norm = d.iter().map(|v| v * v).sum::<f32>().sqrt().max(f32::MIN_POSITIVE);
        d.iter_mut().for_each(|v| *v /= norm);
        rows.push(d);
    }
    let mut values = Vec::with_capacity(rows.len() * rows.len());
    for a in &rows {
        for b in &rows {
            let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
            values.push((dot * 1000.0).round() / 1000.0);
        }
    }
    Ok(Similarity { frame_ids, values })
}

#[cfg(test)]
mod tests {
    use super::spread;

    #[test]
    fn spread_takes_both_ends_and_never_repeats() {
        assert_eq!(spread(3, 5), vec![0, 1, 2]);
        assert_eq!(spread(10, 4), vec![0, 3, 6, 9]);
        let s = spread(1000, 256);
        assert_eq!((s[0], s[255]), (0, 999));
        assert!(s.windows(2).all(|w| w[0] < w[1]));
    }
}
