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

/// Bytes of a whole ORB descriptor (256 binary tests).
pub const DESCRIPTOR_BYTES: usize = 32;
/// Descriptor bits kept by default: the first 112 of ORB's 256 tests (OpenCV's learned pattern,
/// in the order its greedy selection took them: most variance, least correlation first).
/// Measured in docs/verification.md: the verified loops of desk, EuRoC and Corridor stay the
/// same, inliers within 10%, at 17 bytes per keypoint instead of 36.
pub const DEFAULT_DESCRIPTOR_BITS: usize = 112;
/// The fewest descriptor bits accepted: below this the ratio test has too little to go on.
pub const MIN_DESCRIPTOR_BITS: usize = 64;

/// Version 1 (read only; what loopd stored before): 16-byte header, 16-bit positions, the whole
/// 32-byte descriptor.
const MAGIC_V1: &[u8; 4] = b"ORB1";
/// magic + width u32 + height u32 + count u32, all little-endian.
const HEADER_V1: usize = 16;
/// Version 2 (written): 12-bit positions and the descriptor's first bytes.
const MAGIC: &[u8; 4] = b"ORB2";
/// Version 3 (written for frames with depth): version 2, then each keypoint's depth.
const MAGIC_DEPTH: &[u8; 4] = b"ORB3";
/// Version 4 (written for frames whose depth came from a stereo pair): version 3, then the rig's
/// focal length times baseline (pixels x metres, f32), what a depth's noise follows from.
const MAGIC_STEREO: &[u8; 4] = b"ORB4";
/// A keypoint's depth: millimetres as u16 (0: none).
const DEPTH_BYTES: usize = 2;
/// Bytes of a stereo frame's focal length times baseline (f32), after its depths.
pub const STEREO_BYTES: usize = 4;
/// magic + descriptor bytes u8 + width u32 + height u32 + count u32, all little-endian.
const HEADER_BYTES: usize = 17;
/// x, y as 12-bit fixed point fractions of width and height, packed in 3 bytes.
const POSITION_BYTES: usize = 3;
/// Steps of the position grid along each side (12 bits).
const POSITION_STEPS: f64 = 4095.0;
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
    /// Descriptor bits kept (a multiple of 8 in 64..=256): the first tests of ORB's pattern.
    pub descriptor_bits: usize,
}

impl Default for FeatureParams {
    fn default() -> Self {
        // 1000 keeps K=5 candidate verifications at ~12 ms on 2 cores (1500: ~29 ms, at the
        // 30 ms budget) while true loops still get >= 3x the 30-inlier gate.
        Self { max_features: 1000, max_side: 640, descriptor_bits: DEFAULT_DESCRIPTOR_BITS }
    }
}

impl FeatureParams {
    /// Refuses settings extraction cannot honour, with the reason.
    pub fn validate(&self) -> Result<(), VerifyError> {
        if self.max_features == 0 || self.max_features > MAX_FEATURES {
            return Err(VerifyError::Invalid(format!(
                "max_features must be in 1..={MAX_FEATURES}, got {}",
                self.max_features
            )));
        }
        let b = self.descriptor_bits;
        if !(MIN_DESCRIPTOR_BITS..=8 * DESCRIPTOR_BYTES).contains(&b) || !b.is_multiple_of(8) {
            return Err(VerifyError::Invalid(format!(
                "descriptor bits must be a multiple of 8 in {MIN_DESCRIPTOR_BITS}..={}, got {b}",
                8 * DESCRIPTOR_BYTES
            )));
        }
        Ok(())
    }
}

/// Parses `--feature-bits` (server and `loopd eval`): a multiple of 8 in 64..=256.
pub fn parse_descriptor_bits(s: &str) -> Result<usize, String> {
    let bits: usize = s.trim().parse().map_err(|e| format!("{s:?}: {e}"))?;
    let p = FeatureParams { descriptor_bits: bits, ..FeatureParams::default() };
    p.validate().map_err(|e| e.to_string())?;
    Ok(bits)
}

/// Keypoints (x, y in ORIGINAL image pixels) + ORB descriptors, plus the image size.
///
/// A descriptor keeps its first `descriptor_bytes` bytes (the first 8 × that many binary tests);
/// the rest of its 32 bytes are zero. Two feature sets are matched on the bytes both keep.
#[derive(Clone, Debug, PartialEq)]
pub struct Features {
    pub width: u32,
    pub height: u32,
    pub points: Vec<[f32; 2]>,
    pub descriptors: Vec<[u8; DESCRIPTOR_BYTES]>,
    /// Bytes of each descriptor that carry tests (1..=32); the others are zero.
    pub descriptor_bytes: usize,
    /// Each keypoint's depth in metres (0: none), when the frame came with depth; else empty.
    pub depths: Vec<f32>,
    /// Where the depths came from a stereo pair, its rectified focal length times its baseline
    /// (pixels x metres): a depth z is then good to z² σ_disparity / (f·B). 0: a depth sensor.
    pub stereo_focal_baseline: f32,
}

