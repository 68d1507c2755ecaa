//! Geometric verification on bad and degenerate inputs. Frames without texture, tiny frames and
//! malformed feature records never panic: Err from extraction/decoding,
//! `verified: false` with a reason from verification.

use crate::common::*;
use loopd::model::preprocess::ImageLimits;
use std::io::Cursor;

use image::{DynamicImage, ImageFormat};
use loopd::verify::features::{extract, from_image_bytes, parse_descriptor_bits, FeatureParams, Features};
use loopd::verify::geometric::{verify, Intrinsics, VerifyParams};
use loopd::verify::VerifyError;

fn desk1() -> Option<Vec<u8>> {
    Some(std::fs::read(data("slambook2-ch11/1.png")).expect("desk frame"))
}

fn noise(w: u32, h: u32, seed: u64) -> Vec<u8> {
    // xorshift: deterministic texture without a rand dependency.
    let mut s = seed | 1;
    (0..w * h)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 56) as u8
        })
        .collect()
}

fn fake(n: usize) -> Features {
    Features {
        width: 640,
        height: 480,
        points: (0..n).map(|i| [i as f32, i as f32]).collect(),
        descriptors: (0..n).map(|i| [i as u8; 32]).collect(),
        descriptor_bytes: 32,
        depths: Vec::new(),
        stereo_focal_baseline: 0.0,
    }
}

fn reason(v: &loopd::verify::geometric::Verification) -> String {
    assert!(!v.verified, "expected rejection, got {v:?}");
    v.reason.clone().unwrap_or_default()
}

#[test]
fn blank_image_has_no_features_and_is_rejected() {
    let p = FeatureParams::default();
    let f = extract(&vec![128u8; 640 * 480], 640, 480, &p).expect("blank image extracts");
    assert_eq!(f.len(), 0);
    let v = verify(&f, &f, None, &VerifyParams::default());
    assert!(reason(&v).contains("too few features"), "{v:?}");
}

#[test]
fn tiny_images_do_not_panic() {
    let p = FeatureParams::default();
    for (w, h) in [(1, 1), (2, 2), (16, 16), (31, 31), (62, 62), (63, 63), (64, 8), (70, 70), (2000, 3)] {
        let f = extract(&noise(w, h, 7), w, h, &p).expect("tiny image extracts");
        let v = verify(&f, &f, None, &VerifyParams::default());
        assert!(!v.verified, "{w}x{h}: {v:?}");
    }
}

#[test]
fn bad_buffers_are_errors() {
    let p = FeatureParams::default();
    assert!(extract(&[0u8; 10], 4, 4, &p).unwrap_err().to_string().contains("expected 16"));
    assert!(extract(&[], 0, 10, &p).unwrap_err().to_string().contains("empty image"));
    let zero = FeatureParams { max_features: 0, ..p.clone() };
    assert!(extract(&[0u8; 16], 4, 4, &zero).unwrap_err().to_string().contains("max_features"));
    let limits = ImageLimits::default();
    // A client's image that cannot be used is Invalid (a 400 where it is refused), not a failure.
    assert!(matches!(from_image_bytes(b"not an image", &limits, &p), Err(VerifyError::Invalid(_))));
    assert!(matches!(from_image_bytes(&[], &limits, &p), Err(VerifyError::Invalid(_))));
    assert!(matches!(extract(&[], 0, 10, &p), Err(VerifyError::Invalid(_))));
}

#[test]
fn too_few_features_and_inconsistent_features() {
    let p = VerifyParams::default();
    assert!(reason(&verify(&fake(7), &fake(500), None, &p)).contains("too few features (query 7"));
    let mut broken = fake(20);
    broken.descriptors.pop();
    assert!(reason(&verify(&broken, &fake(20), None, &p)).contains("20 points but 19 descriptors"));
    let mut nan = fake(20);
    nan.points[3] = [f32::NAN, 1.0];
    assert!(reason(&verify(&fake(20), &nan, None, &p)).contains("non-finite keypoint"));
}

#[test]
fn identical_random_descriptors_do_not_verify_without_geometry() {
    // All points on a line: degenerate for F; must not panic, must not report a pose.
    let f = fake(200);
    let v = verify(&f, &f, None, &VerifyParams::default());
    assert!(v.relative_pose.is_none());
    let k = Intrinsics { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, dist: None };
    let _ = verify(&f, &f, Some(&k), &VerifyParams::default());
}

