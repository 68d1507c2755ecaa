//! Depth at a frame's keypoints from the right image of a stereo pair: both images' ORB keypoints
//! rectified (OpenCV `stereoRectify` + `undistortPoints`), each left keypoint matched along its
//! rectified row (±2 px, Hamming ratio test), its disparity turned into depth in the left camera.
//! The result fills [`Features::depths`] as a depth image's would, so a stereo frame verifies
//! with metric poses like an RGB-D one.
use super::error::VerifyError;
use super::features::Features;
use super::geometric::Intrinsics;
use nalgebra::{Matrix3, Vector3};
use opencv::calib3d;
use opencv::core::{self, Mat, Point2f, Size, TermCriteria, Vector};
use opencv::prelude::*;

/// Rows a right keypoint may be off its left keypoint's after rectification (pixels).
const ROW_TOLERANCE_PX: f32 = 2.0;
/// Lowe ratio of the best to the second-best Hamming distance along the row.
const RATIO: f32 = 0.8;
/// Disparities below this are too far to measure (pixels).
const MIN_DISPARITY_PX: f32 = 1.0;

/// A calibrated stereo pair, rectified once.
pub struct StereoRig {
    left: Intrinsics,
    right: Intrinsics,
    /// Rectifying rotations and projections (OpenCV's R1, P1, R2, P2).
    r1: Mat,
    p1: Mat,
    r2: Mat,
    p2: Mat,
    /// R1 as a matrix: the rectified left camera's rotation from the left camera.
    r1m: Matrix3<f64>,
    /// Rectified focal length, principal point and baseline (metres).
    f: f64,
    cx: f64,
    cy: f64,
    baseline: f64,
}

fn dist(d: Option<[f64; 5]>) -> opencv::Result<Mat> {
    Mat::from_slice(&d.unwrap_or([0.0; 5]))?.try_clone()
}

fn camera_matrix(k: &Intrinsics) -> opencv::Result<Mat> {
    Mat::from_slice_2d(&[[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]])
}

impl StereoRig {
    /// The rig of a left camera, a right camera and the right camera's pose in the left's
    /// (X_right = R X_left + t, metres) for images of `width` x `height`.
    pub fn new(
        left: Intrinsics,
        right: Intrinsics,
        rotation: [f64; 9],
        translation: [f64; 3],
        width: u32,
        height: u32,
    ) -> Result<Self, VerifyError> {
        left.validate()?;
        right.validate()?;
        let r = Matrix3::from_row_slice(&rotation);
        if rotation.iter().chain(&translation).any(|v| !v.is_finite())
            || (r.transpose() * r - Matrix3::identity()).abs().max() > 1e-3
            || (r.determinant() - 1.0).abs() > 1e-3
        {
            return Err(VerifyError::Invalid(format!("stereo rotation {rotation:?} is not a rotation matrix")));
        }
        let baseline = Vector3::from_row_slice(&translation).norm();
        if baseline.is_nan() || baseline <= 1e-6 {
            return Err(VerifyError::Invalid("stereo translation is zero: no baseline".into()));
        }
        let rectify = || -> opencv::Result<Self> {
            let r = Mat::from_slice_2d(&[
                [rotation[0], rotation[1], rotation[2]],
                [rotation[3], rotation[4], rotation[5]],
                [rotation[6], rotation[7], rotation[8]],
            ])?;
            let t = Mat::from_slice_2d(&[[translation[0]], [translation[1]], [translation[2]]])?;
            let (mut r1, mut r2, mut p1, mut p2, mut q) =
                (Mat::default(), Mat::default(), Mat::default(), Mat::default(), Mat::default());
            let size = Size::new(width as i32, height as i32);
            calib3d::stereo_rectify(
                &camera_matrix(&left)?,
                &dist(left.dist)?,
                &camera_matrix(&right)?,
                &dist(right.dist)?,
                size,
                &r,
                &t,
                &mut r1,
                &mut r2,
                &mut p1,
                &mut p2,
                &mut q,
                calib3d::CALIB_ZERO_DISPARITY,
                0.0,
                size,
                None,
                None,
            )?;
            let mut r1m = Matrix3::zeros();
            for i in 0..3 {
                for j in 0..3 {
                    r1m[(i, j)] = *r1.at_2d::<f64>(i as i32, j as i32)?;
                }
            }
            let f = *p1.at_2d::<f64>(0, 0)?;
            let (cx, cy) = (*p1.at_2d::<f64>(0, 2)?, *p1.at_2d::<f64>(1, 2)?);
            // P2[0,3] = -f * baseline (the right camera sits at +baseline along the rectified x).
            let baseline = (-*p2.at_2d::<f64>(0, 3)? / *p2.at_2d::<f64>(0, 0)?).abs();
            Ok(Self { left, right, r1, p1, r2, p2, r1m, f, cx, cy, baseline })
        };
        rectify().map_err(|e| VerifyError::Invalid(format!("stereo rectification failed: {e}")))
    }

