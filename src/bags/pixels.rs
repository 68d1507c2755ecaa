//! Raw `sensor_msgs/Image` pixels to a PNG: lossless, so a frame from a bag decodes to exactly
//! the pixels the same frame has as a PNG file, and the engine takes both through one decoder.
use super::msgs::RawImage;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder};

/// The encodings read: name, bytes per pixel.
pub const ENCODINGS: [(&str, usize); 9] = [
    ("rgb8", 3),
    ("bgr8", 3),
    ("rgba8", 4),
    ("bgra8", 4),
    ("mono8", 1),
    ("mono16", 2),
    // OpenCV's names for the same layouts (cv_bridge writes them for unnamed images).
    ("8UC1", 1),
    ("8UC3", 3),
    ("16UC1", 2),
];

/// The image as PNG bytes, honouring `step` (row padding) and `is_bigendian`.
pub fn to_png(m: &RawImage) -> Result<Vec<u8>, String> {
    let bpp = ENCODINGS.iter().find(|(e, _)| *e == m.encoding).map(|(_, b)| *b).ok_or_else(|| {
        let known: Vec<&str> = ENCODINGS.iter().map(|(e, _)| *e).collect();
        format!("encoding '{}' is not read (one of {} expected)", m.encoding, known.join(", "))
    })?;
    let (w, h, step) = (m.width as usize, m.height as usize, m.step as usize);
    if w == 0 || h == 0 {
        return Err(format!("image is {w}x{h}"));
    }
    let row = w.checked_mul(bpp).ok_or("image width overflows")?;
    if step < row {
        return Err(format!("step {step} is shorter than a row ({w} pixels x {bpp} bytes = {row})"));
    }
    // The last row need not carry its padding.
    let need = step.checked_mul(h - 1).and_then(|n| n.checked_add(row)).ok_or("image size overflows")?;
    if m.data.len() < need {
        return Err(format!("{} bytes of pixels; {w}x{h} with step {step} needs {need}", m.data.len()));
    }
    let mut packed = Vec::with_capacity(row * h);
    for r in 0..h {
        let line = &m.data[r * step..r * step + row];
        match m.encoding.as_str() {
            "bgr8" | "8UC3" => line.chunks_exact(3).for_each(|p| packed.extend([p[2], p[1], p[0]])),
            "rgba8" => line.chunks_exact(4).for_each(|p| packed.extend(&p[..3])),
            "bgra8" => line.chunks_exact(4).for_each(|p| packed.extend([p[2], p[1], p[0]])),
            // The encoder takes 16-bit samples in native byte order.
            "mono16" | "16UC1" => line.chunks_exact(2).for_each(|p| {
                let v = if m.big_endian { u16::from_be_bytes([p[0], p[1]]) } else { u16::from_le_bytes([p[0], p[1]]) };
                packed.extend(v.to_ne_bytes())
            }),
            _ => packed.extend_from_slice(line),
        }
    }
    let color = match bpp {
        1 => ExtendedColorType::L8,
        2 => ExtendedColorType::L16,
        _ => ExtendedColorType::Rgb8,
    };
    let mut png = Vec::new();
    // Fast compression: the PNG lives only until the engine decodes it.
    PngEncoder::new_with_quality(&mut png, CompressionType::Fast, FilterType::Sub)
        .write_image(&packed, m.width, m.height, color)
        .map_err(|e| format!("cannot encode the image: {e}"))?;
    Ok(png)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raw<'a>(encoding: &str, w: u32, h: u32, step: u32, big_endian: bool, data: &'a [u8]) -> RawImage<'a> {
        RawImage { stamp: 0.0, height: h, width: w, encoding: encoding.into(), big_endian, step, data }
    }

    fn decoded(png: &[u8]) -> image::DynamicImage {
        image::load_from_memory(png).unwrap()
    }

    #[test]
    fn padding_channel_order_and_byte_order() {
        // 2x2 bgr8 with 2 bytes of padding per row (value 99, never read).
        let bgr = [1, 2, 3, 4, 5, 6, 99, 99, 7, 8, 9, 10, 11, 12];
        let img = decoded(&to_png(&raw("bgr8", 2, 2, 8, false, &bgr)).unwrap()).to_rgb8();
        assert_eq!(img.as_raw(), &[3, 2, 1, 6, 5, 4, 9, 8, 7, 12, 11, 10]);
        // mono16 0x0102 in either byte order.
        let le = decoded(&to_png(&raw("mono16", 1, 1, 2, false, &[2, 1])).unwrap()).to_luma16();
        let be = decoded(&to_png(&raw("mono16", 1, 1, 2, true, &[1, 2])).unwrap()).to_luma16();
        assert_eq!((le.as_raw()[0], be.as_raw()[0]), (0x0102, 0x0102));
        let rgba = decoded(&to_png(&raw("bgra8", 1, 1, 4, false, &[1, 2, 3, 4])).unwrap()).to_rgb8();
        assert_eq!(rgba.as_raw(), &[3, 2, 1]);
    }

    #[test]
    fn bad_images_are_errors() {
        assert!(to_png(&raw("bayer_rggb8", 1, 1, 1, false, &[0])).unwrap_err().contains("not read"));
        assert!(to_png(&raw("rgb8", 2, 2, 5, false, &[0; 12])).unwrap_err().contains("shorter than a row"));
        assert!(to_png(&raw("rgb8", 2, 2, 6, false, &[0; 11])).unwrap_err().contains("needs 12"));
        assert!(to_png(&raw("mono8", 0, 2, 0, false, &[])).is_err());
        assert!(to_png(&raw("mono8", u32::MAX, u32::MAX, u32::MAX, false, &[])).is_err());
    }
}