#[test]
fn invalid_intrinsics_are_rejected_with_reason() {
    let f = fake(100);
    let good = Intrinsics { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, dist: None };
    assert!(good.validate().is_ok());
    let bad = [
        Intrinsics { fx: 0.0, ..good },
        Intrinsics { fy: -1.0, ..good },
        Intrinsics { fx: f64::NAN, ..good },
        Intrinsics { cx: f64::INFINITY, ..good },
        Intrinsics { dist: Some([0.0, f64::NAN, 0.0, 0.0, 0.0]), ..good },
    ];
    for k in bad {
        assert!(k.validate().is_err(), "{k:?}");
        let v = verify(&f, &f, Some(&k), &VerifyParams::default());
        assert!(reason(&v).starts_with("invalid intrinsics"), "{v:?}");
    }
    let mut other = fake(100);
    other.width = 320;
    assert!(reason(&verify(&f, &other, Some(&good), &VerifyParams::default())).contains("image sizes differ"));
}

#[test]
fn invalid_params_are_rejected_with_reason() {
    let f = fake(100);
    for p in [
        VerifyParams { ratio: 0.0, ..VerifyParams::default() },
        VerifyParams { ratio: f32::NAN, ..VerifyParams::default() },
        VerifyParams { ransac_threshold_px: -1.0, ..VerifyParams::default() },
        VerifyParams { confidence: 1.0, ..VerifyParams::default() },
    ] {
        assert!(reason(&verify(&f, &f, None, &p)).starts_with("invalid params"), "{p:?}");
    }
}

/// What loopd stored before version 2: `"ORB1" | width | height | n | n × (x, y u16) | n × 32 B`.
fn encode_v1(f: &Features) -> Vec<u8> {
    let mut out = b"ORB1".to_vec();
    for v in [f.width, f.height, f.len() as u32] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for p in &f.points {
        out.extend_from_slice(&((p[0] as f64 / f.width as f64 * 65535.0).round() as u16).to_le_bytes());
        out.extend_from_slice(&((p[1] as f64 / f.height as f64 * 65535.0).round() as u16).to_le_bytes());
    }
    for d in &f.descriptors {
        out.extend_from_slice(d);
    }
    out
}

#[test]
fn encode_decode_roundtrip_and_size() {
    let bytes = desk1().unwrap_or_default();
    let f = from_image_bytes(
        &bytes,
        &ImageLimits::default(),
        &FeatureParams { max_features: 1500, ..FeatureParams::default() },
    )
    .expect("extract");
    assert_eq!((f.len(), f.descriptor_bytes), (1500, 14));
    // Only the first 112 tests are kept; the rest of each descriptor is zero.
    assert!(f.descriptors.iter().all(|d| d[14..].iter().all(|&b| b == 0)));
    assert!(f.descriptors.iter().filter(|d| d[..14].iter().any(|&b| b != 0)).count() > 1400);
    let blob = f.encode();
    assert_eq!(blob.len(), Features::encoded_len(1500, 14));
    assert_eq!(blob.len(), 17 + 1500 * 17);
    let g = Features::decode(&blob).expect("decode");
    assert_eq!((g.width, g.height, g.len(), g.descriptor_bytes), (f.width, f.height, f.len(), 14));
    assert_eq!(g.descriptors, f.descriptors);
    // 12-bit positions: within 640 / 8190 px.
    for (a, b) in f.points.iter().zip(&g.points) {
        assert!((a[0] - b[0]).abs() <= 0.079 && (a[1] - b[1]).abs() <= 0.079, "{a:?} vs {b:?}");
    }
    // Malformed blobs.
    assert!(Features::decode(&blob[..blob.len() - 1]).unwrap_err().to_string().contains("expected"));
    assert!(Features::decode(&blob[..10]).unwrap_err().to_string().contains("too short"));
    // A record that breaks its format is Corrupt: the server's data, not the client's input.
    assert!(matches!(Features::decode(&blob[..10]), Err(VerifyError::Corrupt(_))));
    let mut bad = blob.clone();
    bad[0] = b'X';
    assert!(Features::decode(&bad).unwrap_err().to_string().contains("magic"));
    let mut wide = blob.clone();
    wide[4] = 33;
    assert!(Features::decode(&wide).unwrap_err().to_string().contains("33 descriptor bytes"));
    let mut huge = blob[..17].to_vec();
    huge[13..17].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(Features::decode(&huge).unwrap_err().to_string().contains("exceeds limit"));
    let mut zero = blob;
    zero[5..9].copy_from_slice(&0u32.to_le_bytes());
    assert!(Features::decode(&zero).unwrap_err().to_string().contains("invalid image size"));
    let empty = Features::none(1, 1, 14);
    assert_eq!(Features::decode(&empty.encode()).expect("empty roundtrip"), empty);
}

