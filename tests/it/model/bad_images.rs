//! Bad images get a clear error, never a panic, from the library and from the CLI.
use crate::common::*;
use loopd::model::preprocess::{decode, ImageError, ImageLimits};

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xffff_ffffu32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0xedb8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

/// A PNG whose IHDR claims `w` x `h` (valid CRC) followed by a tiny bogus IDAT.
fn png_claiming(w: u32, h: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        out.extend((data.len() as u32).to_be_bytes());
        let mut body = kind.to_vec();
        body.extend(data);
        out.extend(&body);
        out.extend(crc32(&body).to_be_bytes());
    };
    let mut ihdr = Vec::new();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]); // 8-bit RGB
    chunk(b"IHDR", &ihdr);
    chunk(b"IDAT", &[0x78, 0x9c, 0x03, 0x00]);
    chunk(b"IEND", &[]);
    out
}

fn one_pixel_png() -> Vec<u8> {
    let mut buf = std::io::Cursor::new(Vec::new());
    image::RgbImage::from_pixel(1, 1, image::Rgb([10, 20, 30])).write_to(&mut buf, image::ImageFormat::Png).unwrap();
    buf.into_inner()
}

fn cases() -> Vec<(&'static str, Vec<u8>)> {
    let dog = std::fs::read(data("photos/dog.jpg")).unwrap();
    vec![
        ("empty.jpg", Vec::new()),
        ("truncated.jpg", dog[..dog.len() / 3].to_vec()),
        ("notes.txt", b"this is a text file, not an image\n".to_vec()),
        ("one-pixel.png", one_pixel_png()),
        ("huge-header.png", png_claiming(100_000, 100_000)),
    ]
}

#[test]
fn decoder_returns_a_specific_error_for_each_bad_image() {
    let limits = ImageLimits::default();
    let errors: Vec<_> = cases()
        .iter()
        .map(|(name, bytes)| match decode(bytes, &limits) {
            Ok(img) => panic!("{name} decoded as {}x{}", img.width(), img.height()),
            Err(e) => (*name, e),
        })
        .collect();
    assert_eq!(errors[0].1, ImageError::Empty);
    assert_eq!(errors[1].1, ImageError::Corrupt("JPEG is truncated (no end-of-image marker)".into()));
    assert_eq!(errors[2].1, ImageError::UnknownFormat);
    assert_eq!(errors[3].1, ImageError::TooSmall { width: 1, height: 1, min: 16 });
    assert_eq!(errors[4].1, ImageError::TooManyPixels { width: 100_000, height: 100_000, max: limits.max_pixels });
    // Byte limit is checked before anything else.
    let small = ImageLimits { max_bytes: 10, ..limits };
    assert!(matches!(decode(&cases()[1].1, &small), Err(ImageError::TooManyBytes { .. })));
    // and the good image still decodes
    assert_eq!(decode(&std::fs::read(data("photos/dog.jpg")).unwrap(), &limits).unwrap().width(), 768);
}

#[test]
fn cli_reports_each_bad_file_and_still_embeds_the_good_one() {
    let dir = tempfile::tempdir().unwrap();
    let mut args = vec!["embed".to_string(), "--json".into()];
    for (name, bytes) in cases() {
        let p = dir.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        args.push(p.display().to_string());
    }
    args.push(data("photos/kite.jpg").display().to_string());
    let out = loopd_bin().args(&args).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "bad files make the exit status 1: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    for (name, msg) in [
        ("empty.jpg", "empty"),
        ("truncated.jpg", "truncated"),
        ("notes.txt", "not a supported image format"),
        ("one-pixel.png", "at least 16 pixels"),
        ("huge-header.png", "above the limit"),
    ] {
        let line =
            stderr.lines().find(|l| l.contains(name)).unwrap_or_else(|| panic!("no error line for {name}: {stderr}"));
        assert!(line.contains(msg), "{name}: {line}");
    }
    let lines: Vec<serde_json::Value> = stdout.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len(), 1, "only the good image is embedded");
    assert!(lines[0]["path"].as_str().unwrap().ends_with("kite.jpg"));
    assert_eq!(lines[0]["descriptor"].as_array().unwrap().len(), 2048);
}

#[test]
fn every_real_frame_in_shared_data_decodes() {
    // The strict checks (truncation, size) must not reject real camera frames.
    let limits = ImageLimits::default();
    let mut n = 0;
    for dir in [
        "photos",
        "corridor/query",
        "corridor/ref",
        "slambook2-ch11",
        "euroc-lcd",
        "nordland-64x32/summer",
        "nordland-64x32/winter",
    ] {
        for entry in std::fs::read_dir(data(dir)).unwrap() {
            let p = entry.unwrap().path();
            let ext = p.extension().and_then(|e| e.to_str()).unwrap_or("").to_lowercase();
            if !["jpg", "jpeg", "png"].contains(&ext.as_str()) {
                continue;
            }
            if let Err(e) = decode(&std::fs::read(&p).unwrap(), &limits) {
                panic!("{}: {e}", p.display());
            }
            n += 1;
        }
    }
    assert!(n > 4000, "only {n} frames found");
}
