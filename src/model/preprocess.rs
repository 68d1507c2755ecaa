//! Image bytes -> network input: decoding under explicit limits, resizing, normalisation.
use super::config::{Normalization, Preprocess, ResizeMode};
use image::{imageops::FilterType, ImageReader, RgbImage};
use std::io::Cursor;
use tch::Tensor;

/// Keras "caffe" mean, in BGR order.
const CAFFE_MEAN_BGR: [f32; 3] = [103.939, 116.779, 123.68];
const TORCH_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const TORCH_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// What an incoming image may be. Checked before any large allocation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageLimits {
    pub max_bytes: usize,
    pub max_pixels: u64,
    /// Smallest side accepted: a few pixels hold no place information.
    pub min_side: u32,
    /// Largest decoded pixel buffer (width x height x channels x bytes per channel): a small
    /// 16-bit PNG can decode to hundreds of MB. Memory for decoding is at most this per decode
    /// worker (plus its 8-bit RGB copy).
    pub max_decode_bytes: u64,
}

impl Default for ImageLimits {
    fn default() -> Self {
        Self { max_bytes: 16 << 20, max_pixels: 40_000_000, min_side: 16, max_decode_bytes: 192 << 20 }
    }
}

#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum ImageError {
    #[error("image is empty (0 bytes)")]
    Empty,
    #[error("image is {bytes} bytes, above the limit of {max} bytes")]
    TooManyBytes { bytes: usize, max: usize },
    #[error("not a supported image format (JPEG, PNG, BMP, TIFF or WebP expected)")]
    UnknownFormat,
    #[error("image is {width}x{height} = {} pixels, above the limit of {max} pixels", *width as u64 * *height as u64)]
    TooManyPixels { width: u32, height: u32, max: u64 },
    #[error("image is {width}x{height}; each side must be at least {min} pixels")]
    TooSmall { width: u32, height: u32, min: u32 },
    #[error("image is {width}x{height} with {bytes_per_pixel} bytes per pixel: decoding needs {} bytes, above the limit of {max} bytes", *width as u64 * *height as u64 * *bytes_per_pixel as u64)]
    TooMuchMemory { width: u32, height: u32, bytes_per_pixel: u8, max: u64 },
    #[error("cannot decode image: {0}")]
    Corrupt(String),
}

/// Decodes to RGB, refusing oversized headers before the pixel buffer is allocated.
pub fn decode(bytes: &[u8], limits: &ImageLimits) -> Result<RgbImage, ImageError> {
    if bytes.is_empty() {
        return Err(ImageError::Empty);
    }
    if bytes.len() > limits.max_bytes {
        return Err(ImageError::TooManyBytes { bytes: bytes.len(), max: limits.max_bytes });
    }
    let reader =
        || ImageReader::new(Cursor::new(bytes)).with_guessed_format().map_err(|e| ImageError::Corrupt(e.to_string()));
    let probe = reader()?;
    let probe_format = probe.format();
    if probe_format.is_none() {
        return Err(ImageError::UnknownFormat);
    }
    let decoder = probe.into_decoder().map_err(|e| ImageError::Corrupt(e.to_string()))?;
    let (width, height) = image::ImageDecoder::dimensions(&decoder);
    let bytes_per_pixel = image::ImageDecoder::color_type(&decoder).bytes_per_pixel();
    if width as u64 * height as u64 > limits.max_pixels {
        return Err(ImageError::TooManyPixels { width, height, max: limits.max_pixels });
    }
    if width < limits.min_side || height < limits.min_side {
        return Err(ImageError::TooSmall { width, height, min: limits.min_side });
    }
    if width as u64 * height as u64 * bytes_per_pixel as u64 > limits.max_decode_bytes {
        return Err(ImageError::TooMuchMemory { width, height, bytes_per_pixel, max: limits.max_decode_bytes });
    }
    if probe_format == Some(image::ImageFormat::Jpeg) && !jpeg_is_complete(bytes) {
        // Decoders fill a cut-off JPEG with grey and report success; a partial frame is not a place.
        return Err(ImageError::Corrupt("JPEG is truncated (no end-of-image marker)".into()));
    }
    let mut r = reader()?;
    let mut dl = image::Limits::default();
    dl.max_image_width = Some(width);
    dl.max_image_height = Some(height);
    // The pixel buffer is bounded above; the decoder's own working buffers come on top of it.
    dl.max_alloc = Some(limits.max_decode_bytes.saturating_mul(2));
    r.limits(dl);
    let img = r.decode().map_err(|e| ImageError::Corrupt(e.to_string()))?;
    Ok(img.to_rgb8())
}

