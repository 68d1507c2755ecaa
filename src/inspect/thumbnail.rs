//! A frame's thumbnail: the picture decoded under the model's input limits, shrunk so its long
//! side is at most [`SIDE`] pixels, as a JPEG. Small enough to keep with every frame (a few KB).
use crate::model::preprocess::{decode, ImageLimits};
use image::codecs::jpeg::JpegEncoder;
use image::{ImageFormat, ImageReader};
use std::io::Cursor;

/// Long side of a thumbnail, in pixels.
pub const SIDE: u32 = 160;
/// JPEG quality: sharp enough to recognise a place, about 5 KB at 160x120.
const QUALITY: u8 = 80;
/// A JPEG already within [`SIDE`] and this size is its own thumbnail (no decode, no re-encode).
const KEPT_AS_IS_BYTES: usize = 32 << 10;

/// Whether the picture is a small JPEG that can serve as its own thumbnail (header only read).
fn small_jpeg(bytes: &[u8]) -> bool {
    if bytes.len() > KEPT_AS_IS_BYTES {
        return false;
    }
    let Ok(reader) = ImageReader::new(Cursor::new(bytes)).with_guessed_format() else { return false };
    reader.format() == Some(ImageFormat::Jpeg) && reader.into_dimensions().is_ok_and(|(w, h)| w.max(h) <= SIDE)
}

pub fn make(bytes: &[u8], limits: &ImageLimits) -> Result<Vec<u8>, String> {
    if small_jpeg(bytes) {
        return Ok(bytes.to_vec());
    }
    let rgb = decode(bytes, limits).map_err(|e| e.to_string())?;
    let (w, h) = rgb.dimensions();
    let scale = (SIDE as f64 / w.max(h) as f64).min(1.0);
    let (tw, th) = (((w as f64 * scale).round() as u32).max(1), ((h as f64 * scale).round() as u32).max(1));
    // `thumbnail` averages the source pixels under each target pixel: no aliasing when shrinking.
    let small = image::imageops::thumbnail(&rgb, tw, th);
    let mut out = Vec::new();
    JpegEncoder::new_with_quality(&mut out, QUALITY).encode_image(&small).map_err(|e| format!("JPEG encoding: {e}"))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_real_frame_shrinks_to_a_small_jpeg_of_its_shape() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/slambook2-ch11/1.png");
        let bytes = std::fs::read(&path).expect("the desk frames in ../shared/data");
        let jpeg = make(&bytes, &ImageLimits::default()).expect("thumbnail");
        let t = image::load_from_memory_with_format(&jpeg, image::ImageFormat::Jpeg).expect("a JPEG");
        assert_eq!((t.width(), t.height()), (160, 120), "640x480 keeps its 4:3 shape");
        assert!(jpeg.len() < 16 << 10, "{} bytes", jpeg.len());
    }

    #[test]
    fn a_small_jpeg_is_its_own_thumbnail() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/corridor/ref/0000000.jpg");
        let bytes = std::fs::read(&path).expect("the corridor frames in ../shared/data");
        assert_eq!(make(&bytes, &ImageLimits::default()).expect("thumbnail"), bytes, "160x120 JPEG kept as is");
    }

    #[test]
    fn what_is_not_an_image_is_an_error() {
        assert!(make(b"not an image", &ImageLimits::default()).is_err());
    }
}
