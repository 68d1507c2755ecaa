//! Depth registered to a frame's image (an RGB-D camera's depth image), for metric loop poses: a
//! 16-bit PNG, PGM or TIFF in the session camera's `depth_scale` units per metre (1000: mm; TUM's
//! 5000), or a float TIFF in metres. Only the depth at the frame's keypoints is kept, in its
//! feature record ([`Features::depths`]), not the image.
use super::error::VerifyError;
use super::features::Features;
use crate::model::preprocess::ImageLimits;
use image::{DynamicImage, ImageReader};
use std::io::Cursor;

/// Depth units per metre when the session's camera does not say (millimetres).
pub const DEFAULT_DEPTH_SCALE: f64 = 1000.0;

/// Farthest depth kept (the record stores millimetres in 16 bits).
pub const MAX_DEPTH_M: f32 = 65.535;

/// A depth image in metres; 0 where the sensor gave none.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub metres: Vec<f32>,
}

impl DepthImage {
    /// Decodes a depth image sent with a frame: 16-bit greyscale (PNG, PGM, TIFF) divided by
    /// `scale`, or 32-bit float (TIFF) as metres. 8-bit images, colour images, images over the
    /// model's limits and images without one valid depth are refused, with the reason.
    pub fn decode(bytes: &[u8], scale: f64, limits: &ImageLimits) -> Result<Self, VerifyError> {
        let bad = |why: String| VerifyError::Invalid(format!("depth image: {why}"));
        if !(scale.is_finite() && scale > 0.0) {
            return Err(bad(format!("depth_scale {scale} must be a finite number > 0")));
        }
        if bytes.is_empty() {
            return Err(bad("empty (0 bytes)".into()));
        }
        if bytes.len() > limits.max_bytes {
            return Err(bad(format!("{} bytes, above the limit of {}", bytes.len(), limits.max_bytes)));
        }
        let reader = ImageReader::new(Cursor::new(bytes)).with_guessed_format().map_err(|e| bad(e.to_string()))?;
        if reader.format().is_none() {
            return Err(bad("not a PNG, PGM or TIFF image".into()));
        }
        let decoder = reader.into_decoder().map_err(|e| bad(e.to_string()))?;
        let (width, height) = image::ImageDecoder::dimensions(&decoder);
        let bpp = image::ImageDecoder::color_type(&decoder).bytes_per_pixel() as u64;
        if width as u64 * height as u64 > limits.max_pixels
            || width as u64 * height as u64 * bpp > limits.max_decode_bytes
        {
            return Err(bad(format!("{width}x{height} is over the image limits")));
        }
        let img = DynamicImage::from_decoder(decoder).map_err(|e| bad(e.to_string()))?;
        let metres: Vec<f32> = match &img {
            DynamicImage::ImageLuma16(g) => g.as_raw().iter().map(|&v| (v as f64 / scale) as f32).collect(),
            DynamicImage::ImageRgb32F(g) => g.as_raw().chunks_exact(3).map(|p| p[0]).collect(),
            DynamicImage::ImageRgba32F(g) => g.as_raw().chunks_exact(4).map(|p| p[0]).collect(),
            other => {
                return Err(bad(format!(
                    "{:?} pixels; depth must be 16-bit greyscale (in depth_scale units per metre) or 32-bit float \
                     (metres)",
                    other.color()
                )))
            }
        };
        Self::from_metres(width, height, metres)
    }

    /// A depth image from metres (non-finite, negative and farther than [`MAX_DEPTH_M`] values
    /// become "no depth"); refused when no pixel has a depth.
    pub fn from_metres(width: u32, height: u32, mut metres: Vec<f32>) -> Result<Self, VerifyError> {
        if metres.len() != width as usize * height as usize {
            return Err(VerifyError::Invalid(format!("depth image: {} values for {width}x{height}", metres.len())));
        }
        metres.iter_mut().for_each(|v| {
            if !(v.is_finite() && *v > 0.0 && *v <= MAX_DEPTH_M) {
                *v = 0.0
            }
        });
        if metres.iter().all(|&v| v == 0.0) {
            return Err(VerifyError::Invalid(
                "depth image: no pixel has a depth (all zero, NaN or out of range)".into(),
            ));
        }
        Ok(Self { width, height, metres })
    }

    /// The depth at pixel (x, y): the nearest pixel's, else the nearest of its 8 neighbours'
    /// (a corner often sits on a depth edge, where the sensor has a hole); 0 without one.
    pub fn at(&self, x: f32, y: f32) -> f32 {
        let (w, h) = (self.width as i64, self.height as i64);
        let (cx, cy) = (x.round() as i64, y.round() as i64);
        let get = |x: i64, y: i64| {
            if x < 0 || y < 0 || x >= w || y >= h {
                0.0
            } else {
                self.metres[(y * w + x) as usize]
            }
        };
        let centre = get(cx, cy);
        if centre > 0.0 {
            return centre;
        }
        // A hole: the nearest surface around it (the smallest depth), not a mix of two.
        let mut best = 0.0f32;
        for dy in -1..=1 {
            for dx in -1..=1 {
                let d = get(cx + dx, cy + dy);
                if d > 0.0 && (best == 0.0 || d < best) {
                    best = d;
                }
            }
        }
        best
    }

    /// Gives every keypoint of `f` its depth; refused when the depth image is not the size of
    /// the image the features came from (it must be registered to it).
    pub fn attach(&self, f: &mut Features) -> Result<(), VerifyError> {
        if (self.width, self.height) != (f.width, f.height) {
            return Err(VerifyError::Invalid(format!(
                "depth image is {}x{}, the image {}x{}: depth must be registered to the image, pixel for pixel",
                self.width, self.height, f.width, f.height
            )));
        }
        f.depths = f.points.iter().map(|p| self.at(p[0], p[1])).collect();
        Ok(())
    }
}
