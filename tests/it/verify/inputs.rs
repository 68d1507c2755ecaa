//! Geometric verification on bad and degenerate inputs. Frames without texture, tiny frames and
//! malformed feature records never panic: Err from extraction/decoding,
//! `verified: false` with a reason from verification.

use crate::common::*;
use loopd::model::preprocess::ImageLimits;
use std::io::Cursor;

use image::{DynamicImage, ImageFormat};
use loopd::verify::features::{extract, from_image_bytes, FeatureParams, Features};
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

#[test]
fn encode_decode_roundtrip_and_size() {
    let bytes = desk1().unwrap_or_default();
    let f = from_image_bytes(
        &bytes,
        &ImageLimits::default(),
        &FeatureParams { max_features: 1500, ..FeatureParams::default() },
    )
    .expect("extract");
    assert_eq!(f.len(), 1500);
    let blob = f.encode();
    assert_eq!(blob.len(), Features::encoded_len(1500));
    assert_eq!(blob.len(), 54_016);
    assert!(blob.len() <= 64 * 1024);
    let g = Features::decode(&blob).expect("decode");
    assert_eq!((g.width, g.height, g.len()), (f.width, f.height, f.len()));
    assert_eq!(g.descriptors, f.descriptors);
    for (a, b) in f.points.iter().zip(&g.points) {
        assert!((a[0] - b[0]).abs() < 0.01 && (a[1] - b[1]).abs() < 0.01, "{a:?} vs {b:?}");
    }
    // Malformed blobs.
    assert!(Features::decode(&blob[..blob.len() - 1]).unwrap_err().to_string().contains("expected"));
    assert!(Features::decode(&blob[..10]).unwrap_err().to_string().contains("too short"));
    // A record that breaks its format is Corrupt: the server's data, not the client's input.
    assert!(matches!(Features::decode(&blob[..10]), Err(VerifyError::Corrupt(_))));
    let mut bad = blob.clone();
    bad[0] = b'X';
    assert!(Features::decode(&bad).unwrap_err().to_string().contains("magic"));
    let mut huge = blob[..16].to_vec();
    huge[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(Features::decode(&huge).unwrap_err().to_string().contains("exceeds limit"));
    let mut zero = blob;
    zero[4..8].copy_from_slice(&0u32.to_le_bytes());
    assert!(Features::decode(&zero).unwrap_err().to_string().contains("invalid image size"));
    let empty = Features { width: 1, height: 1, points: vec![], descriptors: vec![] };
    assert_eq!(Features::decode(&empty.encode()).expect("empty roundtrip"), empty);
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
            // Valid header with an arbitrary count.
            b[..4].copy_from_slice(b"ORB1");
            b[4..8].copy_from_slice(&640u32.to_le_bytes());
            b[8..12].copy_from_slice(&480u32.to_le_bytes());
            b[12..16].copy_from_slice(&(len / 36).to_le_bytes());
            if let Ok(f) = Features::decode(&b) {
                assert_eq!(f.points.len(), f.descriptors.len());
                let _ = verify(&f, &f, None, &VerifyParams::default());
            }
        }
    }
}
