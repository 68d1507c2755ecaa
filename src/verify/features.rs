//! ORB keypoints + descriptors for geometric loop-closure verification (OpenCV).
//!
//! Keypoints are always stored in ORIGINAL image pixels, even though extraction may run
//! on a downscaled copy, so that camera intrinsics of the original image apply to them.

use opencv::core::{self, Mat, Size, ToInputArray, Vector};
use opencv::features2d::{ORB_ScoreType, ORB};
use opencv::imgproc;
use opencv::prelude::*;

use super::error::VerifyError;
use crate::model::preprocess::{decode, ImageLimits};

/// Bytes per ORB descriptor (256 bits).
pub const DESCRIPTOR_BYTES: usize = 32;

const MAGIC: &[u8; 4] = b"ORB1";
/// magic + width u32 + height u32 + count u32, all little-endian.
const HEADER_BYTES: usize = 16;
/// x, y as u16 fixed point (fraction of width / height) + raw descriptor.
const BYTES_PER_FEATURE: usize = 4 + DESCRIPTOR_BYTES;
/// ORB edge threshold = patch size (OpenCV default).
const ORB_EDGE: i32 = 31;
/// Hard cap so a decoded blob can never ask for an absurd allocation.
const MAX_FEATURES: usize = 100_000;

#[derive(Clone, Debug)]
pub struct FeatureParams {
    /// Upper bound on ORB keypoints per frame.
    pub max_features: usize,
    /// Downscale so that the long side is at most this many pixels before extraction (0 = never).
    pub max_side: u32,
}

impl Default for FeatureParams {
    fn default() -> Self {
        // 1000 keeps K=5 candidate verifications at ~12 ms on 2 cores (1500: ~29 ms, at the
        // 30 ms budget) while true loops still get >= 3x the 30-inlier gate.
        Self { max_features: 1000, max_side: 640 }
    }
}

/// Keypoints (x, y in ORIGINAL image pixels) + 32-byte ORB descriptors, plus the image size.
#[derive(Clone, Debug, PartialEq)]
pub struct Features {
    pub width: u32,
    pub height: u32,
    pub points: Vec<[f32; 2]>,
    pub descriptors: Vec<[u8; DESCRIPTOR_BYTES]>,
}

impl Features {
    /// Number of keypoints.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Keeps the first `n` features (extraction order).
    pub fn truncate(&mut self, n: usize) {
        self.points.truncate(n);
        self.descriptors.truncate(n);
    }

    /// Checks the invariants that `extract`/`decode` guarantee (fields are public).
    pub fn validate(&self) -> Result<(), VerifyError> {
        if self.points.len() != self.descriptors.len() {
            return Err(VerifyError::Corrupt(format!(
                "features: {} points but {} descriptors",
                self.points.len(),
                self.descriptors.len()
            )));
        }
        if let Some(p) = self.points.iter().find(|p| !p[0].is_finite() || !p[1].is_finite()) {
            return Err(VerifyError::Corrupt(format!("features: non-finite keypoint ({}, {})", p[0], p[1])));
        }
        Ok(())
    }

    /// Encoded size for `n` features: 16 + 36 n bytes (1500 features = 54,016 bytes).
    pub const fn encoded_len(n: usize) -> usize {
        HEADER_BYTES + n * BYTES_PER_FEATURE
    }