#[test]
fn features_stored_before_version_2_still_decode_and_match_new_ones() {
    let bytes = desk1().unwrap_or_default();
    let whole = FeatureParams { descriptor_bits: 256, ..FeatureParams::default() };
    let old = from_image_bytes(&bytes, &ImageLimits::default(), &whole).expect("extract");
    assert_eq!(old.descriptor_bytes, 32);
    let blob = encode_v1(&old);
    assert_eq!(blob.len(), 16 + 36 * old.len());
    let g = Features::decode(&blob).expect("decode v1");
    assert_eq!((g.len(), g.descriptor_bytes), (old.len(), 32));
    assert_eq!(g.descriptors, old.descriptors);
    for (a, b) in old.points.iter().zip(&g.points) {
        assert!((a[0] - b[0]).abs() < 0.01 && (a[1] - b[1]).abs() < 0.01, "{a:?} vs {b:?}");
    }
    // A new 112-bit query against an old 256-bit record is matched on the 112 bits both keep:
    // the same matches as two 112-bit sets.
    let new = from_image_bytes(&bytes, &ImageLimits::default(), &FeatureParams::default()).expect("extract");
    let p = VerifyParams::default();
    let mixed = verify(&new, &g, None, &p);
    let mut short = g.clone();
    short.shorten(14);
    assert!(short.descriptors.iter().all(|d| d[14..].iter().all(|&b| b == 0)));
    let same = verify(&new, &short, None, &p);
    assert_eq!((mixed.matches, mixed.inliers), (same.matches, same.inliers));
    assert!(mixed.verified && mixed.matches > 900, "{mixed:?}");
}

#[test]
fn feature_bits_outside_the_range_are_refused() {
    for bad in ["0", "56", "100", "264", "x", "-8"] {
        let e = parse_descriptor_bits(bad).unwrap_err();
        assert!(e.contains("multiple of 8 in 64..=256") || e.contains(bad), "{bad}: {e}");
    }
    assert_eq!(parse_descriptor_bits("256"), Ok(256));
    assert_eq!(parse_descriptor_bits("64"), Ok(64));
    let p = FeatureParams { descriptor_bits: 40, ..FeatureParams::default() };
    let e = extract(&[0u8; 16], 4, 4, &p).unwrap_err().to_string();
    assert!(e.contains("got 40"), "{e}");
}

#[test]
fn all_pixel_formats_decode_and_extract() {
    let bytes = desk1().unwrap_or_default();
    let rgb = image::load_from_memory(&bytes).expect("desk decodes");
    let variants: Vec<(&str, DynamicImage, ImageFormat)> = vec![
        ("gray8 png", DynamicImage::ImageLuma8(rgb.to_luma8()), ImageFormat::Png),
        ("rgb8 png", DynamicImage::ImageRgb8(rgb.to_rgb8()), ImageFormat::Png),
        ("rgba8 png", DynamicImage::ImageRgba8(rgb.to_rgba8()), ImageFormat::Png),
        ("gray16 png", DynamicImage::ImageLuma16(rgb.to_luma16()), ImageFormat::Png),
        ("rgb16 png", DynamicImage::ImageRgb16(rgb.to_rgb16()), ImageFormat::Png),
        ("rgba16 png", DynamicImage::ImageRgba16(rgb.to_rgba16()), ImageFormat::Png),
        ("rgb8 jpeg", DynamicImage::ImageRgb8(rgb.to_rgb8()), ImageFormat::Jpeg),
        ("gray8 jpeg", DynamicImage::ImageLuma8(rgb.to_luma8()), ImageFormat::Jpeg),
    ];
    let reference = from_image_bytes(&bytes, &ImageLimits::default(), &FeatureParams::default()).expect("reference");
    for (name, img, fmt) in variants {
        let mut buf = Cursor::new(Vec::new());
        img.write_to(&mut buf, fmt).unwrap_or_else(|e| panic!("{name}: encode: {e}"));
        let f = from_image_bytes(buf.get_ref(), &ImageLimits::default(), &FeatureParams::default())
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!((f.width, f.height), (640, 480), "{name}");
        assert!(f.len() > 900, "{name}: {} features", f.len());
        // Same picture in another container: must still verify against the original.
        let v = verify(&reference, &f, None, &VerifyParams::default());
        assert!(v.verified, "{name}: {v:?}");
    }
}