/// Output size for an image of `w` x `h`.
pub fn target_size(w: u32, h: u32, p: &Preprocess) -> (u32, u32) {
    match p.resize {
        ResizeMode::Stretch => (p.width, p.height),
        ResizeMode::Keep => {
            let s = (p.width as f64 / w as f64).min(p.height as f64 / h as f64);
            (((w as f64 * s).round() as u32).max(32), ((h as f64 * s).round() as u32).max(32))
        }
    }
}

/// Resized, normalised CHW float tensor ([3, H, W]) ready to stack into a batch.
pub fn to_input(img: &RgbImage, p: &Preprocess) -> Tensor {
    let (w, h) = target_size(img.width(), img.height(), p);
    let resized =
        if (w, h) == img.dimensions() { img.clone() } else { image::imageops::resize(img, w, h, FilterType::Triangle) };
    let plane = (w * h) as usize;
    let mut chw = vec![0f32; 3 * plane];
    for (i, px) in resized.pixels().enumerate() {
        let [r, g, b] = px.0.map(f32::from);
        match p.normalization {
            Normalization::Caffe => {
                chw[i] = b - CAFFE_MEAN_BGR[0];
                chw[plane + i] = g - CAFFE_MEAN_BGR[1];
                chw[2 * plane + i] = r - CAFFE_MEAN_BGR[2];
            }
            Normalization::Torch => {
                for (c, v) in [r, g, b].into_iter().enumerate() {
                    chw[c * plane + i] = (v / 255.0 - TORCH_MEAN[c]) / TORCH_STD[c];
                }
            }
        }
    }
    Tensor::from_slice(&chw).reshape([3, h as i64, w as i64])
}

/// The resized image as an RGB 0-255 float tensor ([3, H, W]) before normalisation (training
/// augments here); `normalize(resized_rgb(img, p), p.normalization)` equals `to_input(img, p)`.
pub fn resized_rgb(img: &RgbImage, p: &Preprocess) -> Tensor {
    let (w, h) = target_size(img.width(), img.height(), p);
    let resized =
        if (w, h) == img.dimensions() { img.clone() } else { image::imageops::resize(img, w, h, FilterType::Triangle) };
    Tensor::from_slice(resized.as_raw()).reshape([h as i64, w as i64, 3]).permute([2, 0, 1]).to_kind(tch::Kind::Float)
}

/// Normalises RGB 0-255 tensors ([3, H, W] or [N, 3, H, W]) as `to_input` does.
pub fn normalize(rgb: &Tensor, n: Normalization) -> Tensor {
    let c = if rgb.dim() == 4 { 1 } else { 0 };
    let shape: Vec<i64> = (0..rgb.dim()).map(|d| if d as i64 == c { 3 } else { 1 }).collect();
    let column = |v: [f32; 3]| Tensor::from_slice(&v).reshape(shape.as_slice());
    match n {
        Normalization::Caffe => rgb.flip([c]) - column(CAFFE_MEAN_BGR),
        Normalization::Torch => (rgb / 255.0 - column(TORCH_MEAN)) / column(TORCH_STD),
    }
}

/// Decode and preprocess in one step (the work of a decoding worker).
pub fn prepare(bytes: &[u8], limits: &ImageLimits, p: &Preprocess) -> Result<Tensor, ImageError> {
    Ok(to_input(&decode(bytes, limits)?, p))
}

/// Walks the JPEG's segments and entropy-coded scans and reports whether the
/// end-of-image marker is reached before the data runs out.
fn jpeg_is_complete(b: &[u8]) -> bool {
    let mut i = 2; // after SOI
    while i + 1 < b.len() {
        if b[i] != 0xFF {
            return false;
        }
        let marker = b[i + 1];
        match marker {
            0xD9 => return true,
            0xFF => i += 1, // fill byte
            0x01 | 0xD0..=0xD7 => i += 2,
            _ => {
                let Some(len) = b.get(i + 2..i + 4).map(|l| u16::from_be_bytes([l[0], l[1]]) as usize) else {
                    return false;
                };
                i += 2 + len;
                if marker == 0xDA {
                    // Entropy-coded data runs to the next marker that is not stuffing or a restart.
                    while i + 1 < b.len() && !(b[i] == 0xFF && b[i + 1] != 0x00 && !(0xD0..=0xD7).contains(&b[i + 1])) {
                        i += 1;
                    }
                }
            }
        }
    }
    false
}