    /// Compact little-endian encoding: `"ORB1" | width u32 | height u32 | n u32 | n × (x u16, y u16) | n × 32 B`.
    /// x, y are fixed point fractions of width/height (error ≤ side/131070 px, 0.005 px at 640).
    pub fn encode(&self) -> Vec<u8> {
        // Never write more entries than the shorter of the two vectors (they should match).
        let n = self.points.len().min(self.descriptors.len());
        let mut out = Vec::with_capacity(Self::encoded_len(n));
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&self.width.to_le_bytes());
        out.extend_from_slice(&self.height.to_le_bytes());
        out.extend_from_slice(&(n as u32).to_le_bytes());
        for p in &self.points[..n] {
            out.extend_from_slice(&quantize(p[0], self.width).to_le_bytes());
            out.extend_from_slice(&quantize(p[1], self.height).to_le_bytes());
        }
        for d in &self.descriptors[..n] {
            out.extend_from_slice(d);
        }
        out
    }

    pub fn decode(b: &[u8]) -> Result<Self, VerifyError> {
        if b.len() < HEADER_BYTES {
            return Err(VerifyError::Corrupt(format!(
                "features blob too short: {} bytes, header needs {HEADER_BYTES}",
                b.len()
            )));
        }
        if &b[0..4] != MAGIC {
            return Err(VerifyError::Corrupt("features blob: bad magic (expected \"ORB1\")".into()));
        }
        let width = read_u32(b, 4);
        let height = read_u32(b, 8);
        let n = read_u32(b, 12) as usize;
        if width == 0 || height == 0 {
            return Err(VerifyError::Corrupt(format!("features blob: invalid image size {width}x{height}")));
        }
        if n > MAX_FEATURES {
            return Err(VerifyError::Corrupt(format!("features blob: {n} features exceeds limit {MAX_FEATURES}")));
        }
        let expected = Self::encoded_len(n);
        if b.len() != expected {
            return Err(VerifyError::Corrupt(format!(
                "features blob: {} bytes, expected {expected} for {n} features",
                b.len()
            )));
        }
        let pts = &b[HEADER_BYTES..HEADER_BYTES + 4 * n];
        let points = pts
            .chunks_exact(4)
            .map(|c| {
                let x = u16::from_le_bytes([c[0], c[1]]);
                let y = u16::from_le_bytes([c[2], c[3]]);
                [dequantize(x, width), dequantize(y, height)]
            })
            .collect();
        let descriptors = b[HEADER_BYTES + 4 * n..]
            .chunks_exact(DESCRIPTOR_BYTES)
            .map(|c| {
                let mut d = [0u8; DESCRIPTOR_BYTES];
                d.copy_from_slice(c);
                d
            })
            .collect();
        Ok(Self { width, height, points, descriptors })
    }
}

fn read_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

fn quantize(v: f32, side: u32) -> u16 {
    if side == 0 || !v.is_finite() {
        return 0;
    }
    // Float-to-int `as` saturates, so out-of-range values clamp instead of wrapping.
    (v as f64 / side as f64 * 65535.0).round() as u16
}

fn dequantize(q: u16, side: u32) -> f32 {
    (q as f64 * side as f64 / 65535.0) as f32
}

/// Extracts ORB features from an 8-bit grayscale buffer (row-major, no padding).
pub fn extract(gray: &[u8], width: u32, height: u32, p: &FeatureParams) -> Result<Features, VerifyError> {
    let expected = (width as usize)
        .checked_mul(height as usize)
        .ok_or_else(|| VerifyError::Invalid(format!("image size {width}x{height} overflows")))?;
    if width == 0 || height == 0 {
        return Err(VerifyError::Invalid(format!("empty image ({width}x{height})")));
    }
    if gray.len() != expected {
        return Err(VerifyError::Invalid(format!(
            "grayscale buffer is {} bytes, expected {expected} for {width}x{height}",
            gray.len()
        )));
    }
    if p.max_features == 0 || p.max_features > MAX_FEATURES {
        return Err(VerifyError::Invalid(format!(
            "max_features must be in 1..={MAX_FEATURES}, got {}",
            p.max_features
        )));
    }
    let rows = i32::try_from(height).map_err(|_| VerifyError::Invalid(format!("image height {height} too large")))?;
    let cols = i32::try_from(width).map_err(|_| VerifyError::Invalid(format!("image width {width} too large")))?;
    extract_cv(gray, rows, cols, p).map_err(|e| VerifyError::Failed(format!("ORB extraction failed: {e}")))
}