impl Features {
    /// No keypoints (an image too small or too plain), with the image's size.
    pub fn none(width: u32, height: u32, descriptor_bytes: usize) -> Self {
        Self {
            width,
            height,
            points: Vec::new(),
            descriptors: Vec::new(),
            descriptor_bytes,
            depths: Vec::new(),
            stereo_focal_baseline: 0.0,
        }
    }

    /// True when the frame came with depth.
    pub fn has_depth(&self) -> bool {
        !self.depths.is_empty()
    }

    /// True when the depths came from a stereo pair (see `stereo_focal_baseline`).
    pub fn stereo_depth(&self) -> bool {
        self.has_depth() && self.stereo_focal_baseline.is_finite() && self.stereo_focal_baseline > 0.0
    }

    /// Keypoint `i`'s depth in metres, if it has one.
    pub fn depth(&self, i: usize) -> Option<f32> {
        self.depths.get(i).copied().filter(|&d| d > 0.0)
    }

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
        self.depths.truncate(n);
    }

    /// Keeps each descriptor's first `bytes` bytes and zeroes the rest (no-op when it keeps fewer).
    pub fn shorten(&mut self, bytes: usize) {
        if bytes >= self.descriptor_bytes {
            return;
        }
        for d in &mut self.descriptors {
            d[bytes..].fill(0);
        }
        self.descriptor_bytes = bytes;
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
        if !(1..=DESCRIPTOR_BYTES).contains(&self.descriptor_bytes) {
            return Err(VerifyError::Corrupt(format!(
                "features: {} descriptor bytes, expected 1..={DESCRIPTOR_BYTES}",
                self.descriptor_bytes
            )));
        }
        if !self.depths.is_empty() && self.depths.len() != self.points.len() {
            return Err(VerifyError::Corrupt(format!(
                "features: {} points but {} depths",
                self.points.len(),
                self.depths.len()
            )));
        }
        if let Some(p) = self.points.iter().find(|p| !p[0].is_finite() || !p[1].is_finite()) {
            return Err(VerifyError::Corrupt(format!("features: non-finite keypoint ({}, {})", p[0], p[1])));
        }
        Ok(())
    }

    /// Encoded size of `n` features of `descriptor_bytes` bytes: 17 + n (3 + bytes); 1,000
    /// keypoints of 112 bits take 17,017 bytes.
    pub const fn encoded_len(n: usize, descriptor_bytes: usize) -> usize {
        HEADER_BYTES + n * (POSITION_BYTES + descriptor_bytes)
    }

    /// Encoded size with each keypoint's depth (2 more bytes a keypoint) or without; a stereo
    /// frame's takes [`STEREO_BYTES`] more.
    pub const fn encoded_len_of(n: usize, descriptor_bytes: usize, depth: bool) -> usize {
        Self::encoded_len(n, descriptor_bytes) + if depth { n * DEPTH_BYTES } else { 0 }
    }

    /// Compact little-endian encoding: `"ORB2" | descriptor bytes u8 | width u32 | height u32 |
    /// n u32 | n × (x, y: 12 bits each, 3 B) | n × descriptor bytes`. x, y are fixed point fractions
    /// of width / height: error at most side / 8190 (0.08 px at 640), a tenth of a pixel of the
    /// image extraction ran on at the default `max_side`. With depth, the magic is `"ORB3"` and
    /// `n × depth` (millimetres, u16; 0: none) follows the descriptors; with stereo depth the
    /// magic is `"ORB4"` and the rig's focal length times baseline (f32) follows the depths.
    pub fn encode(&self) -> Vec<u8> {
        // Never write more entries than the shorter of the two vectors (they should match).
        let n = self.points.len().min(self.descriptors.len());
        let bytes = self.descriptor_bytes.clamp(1, DESCRIPTOR_BYTES);
        let (depth, stereo) = (self.has_depth(), self.stereo_depth());
        let mut out = Vec::with_capacity(Self::encoded_len_of(n, bytes, depth));
        out.extend_from_slice(match (depth, stereo) {
            (_, true) => MAGIC_STEREO,
            (true, false) => MAGIC_DEPTH,
            (false, _) => MAGIC,
        });
        out.push(bytes as u8);
        out.extend_from_slice(&self.width.to_le_bytes());
        out.extend_from_slice(&self.height.to_le_bytes());
        out.extend_from_slice(&(n as u32).to_le_bytes());
        for p in &self.points[..n] {
            let (x, y) = (quantize(p[0], self.width), quantize(p[1], self.height));
            out.push((x & 0xff) as u8);
            out.push(((x >> 8) as u8) | (((y & 0x0f) as u8) << 4));
            out.push((y >> 4) as u8);
        }
        for d in &self.descriptors[..n] {
            out.extend_from_slice(&d[..bytes]);
        }
        if depth {
            for i in 0..n {
                let mm = (self.depths.get(i).copied().unwrap_or(0.0) * 1000.0).round();
                let mm = if mm.is_finite() && (1.0..=65535.0).contains(&mm) { mm as u16 } else { 0 };
                out.extend_from_slice(&mm.to_le_bytes());
            }
        }
        if stereo {
            out.extend_from_slice(&self.stereo_focal_baseline.to_le_bytes());
        }
        out
    }

    /// Reads what [`encode`](Self::encode) wrote, and the version-1 blobs stored before it.
    pub fn decode(b: &[u8]) -> Result<Self, VerifyError> {
        let stereo = b.get(0..4) == Some(MAGIC_STEREO);
        let depth = stereo || b.get(0..4) == Some(MAGIC_DEPTH);
        let (header, bytes, dims_at, pos_bytes) = match b.get(0..4) {
            Some(m) if m == MAGIC || m == MAGIC_DEPTH || m == MAGIC_STEREO => {
                (HEADER_BYTES, b.get(4).copied().map_or(0, usize::from), 5, POSITION_BYTES)
            }
            Some(m) if m == MAGIC_V1 => (HEADER_V1, DESCRIPTOR_BYTES, 4, 4),
            _ => {
                return Err(VerifyError::Corrupt(format!(
                    "features blob: bad magic (expected \"ORB4\", \"ORB3\", \"ORB2\" or \"ORB1\", {} bytes)",
                    b.len()
                )))
            }
        };
        if b.len() < header {
            return Err(VerifyError::Corrupt(format!(
                "features blob too short: {} bytes, header needs {header}",
                b.len()
            )));
        }
        if !(1..=DESCRIPTOR_BYTES).contains(&bytes) {
            return Err(VerifyError::Corrupt(format!(
                "features blob: {bytes} descriptor bytes, expected 1..={DESCRIPTOR_BYTES}"
            )));
        }
        let width = read_u32(b, dims_at);
        let height = read_u32(b, dims_at + 4);
        let n = read_u32(b, dims_at + 8) as usize;
        if width == 0 || height == 0 {
            return Err(VerifyError::Corrupt(format!("features blob: invalid image size {width}x{height}")));
        }
        if n > MAX_FEATURES {
            return Err(VerifyError::Corrupt(format!("features blob: {n} features exceeds limit {MAX_FEATURES}")));
        }
        let trailer = if stereo { STEREO_BYTES } else { 0 };
        let expected = header + n * (pos_bytes + bytes + if depth { DEPTH_BYTES } else { 0 }) + trailer;
        if b.len() != expected {
            return Err(VerifyError::Corrupt(format!(
                "features blob: {} bytes, expected {expected} for {n} features",
                b.len()
            )));
        }
        let pts = &b[header..header + pos_bytes * n];
        let points = if pos_bytes == 4 {
            pts.chunks_exact(4)
                .map(|c| {
                    let x = u16::from_le_bytes([c[0], c[1]]);
                    let y = u16::from_le_bytes([c[2], c[3]]);
                    [dequantize_v1(x, width), dequantize_v1(y, height)]
                })
                .collect()
        } else {
            pts.chunks_exact(3)
                .map(|c| {
                    let x = c[0] as u16 | (((c[1] & 0x0f) as u16) << 8);
                    let y = (c[1] >> 4) as u16 | ((c[2] as u16) << 4);
                    [dequantize(x, width), dequantize(y, height)]
                })
                .collect()
        };
        let descriptors_at = header + pos_bytes * n;
        let depths_at = descriptors_at + bytes * n;
        let depths_end = b.len() - trailer;
        let stereo_focal_baseline = match b.get(depths_end..).and_then(|t| <[u8; 4]>::try_from(t).ok()) {
            Some(t) => f32::from_le_bytes(t),
            None => 0.0,
        };
        if stereo && !(stereo_focal_baseline.is_finite() && stereo_focal_baseline > 0.0) {
            return Err(VerifyError::Corrupt(format!(
                "features blob: stereo focal length x baseline {stereo_focal_baseline} is not a positive number"
            )));
        }
        let depths = if depth {
            b[depths_at..depths_end]
                .chunks_exact(DEPTH_BYTES)
                .map(|c| u16::from_le_bytes([c[0], c[1]]) as f32 / 1000.0)
                .collect()
        } else {
            Vec::new()
        };
        let descriptors = b[descriptors_at..depths_at]
            .chunks_exact(bytes)
            .map(|c| {
                let mut d = [0u8; DESCRIPTOR_BYTES];
                d[..bytes].copy_from_slice(c);
                d
            })
            .collect();
        Ok(Self { width, height, points, descriptors, descriptor_bytes: bytes, depths, stereo_focal_baseline })
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
    ((v as f64 / side as f64 * POSITION_STEPS).round() as u16).min(POSITION_STEPS as u16)
}

fn dequantize(q: u16, side: u32) -> f32 {
    (q as f64 * side as f64 / POSITION_STEPS) as f32
}

fn dequantize_v1(q: u16, side: u32) -> f32 {
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
    p.validate()?;
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
        return Ok(Features::none(cols as u32, rows as u32, p.descriptor_bits / 8));
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
    let kept = p.descriptor_bits / 8;
    let empty = Features::none(cols as u32, rows as u32, kept);
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
            // The first tests only (the rest stay zero): see `DEFAULT_DESCRIPTOR_BITS`.
            let mut d = [0u8; DESCRIPTOR_BYTES];
            d[..kept].copy_from_slice(&row[..kept]);
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