#[test]
fn identical_image_verifies_and_pose_is_identity_or_absent() {
    let bytes = desk1().unwrap_or_default();
    let f = from_image_bytes(&bytes, &ImageLimits::default(), &FeatureParams::default()).expect("extract");
    let v = verify(&f, &f, None, &VerifyParams::default());
    assert!(v.verified && v.inliers > 500, "{v:?}");
    // Zero baseline: translation is undefined; the rotation, if reported, must be ~identity.
    let k = Intrinsics { fx: 517.3, fy: 516.5, cx: 318.6, cy: 255.3, dist: None };
    let v = verify(&f, &f, Some(&k), &VerifyParams::default());
    assert!(v.verified, "{v:?}");
    if let Some(p) = v.relative_pose {
        assert!(p.rotation().angle().to_degrees() < 1.0, "{p:?}");
    }
}

#[test]
fn downscaled_extraction_reports_original_pixels() {
    let bytes = desk1().unwrap_or_default();
    let img = image::load_from_memory(&bytes).expect("decode").to_luma8();
    // Upscale 2x: keypoints from a max_side=640 extraction must land in 1280x960 coordinates.
    let big = image::imageops::resize(&img, 1280, 960, image::imageops::FilterType::Triangle);
    let f = extract(big.as_raw(), 1280, 960, &FeatureParams::default()).expect("extract");
    assert_eq!((f.width, f.height), (1280, 960));
    let max_x = f.points.iter().map(|p| p[0]).fold(0.0f32, f32::max);
    assert!(max_x > 1000.0 && max_x < 1280.0, "max x {max_x}");
    // Keypoints whose descriptor is bit-identical in the original 640x480 extraction are the same
    // physical corner; their coordinates must map by x_big = 2 (x_small + 0.5) - 0.5.
    let small = extract(img.as_raw(), 640, 480, &FeatureParams::default()).expect("extract");
    let index: std::collections::HashMap<[u8; 32], [f32; 2]> =
        small.descriptors.iter().copied().zip(small.points.iter().copied()).collect();
    let mut same = 0;
    for (d, p) in f.descriptors.iter().zip(&f.points) {
        if let Some(s) = index.get(d) {
            let (ex, ey) = (2.0 * (s[0] + 0.5) - 0.5, 2.0 * (s[1] + 0.5) - 0.5);
            if (p[0] - ex).abs() < 2.0 && (p[1] - ey).abs() < 2.0 {
                same += 1;
            }
        }
    }
    assert!(same > 50, "only {same} keypoints map consistently");
}

#[test]
fn decode_never_panics_on_garbage() {
    for len in 0..300u32 {
        let mut b = noise(len.max(1), 1, len as u64 + 3);
        b.truncate(len as usize);
        let _ = Features::decode(&b);
        if b.len() >= 16 {
            // Valid version-1 header with an arbitrary count.
            b[..4].copy_from_slice(b"ORB1");
            b[4..8].copy_from_slice(&640u32.to_le_bytes());
            b[8..12].copy_from_slice(&480u32.to_le_bytes());
            b[12..16].copy_from_slice(&(len / 36).to_le_bytes());
            if let Ok(f) = Features::decode(&b) {
                assert_eq!(f.points.len(), f.descriptors.len());
                let _ = verify(&f, &f, None, &VerifyParams::default());
            }
        }
        if b.len() >= 17 {
            // Valid version-2 header, any descriptor width, an arbitrary count.
            b[..4].copy_from_slice(b"ORB2");
            b[4] = (len % 34) as u8;
            b[5..9].copy_from_slice(&640u32.to_le_bytes());
            b[9..13].copy_from_slice(&480u32.to_le_bytes());
            b[13..17].copy_from_slice(&(len / 17).to_le_bytes());
            if let Ok(f) = Features::decode(&b) {
                assert_eq!(f.points.len(), f.descriptors.len());
                let _ = verify(&f, &f, None, &VerifyParams::default());
            }
        }
    }
}