    /// A rectified pair with this baseline (metres): the right camera is the left one moved
    /// along its x axis.
    pub fn rectified(k: Intrinsics, baseline: f64, width: u32, height: u32) -> Result<Self, VerifyError> {
        if !(baseline.is_finite() && baseline > 0.0) {
            return Err(VerifyError::Invalid(format!("stereo baseline {baseline} must be a finite number > 0")));
        }
        let eye = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        Self::new(k, k, eye, [-baseline, 0.0, 0.0], width, height)
    }

    pub fn baseline(&self) -> f64 {
        self.baseline
    }

    /// The rectified focal length (pixels).
    pub fn focal(&self) -> f64 {
        self.f
    }

    fn rectify_points(&self, f: &Features, k: &Intrinsics, r: &Mat, p: &Mat) -> opencv::Result<Vec<[f32; 2]>> {
        let pts: Vector<Point2f> = f.points.iter().map(|p| Point2f::new(p[0], p[1])).collect();
        if pts.is_empty() {
            return Ok(Vec::new());
        }
        let mut out = Vector::<Point2f>::new();
        let crit = TermCriteria::new(core::TermCriteria_COUNT + core::TermCriteria_EPS, 20, 1e-8)?;
        calib3d::undistort_points_iter(&pts, &mut out, &camera_matrix(k)?, &dist(k.dist)?, r, p, crit)?;
        Ok(out.iter().map(|p| [p.x, p.y]).collect())
    }

    /// Each left keypoint's depth (metres along the left camera's axis; 0 where no right
    /// keypoint matched it along its row), from the right image's features.
    pub fn depths(&self, left: &Features, right: &Features) -> Result<Vec<f32>, VerifyError> {
        let failed = |e: opencv::Error| VerifyError::Failed(format!("stereo matching failed: {e}"));
        let l = self.rectify_points(left, &self.left, &self.r1, &self.p1).map_err(failed)?;
        let r = self.rectify_points(right, &self.right, &self.r2, &self.p2).map_err(failed)?;
        let bytes = left.descriptor_bytes.min(right.descriptor_bytes).max(1);
        // Right keypoints by rectified row, so each left keypoint looks at a few rows only.
        let mut by_row: Vec<(f32, usize)> = r.iter().enumerate().map(|(j, p)| (p[1], j)).collect();
        by_row.sort_by(|a, b| a.0.total_cmp(&b.0));
        let r1t = self.r1m.transpose();
        let mut out = vec![0f32; left.len()];
        for (i, pl) in l.iter().enumerate() {
            let from = by_row.partition_point(|(y, _)| *y < pl[1] - ROW_TOLERANCE_PX);
            let (mut best, mut second, mut at) = (u32::MAX, u32::MAX, None);
            for &(y, j) in &by_row[from..] {
                if y > pl[1] + ROW_TOLERANCE_PX {
                    break;
                }
                if pl[0] - r[j][0] < MIN_DISPARITY_PX {
                    continue;
                }
                let d: u32 = left.descriptors[i][..bytes]
                    .iter()
                    .zip(&right.descriptors[j][..bytes])
                    .map(|(a, b)| (a ^ b).count_ones())
                    .sum();
                if d < best {
                    (second, best, at) = (best, d, Some(j));
                } else if d < second {
                    second = d;
                }
            }
            let Some(j) = at else { continue };
            if second != u32::MAX && best as f32 >= RATIO * second as f32 {
                continue;
            }
            // Too many differing bits for the same corner: a quarter of those compared.
            if best as usize * 4 > bytes * 8 {
                continue;
            }
            let disparity = (pl[0] - r[j][0]) as f64;
            let z = self.f * self.baseline / disparity;
            let x = (pl[0] as f64 - self.cx) / self.f * z;
            let y = (pl[1] as f64 - self.cy) / self.f * z;
            // Back from the rectified left camera to the left camera.
            let p = r1t * Vector3::new(x, y, z);
            if p.z.is_finite() && p.z > 0.0 {
                out[i] = p.z as f32;
            }
        }
        Ok(out)
    }

    /// Fills `left`'s depths from the right image's features.
    pub fn attach(&self, left: &mut Features, right: &Features) -> Result<(), VerifyError> {
        if (left.width, left.height) != (right.width, right.height) {
            return Err(VerifyError::Invalid(format!(
                "the right image is {}x{}, the left {}x{}",
                right.width, right.height, left.width, left.height
            )));
        }
        left.depths = self.depths(left, right)?;
        left.stereo_focal_baseline = (self.f * self.baseline) as f32;
        Ok(())
    }
}