fn extract_cv(gray: &[u8], rows: i32, cols: i32, p: &FeatureParams) -> opencv::Result<Features> {
    // Borrows the caller's buffer; no copy.
    let img = Mat::new_rows_cols_with_data(rows, cols, gray)?;
    let long = rows.max(cols);
    let scale = if p.max_side > 0 && long as u32 > p.max_side { p.max_side as f64 / long as f64 } else { 1.0 };

    let size = if scale < 1.0 {
        Size::new(((cols as f64 * scale).round() as i32).max(1), ((rows as f64 * scale).round() as i32).max(1))
    } else {
        Size::new(cols, rows)
    };
    // ORB keeps keypoints EDGE px from the border (none fit below 2*EDGE+1) and its pyramid
    // `resize` asserts on 1-2 px images, so small inputs get no features instead of an error.
    if size.width.min(size.height) <= 2 * ORB_EDGE {
        return Ok(Features { width: cols as u32, height: rows as u32, points: Vec::new(), descriptors: Vec::new() });
    }
    if scale < 1.0 {
        let mut small = Mat::default();
        // INTER_AREA avoids aliasing when shrinking (ORB's FAST is sensitive to it).
        imgproc::resize(&img, &mut small, size, 0.0, 0.0, imgproc::INTER_AREA)?;
        // Map back with the exact per-axis factor of the resized image.
        let sx = cols as f32 / size.width as f32;
        let sy = rows as f32 / size.height as f32;
        orb(&small, sx, sy, rows, cols, p)
    } else {
        orb(&img, 1.0, 1.0, rows, cols, p)
    }
}

fn orb(
    input: &impl ToInputArray,
    sx: f32,
    sy: f32,
    rows: i32,
    cols: i32,
    p: &FeatureParams,
) -> opencv::Result<Features> {
    let empty = Features { width: cols as u32, height: rows as u32, points: Vec::new(), descriptors: Vec::new() };
    // OpenCV defaults except nfeatures (scale 1.2, 8 levels, edge 31, Harris score, patch 31, FAST 20).
    let mut orb = ORB::create(p.max_features as i32, 1.2, 8, ORB_EDGE, 0, 2, ORB_ScoreType::HARRIS_SCORE, 31, 20)?;
    let mut kps = Vector::<core::KeyPoint>::new();
    let mut desc = Mat::default();
    orb.detect_and_compute(input, &core::no_array(), &mut kps, &mut desc, false)?;

    let n = kps.len();
    let mut points = Vec::with_capacity(n);
    let mut descriptors = Vec::with_capacity(n);
    if n > 0 {
        // ORB returns one CV_8U row of 32 bytes per keypoint; anything else is a bug we report.
        if desc.rows() as usize != n || desc.cols() as usize != DESCRIPTOR_BYTES || desc.typ() != core::CV_8U {
            return Err(opencv::Error::new(
                core::StsBadSize,
                format!(
                    "unexpected descriptor matrix {}x{} type {} for {n} keypoints",
                    desc.rows(),
                    desc.cols(),
                    desc.typ()
                ),
            ));
        }
        let bytes = desc.data_bytes()?;
        for (kp, row) in kps.iter().zip(bytes.chunks_exact(DESCRIPTOR_BYTES)) {
            let pt = kp.pt();
            // Pixel centres: (x + 0.5) * s - 0.5 maps a downscaled pixel centre to the original one.
            points.push([(pt.x + 0.5) * sx - 0.5, (pt.y + 0.5) * sy - 0.5]);
            let mut d = [0u8; DESCRIPTOR_BYTES];
            d.copy_from_slice(row);
            descriptors.push(d);
        }
    }
    Ok(Features { points, descriptors, ..empty })
}

/// Features of an encoded image (any format and depth the model takes), decoded under the same
/// limits as the model's input: the server and `loopd eval` both extract through this.
pub fn from_image_bytes(bytes: &[u8], limits: &ImageLimits, p: &FeatureParams) -> Result<Features, VerifyError> {
    let rgb = decode(bytes, limits).map_err(|e| VerifyError::Invalid(e.to_string()))?;
    let gray = image::imageops::grayscale(&rgb);
    let (w, h) = gray.dimensions();
    extract(gray.as_raw(), w, h, p)
}
