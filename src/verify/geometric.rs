//! Geometric verification of a loop candidate: ORB Hamming 2-NN + Lowe ratio test, then
//! RANSAC on the fundamental matrix (no intrinsics) or the essential matrix + `recoverPose`
//! (intrinsics known, same camera for both frames).
//!
//! Pose convention: `RelativePose` is T_query_candidate, the pose of the CANDIDATE camera
//! expressed in the QUERY camera frame: X_query = R · X_candidate + t, with |t| = 1
//! (monocular scale is unknown). For world poses T_w_q, T_w_c: R = R_w_q^T · R_w_c.
//!
//! With depth at either frame's keypoints ([`super::depth`]) the pose is metric: OpenCV
//! `solvePnPRansac` (EPnP) on the verified matches, the candidate's keypoints lifted to 3D
//! (else the query's, and the result inverted), refined by `solvePnPRefineLM`; its covariance is
//! σ²(JᵀJ)⁻¹ of the refined reprojection problem (J from `projectPoints`, σ² the residual
//! variance), carried to the error of g2o's SE3 edge (translation, then rotation vector).

use nalgebra::{Matrix3, UnitQuaternion};
use opencv::calib3d;
use opencv::core::{self, Mat, Point2f, TermCriteria, Vector};
use opencv::prelude::*;

use super::error::VerifyError;
use super::features::Features;
use super::matching::ratio_matches;
pub use super::matching::Matcher;

/// Fewer correspondences than this cannot constrain F (8-point) robustly.
const MIN_POINTS: usize = 8;
/// Matching is O(n·m); refuse inputs far beyond any sane `max_features` instead of stalling.
const MAX_POINTS: usize = 20_000;
/// PnP inliers a metric pose needs; with fewer the loop keeps the unit direction. As many as a
/// verification needs: on tum-desk 4->2, 21 PnP inliers (of 33) gave a pose 21 cm off, the
/// loops with 44 and more 1.4-3.4 cm (docs/verification.md).
pub const MIN_PNP_INLIERS: usize = 30;
/// PnP RANSAC reprojection threshold (pixels).
const PNP_THRESHOLD_PX: f32 = 4.0;

/// The metric pose's noise model (its covariance, `pnp_covariance`): a keypoint's position is
/// good to this many pixels (one standard deviation) ...
const PIXEL_SIGMA_PX: f64 = 1.0;
/// ... and a depth sensor's depth to this much times its depth squared (metres; structured light
/// loses depth precision with the square of the distance; 2.5 mm at 1 m, 1 cm at 2 m) ...
const DEPTH_SIGMA_PER_M: f64 = 0.0025;
/// ... and a stereo depth to z² σ_d / (f·B): the disparity σ_d is the difference of two keypoint
/// positions, each good to `PIXEL_SIGMA_PX`, so √2 of it; f·B is the rig's (from the frame's
/// features). For EuRoC's rig (f·B ≈ 50 px·m) that is 2.8 cm at 1 m, 25 cm at 3 m.
const DISPARITY_SIGMA_PX: f64 = PIXEL_SIGMA_PX * std::f64::consts::SQRT_2;

/// One standard deviation of a depth `z` (metres) of the frame `f`'s keypoints: its stereo rig's
/// when the depths came from a stereo pair, else a depth sensor's.
fn depth_sigma(f: &Features, z: f64) -> f64 {
    if f.stereo_depth() {
        DISPARITY_SIGMA_PX * z * z / f64::from(f.stereo_focal_baseline)
    } else {
        DEPTH_SIGMA_PER_M * z * z
    }
}
/// What neither accounts for (depth-to-colour registration, calibration, rolling shutter), added
/// to every metric pose's covariance as a floor: one standard deviation per axis of translation
/// (metres) and of rotation (degrees). Fitted on the tum-desk RGB-D loops (the per-axis RMS of
/// their errors), judged on the EuRoC stereo loops (docs/verification.md).
const FLOOR_SIGMA_M: f64 = 0.0136;
const FLOOR_SIGMA_DEG: f64 = 0.22;
/// Inlier matches kept for people to look at (the loop inspector draws them); enough to see
/// where the views agree, small enough to keep with every loop.
pub const MAX_SHOWN_INLIERS: usize = 100;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// OpenCV radial-tangential order: k1 k2 p1 p2 k3.
    pub dist: Option<[f64; 5]>,
}

impl Intrinsics {
    pub fn validate(&self) -> Result<(), VerifyError> {
        if !(self.fx.is_finite() && self.fy.is_finite() && self.fx > 0.0 && self.fy > 0.0) {
            return Err(VerifyError::Invalid(format!(
                "invalid intrinsics: fx={} fy={} must be finite and > 0",
                self.fx, self.fy
            )));
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(VerifyError::Invalid(format!(
                "invalid intrinsics: cx={} cy={} must be finite",
                self.cx, self.cy
            )));
        }
        if let Some(d) = self.dist {
            if d.iter().any(|v| !v.is_finite()) {
                return Err(VerifyError::Invalid(format!("invalid intrinsics: distortion {d:?} must be finite")));
            }
        }
        Ok(())
    }

    fn camera_matrix(&self) -> opencv::Result<Mat> {
        Mat::from_slice_2d(&[[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
    }
}

#[derive(Clone, Debug)]
pub struct VerifyParams {
    /// Lowe ratio: keep a match if best < ratio · second best Hamming distance.
    pub ratio: f32,
    /// Geometric inliers needed to accept the loop.
    pub min_inliers: usize,
    /// RANSAC inlier threshold in ORIGINAL image pixels (Sampson / epipolar distance).
    pub ransac_threshold_px: f64,
    /// RANSAC confidence in (0, 1).
    pub confidence: f64,
    /// Robust estimator (OpenCV method flag).
    pub method: Robust,
    /// Upper bound on RANSAC iterations (bounds the cost of a non-loop candidate).
    pub max_iters: u32,
    /// Brute-force Hamming 2-NN implementation (identical results, different speed).
    pub matcher: Matcher,
}

/// Robust estimator used for F / E.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Robust {
    /// Classic OpenCV RANSAC (`FM_RANSAC` / `RANSAC`).
    Ransac,
    /// USAC with default settings (`USAC_DEFAULT`, OpenCV >= 4.5). Default: its SPRT test makes
    /// hopeless candidates ~10x cheaper than classic RANSAC and it finds more inliers on loops.
    UsacDefault,
    /// USAC with MAGSAC++ scoring (`USAC_MAGSAC`).
    UsacMagsac,
    /// USAC with GC-RANSAC local optimisation (`USAC_ACCURATE`).
    UsacAccurate,
}

impl Robust {
    fn flag(self) -> i32 {
        match self {
            Robust::Ransac => calib3d::RANSAC,
            Robust::UsacDefault => calib3d::USAC_DEFAULT,
            Robust::UsacMagsac => calib3d::USAC_MAGSAC,
            Robust::UsacAccurate => calib3d::USAC_ACCURATE,
        }
    }
}

impl Default for VerifyParams {
    fn default() -> Self {
        Self {
            ratio: 0.8,
            min_inliers: 30,
            ransac_threshold_px: 2.0,
            confidence: 0.999,
            method: Robust::UsacDefault,
            max_iters: 2000,
            matcher: Matcher::Scan,
        }
    }
}

/// A checked candidate: ORB matches after the ratio test, RANSAC inliers, and the verdict.
#[derive(Clone, Debug, PartialEq, serde::Serialize, utoipa::ToSchema)]
pub struct Verification {
    /// Matches surviving the ratio test (one per candidate keypoint).
    pub matches: usize,
    pub inliers: usize,
    /// inliers / matches (0 when there are no matches).
    pub inlier_ratio: f32,
    pub verified: bool,
    /// Why the candidate was not verified.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Only with intrinsics and only when verified; see the module doc for the convention.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub relative_pose: Option<RelativePose>,
    /// The relative pose's translation is in metres (depth at one of the frames), not a unit
    /// direction.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub metric: bool,
    /// 6x6 row-major covariance of a metric pose (x y z in m², then the rotation vector in
    /// rad²), the error g2o's EDGE_SE3:QUAT takes.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<f64>>, min_items = 36, max_items = 36)]
    pub covariance: Option<Vec<f64>>,
    /// Matches consistent with the metric pose (PnP inliers); 0 without one.
    #[serde(skip_serializing_if = "is_zero")]
    pub pose_inliers: usize,
    /// Up to [`MAX_SHOWN_INLIERS`] inlier matches as (query x, y, candidate x, y), each a
    /// fraction of its image's width or height; kept with the loop, not answered.
    #[serde(skip)]
    pub inlier_matches: Vec<[f32; 4]>,
}

impl Verification {
    /// Not checked at all (no features to check with), and why.
    pub fn unchecked(reason: String) -> Self {
        Self::rejected(0, 0, reason)
    }

    fn rejected(matches: usize, inliers: usize, reason: String) -> Self {
        Self {
            matches,
            inliers,
            inlier_ratio: ratio_of(inliers, matches),
            verified: false,
            reason: Some(reason),
            relative_pose: None,
            metric: false,
            covariance: None,
            pose_inliers: 0,
            inlier_matches: Vec::new(),
        }
    }
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// T_query_candidate: unit quaternion (qw >= 0) and unit translation direction; the one rigid
/// transform type, as kept with a loop (`store::loops::Transform`).
pub type RelativePose = crate::store::loops::Transform;

impl RelativePose {
    pub fn rotation(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(self.qw, self.qx, self.qy, self.qz))
    }
}

fn ratio_of(a: usize, b: usize) -> f32 {
    if b == 0 {
        0.0
    } else {
        a as f32 / b as f32
    }
}

/// Never panics: every failure (bad input, degenerate geometry, OpenCV error) is
/// `verified: false` with a reason. Invalid intrinsics are also a rejection with reason
/// "invalid intrinsics: ..."; call `Intrinsics::validate` at the API edge to turn it into a 400.
pub fn verify(query: &Features, candidate: &Features, intr: Option<&Intrinsics>, p: &VerifyParams) -> Verification {
    match verify_inner(query, candidate, intr, p) {
        Ok(v) => v,
        Err(reason) => Verification::rejected(0, 0, reason.to_string()),
    }
}

fn check_params(p: &VerifyParams) -> Result<(), VerifyError> {
    if !(p.ratio > 0.0 && p.ratio <= 1.0) {
        return Err(VerifyError::Invalid(format!("invalid params: ratio {} must be in (0, 1]", p.ratio)));
    }
    if !(p.ransac_threshold_px.is_finite() && p.ransac_threshold_px > 0.0) {
        return Err(VerifyError::Invalid(format!(
            "invalid params: ransac_threshold_px {} must be > 0",
            p.ransac_threshold_px
        )));
    }
    if !(p.confidence > 0.0 && p.confidence < 1.0) {
        return Err(VerifyError::Invalid(format!("invalid params: confidence {} must be in (0, 1)", p.confidence)));
    }
    Ok(())
}

fn verify_inner(
    q: &Features,
    c: &Features,
    intr: Option<&Intrinsics>,
    p: &VerifyParams,
) -> Result<Verification, VerifyError> {
    check_params(p)?;
    q.validate().map_err(|e| e.context("query "))?;
    c.validate().map_err(|e| e.context("candidate "))?;
    if let Some(k) = intr {
        k.validate()?;
        // One intrinsics set is only meaningful if both frames come from the same sensor mode.
        if (q.width, q.height) != (c.width, c.height) {
            return Err(VerifyError::Invalid(format!(
                "image sizes differ ({}x{} vs {}x{}) but one set of intrinsics was given",
                q.width, q.height, c.width, c.height
            )));
        }
    }
    if q.len() > MAX_POINTS || c.len() > MAX_POINTS {
        return Err(VerifyError::Invalid(format!(
            "too many features (query {}, candidate {}; limit {MAX_POINTS})",
            q.len(),
            c.len()
        )));
    }
    if q.len() < MIN_POINTS || c.len() < MIN_POINTS {
        return Ok(Verification::rejected(
            0,
            0,
            format!("too few features (query {}, candidate {})", q.len(), c.len()),
        ));
    }

    let matches = ratio_matches(q, c, p.ratio, p.matcher)?;
    let n = matches.len();
    if n < MIN_POINTS.max(p.min_inliers) {
        return Ok(Verification::rejected(n, 0, format!("too few matches after ratio test ({n})")));
    }

    // points1 = candidate, points2 = query, so that recoverPose yields X_q = R X_c + t.
    let mut pc = Vector::<Point2f>::with_capacity(n);
    let mut pq = Vector::<Point2f>::with_capacity(n);
    for &(qi, ci) in &matches {
        pq.push(Point2f::new(q.points[qi][0], q.points[qi][1]));
        pc.push(Point2f::new(c.points[ci][0], c.points[ci][1]));
    }

    let (mut mask, pose) = match intr {
        None => (
            fundamental_inliers(&pc, &pq, p)
                .map_err(|e| VerifyError::Failed(format!("fundamental RANSAC failed: {e}")))?,
            None,
        ),
        Some(k) => {
            essential_pose(&pc, &pq, k, p).map_err(|e| VerifyError::Failed(format!("essential RANSAC failed: {e}")))?
        }
    };
    // Zero baseline, pure rotation or a planar scene make F/E degenerate, and USAC then rejects
    // the model (identical images give 0 inliers). Such views are still consistent under a
    // homography, which is a valid verification; the pose is then left out (t undefined).
    if count(&mask) < p.min_inliers {
        let h = homography_inliers(&pc, &pq, p)
            .map_err(|e| VerifyError::Failed(format!("homography RANSAC failed: {e}")))?;
        if count(&h) >= p.min_inliers {
            mask = h;
        }
    }

    let inliers = count(&mask);
    if inliers < p.min_inliers {
        return Ok(Verification::rejected(n, inliers, format!("too few inliers ({inliers} < {})", p.min_inliers)));
    }
    let mut v = Verification {
        matches: n,
        inliers,
        inlier_ratio: ratio_of(inliers, n),
        verified: true,
        reason: None,
        relative_pose: pose,
        metric: false,
        covariance: None,
        pose_inliers: 0,
        inlier_matches: shown_inliers(q, c, &matches, &mask),
    };
    if let Some(k) = intr.filter(|_| q.has_depth() || c.has_depth()) {
        // A failed PnP leaves the verified loop with its direction (marked not metric).
        if let Ok(Some(m)) = metric_pose(q, c, &matches, &mask, k) {
            v.relative_pose = Some(m.pose);
            v.metric = true;
            v.covariance = Some(m.covariance);
            v.pose_inliers = m.inliers;
        }
    }
    Ok(v)
}

/// A metric relative pose (T_query_candidate), its covariance and its PnP inliers.
pub struct MetricPose {
    pub pose: RelativePose,
    pub covariance: Vec<f64>,
    pub inliers: usize,
}

/// Which frame's depth lifts the matches to 3D.
#[derive(Clone, Copy, PartialEq)]
enum Lifted {
    Candidate,
    Query,
}

/// PnP on the verified matches with depth on one side; None when too few matches have depth or
/// PnP finds fewer than [`MIN_PNP_INLIERS`] inliers.
pub fn metric_pose(
    q: &Features,
    c: &Features,
    matches: &[(usize, usize)],
    mask: &[bool],
    k: &Intrinsics,
) -> opencv::Result<Option<MetricPose>> {
    // The candidate's depth when it has it: the result is then T_query_candidate directly.
    let lifted = if c.has_depth() { Lifted::Candidate } else { Lifted::Query };
    let (from, to) = match lifted {
        Lifted::Candidate => (c, q),
        Lifted::Query => (q, c),
    };
    let kmat = k.camera_matrix()?;
    let mut obj = Vector::<core::Point3f>::new();
    let (mut src, mut dst) = (Vector::<Point2f>::new(), Vector::<Point2f>::new());
    for (&(qi, ci), _) in matches.iter().zip(mask).filter(|(_, &keep)| keep) {
        let (fi, ti) = match lifted {
            Lifted::Candidate => (ci, qi),
            Lifted::Query => (qi, ci),
        };
        let Some(z) = from.depth(fi) else { continue };
        src.push(Point2f::new(from.points[fi][0], from.points[fi][1]));
        dst.push(Point2f::new(to.points[ti][0], to.points[ti][1]));
        obj.push(core::Point3f::new(z, 0.0, 0.0));
    }
    if obj.len() < MIN_PNP_INLIERS {
        return Ok(None);
    }
    // Undistorted pixels (P = K): the lifted rays and the observations in one pinhole camera.
    let (src, dst) = match k.dist {
        Some(d) => (undistort(&src, &kmat, &d)?, undistort(&dst, &kmat, &d)?),
        None => (src, dst),
    };
    let mut points = Vector::<core::Point3f>::with_capacity(obj.len());
    for (p, o) in src.iter().zip(obj.iter()) {
        let z = o.x as f64;
        let x = (p.x as f64 - k.cx) / k.fx * z;
        let y = (p.y as f64 - k.cy) / k.fy * z;
        points.push(core::Point3f::new(x as f32, y as f32, z as f32));
    }
    let (mut rvec, mut tvec, mut inliers) = (Mat::default(), Mat::default(), Vector::<i32>::new());
    let found = calib3d::solve_pnp_ransac(
        &points,
        &dst,
        &kmat,
        &core::no_array(),
        &mut rvec,
        &mut tvec,
        false,
        500,
        PNP_THRESHOLD_PX,
        0.999,
        &mut inliers,
        calib3d::SOLVEPNP_EPNP,
    )?;
    if !found || inliers.len() < MIN_PNP_INLIERS {
        return Ok(None);
    }
    let mut obj_in = Vector::<core::Point3f>::with_capacity(inliers.len());
    let mut img_in = Vector::<Point2f>::with_capacity(inliers.len());
    for i in inliers.iter() {
        obj_in.push(points.get(i as usize)?);
        img_in.push(dst.get(i as usize)?);
    }
    let crit = TermCriteria::new(core::TermCriteria_COUNT + core::TermCriteria_EPS, 50, 1e-10)?;
    calib3d::solve_pnp_refine_lm(&obj_in, &img_in, &kmat, &core::no_array(), &mut rvec, &mut tvec, crit)?;
    let p = [
        *rvec.at::<f64>(0)?,
        *rvec.at::<f64>(1)?,
        *rvec.at::<f64>(2)?,
        *tvec.at::<f64>(0)?,
        *tvec.at::<f64>(1)?,
        *tvec.at::<f64>(2)?,
    ];
    if p.iter().any(|v| !v.is_finite()) {
        return Ok(None);
    }
    let sigma_z = |z: f64| depth_sigma(from, z);
    let Some(cov_p) = pnp_covariance(&obj_in, &img_in, &kmat, &rvec, &tvec, sigma_z)? else { return Ok(None) };
    // The pose as an edge measures it (T_query_candidate), from PnP's parameters.
    let edge = |p: &[f64; 6]| {
        let t = pnp_transform(p);
        match lifted {
            Lifted::Candidate => t,
            Lifted::Query => t.inverse(),
        }
    };
    let estimate = edge(&p);
    // g2o's error of a perturbed pose against the estimate: (R̂ᵀ(t − t̂), log(R̂ᵀR)).
    let error = |p: &[f64; 6]| {
        let d = estimate.inverse() * edge(p);
        let r = d.rotation.scaled_axis();
        [d.translation.x, d.translation.y, d.translation.z, r.x, r.y, r.z]
    };
    let mut g = nalgebra::Matrix6::<f64>::zeros();
    for j in 0..6 {
        let h = 1e-6;
        let (mut hi, mut lo) = (p, p);
        hi[j] += h;
        lo[j] -= h;
        let (a, b) = (error(&hi), error(&lo));
        for i in 0..6 {
            g[(i, j)] = (a[i] - b[i]) / (2.0 * h);
        }
    }
    let mut cov = g * cov_p * g.transpose();
    let (ft, fr) = (FLOOR_SIGMA_M.powi(2), FLOOR_SIGMA_DEG.to_radians().powi(2));
    for (i, floor) in [ft, ft, ft, fr, fr, fr].into_iter().enumerate() {
        cov[(i, i)] += floor;
    }
    let cov = (cov + cov.transpose()) * 0.5;
    if cov.iter().any(|v| !v.is_finite()) {
        return Ok(None);
    }
    let (t, rq) = (estimate.translation.vector, estimate.rotation);
    let s = if rq.w < 0.0 { -1.0 } else { 1.0 };
    let pose = RelativePose { qx: s * rq.i, qy: s * rq.j, qz: s * rq.k, qw: s * rq.w, tx: t.x, ty: t.y, tz: t.z };
    let covariance = (0..6).flat_map(|r| (0..6).map(move |c| (r, c))).map(|(r, c)| cov[(r, c)]).collect();
    Ok(Some(MetricPose { pose, covariance, inliers: inliers.len() }))
}

/// PnP's (rvec, tvec) as the transform it maps the lifted points by.
fn pnp_transform(p: &[f64; 6]) -> nalgebra::Isometry3<f64> {
    let r = UnitQuaternion::from_scaled_axis(nalgebra::Vector3::new(p[0], p[1], p[2]));
    nalgebra::Isometry3::from_parts(nalgebra::Translation3::new(p[3], p[4], p[5]), r)
}

/// The covariance of (rvec, tvec) of the refined reprojection problem, (Σ Jᵢᵀ Wᵢ Jᵢ)⁻¹ scaled by
/// the residuals' variance factor where that exceeds 1; None when it is singular. Each point's
/// residual covariance Wᵢ⁻¹ is its pixel noise plus its depth noise carried into the image:
/// σₚ²I + σ_z² (∂π/∂X · dX/dz)(∂π/∂X · dX/dz)ᵀ, where X = z·ray is the lifted point, ∂π/∂X is
/// `projectPoints`' Jacobian in tvec times R (Rodrigues), and σ_z = `sigma_z(z)` (`depth_sigma`).
fn pnp_covariance(
    obj: &Vector<core::Point3f>,
    img: &Vector<Point2f>,
    kmat: &Mat,
    rvec: &Mat,
    tvec: &Mat,
    sigma_z: impl Fn(f64) -> f64,
) -> opencv::Result<Option<nalgebra::Matrix6<f64>>> {
    let (mut projected, mut jac) = (Vector::<Point2f>::new(), Mat::default());
    calib3d::project_points(obj, rvec, tvec, kmat, &core::no_array(), &mut projected, &mut jac, 0.0)?;
    let n = obj.len();
    if jac.rows() as usize != 2 * n || (jac.cols() as usize) < 6 || n * 2 <= 6 {
        return Ok(None);
    }
    let mut rmat = Mat::default();
    calib3d::rodrigues(rvec, &mut rmat, &mut core::no_array())?;
    let mut r = Matrix3::<f64>::zeros();
    for i in 0..3 {
        for j in 0..3 {
            r[(i, j)] = *rmat.at_2d::<f64>(i as i32, j as i32)?;
        }
    }
    let mut info = nalgebra::Matrix6::<f64>::zeros();
    let mut chi2 = 0.0;
    for i in 0..n {
        let (pr, ob, x) = (projected.get(i)?, img.get(i)?, obj.get(i)?);
        let mut j = nalgebra::Matrix2x6::<f64>::zeros();
        for row in 0..2 {
            for c in 0..6 {
                j[(row, c)] = *jac.at_2d::<f64>((2 * i + row) as i32, c as i32)?;
            }
        }
        // The depth's direction in the image: d(projection)/dz = J_t · R · ray.
        let z = (x.z as f64).max(1e-6);
        let ray = nalgebra::Vector3::new(x.x as f64 / z, x.y as f64 / z, 1.0);
        let along = j.fixed_view::<2, 3>(0, 3) * (r * ray);
        let c = nalgebra::Matrix2::identity() * PIXEL_SIGMA_PX.powi(2) + along * along.transpose() * sigma_z(z).powi(2);
        let Some(w) = c.try_inverse() else { return Ok(None) };
        let e = nalgebra::Vector2::new((pr.x - ob.x) as f64, (pr.y - ob.y) as f64);
        chi2 += (e.transpose() * w * e)[(0, 0)];
        info += j.transpose() * w * j;
    }
    let factor = (chi2 / (2 * n - 6) as f64).max(1.0);
    Ok(info.try_inverse().map(|cov| cov * factor))
}

fn count(mask: &[bool]) -> usize {
    mask.iter().filter(|&&m| m).count()
}

/// The first inliers, each point as a fraction of its image's size (see `inlier_matches`).
fn shown_inliers(q: &Features, c: &Features, matches: &[(usize, usize)], mask: &[bool]) -> Vec<[f32; 4]> {
    let (qw, qh) = (q.width.max(1) as f32, q.height.max(1) as f32);
    let (cw, ch) = (c.width.max(1) as f32, c.height.max(1) as f32);
    matches
        .iter()
        .zip(mask)
        .filter(|(_, &keep)| keep)
        .take(MAX_SHOWN_INLIERS)
        .map(|(&(qi, ci), _)| {
            let (a, b) = (q.points[qi], c.points[ci]);
            [a[0] / qw, a[1] / qh, b[0] / cw, b[1] / ch]
        })
        .collect()
}

/// RANSAC's inlier mask as one flag per correspondence (empty: no model).
fn mask_flags(mask: &Mat, n: usize) -> opencv::Result<Vec<bool>> {
    if mask.empty() {
        return Ok(Vec::new());
    }
    let m = mask.data_bytes()?;
    if m.len() != n {
        return Err(opencv::Error::new(
            core::StsBadSize,
            format!("inlier mask has {} entries for {n} points", m.len()),
        ));
    }
    Ok(m.iter().map(|&v| v != 0).collect())
}

fn iters(p: &VerifyParams) -> i32 {
    i32::try_from(p.max_iters.max(1)).unwrap_or(i32::MAX)
}

fn fundamental_inliers(pc: &Vector<Point2f>, pq: &Vector<Point2f>, p: &VerifyParams) -> opencv::Result<Vec<bool>> {
    let mut mask = Mat::default();
    let f = calib3d::find_fundamental_mat(
        pc,
        pq,
        p.method.flag(),
        p.ransac_threshold_px,
        p.confidence,
        iters(p),
        &mut mask,
    )?;
    // Empty F means RANSAC found no model (degenerate configuration).
    if f.empty() {
        return Ok(Vec::new());
    }
    mask_flags(&mask, pc.len())
}

fn homography_inliers(pc: &Vector<Point2f>, pq: &Vector<Point2f>, p: &VerifyParams) -> opencv::Result<Vec<bool>> {
    let mut mask = Mat::default();
    let h = calib3d::find_homography_ext(
        pc,
        pq,
        p.method.flag(),
        p.ransac_threshold_px,
        &mut mask,
        iters(p),
        p.confidence,
    )?;
    if h.empty() {
        return Ok(Vec::new());
    }
    mask_flags(&mask, pc.len())
}

fn essential_pose(
    pc: &Vector<Point2f>,
    pq: &Vector<Point2f>,
    k: &Intrinsics,
    p: &VerifyParams,
) -> opencv::Result<(Vec<bool>, Option<RelativePose>)> {
    let kmat = k.camera_matrix()?;
    let (pc, pq) = match k.dist {
        Some(d) => (undistort(pc, &kmat, &d)?, undistort(pq, &kmat, &d)?),
        None => (pc.clone(), pq.clone()),
    };
    let mut mask = Mat::default();
    let e = calib3d::find_essential_mat(
        &pc,
        &pq,
        &kmat,
        p.method.flag(),
        p.confidence,
        p.ransac_threshold_px,
        iters(p),
        &mut mask,
    )?;
    // findEssentialMat may return several stacked 3x3 solutions (3k x 3); only 3x3 is usable.
    if e.rows() != 3 || e.cols() != 3 {
        return Ok((Vec::new(), None));
    }
    let inliers = mask_flags(&mask, pc.len())?;
    if count(&inliers) < p.min_inliers {
        return Ok((inliers, None));
    }
    let (mut r, mut t) = (Mat::default(), Mat::default());
    // RANSAC keeps the minimal-sample E; a least-squares 8-point E on all inliers (normalised
    // coordinates) halves the rotation error on the EuRoC loops (see the prototype report).
    let (nc, nq) = normalized_inliers(&pc, &pq, &inliers, k)?;
    if nc.len() < MIN_POINTS {
        return Ok((inliers, None));
    }
    let e8 = calib3d::find_fundamental_mat(&nc, &nq, calib3d::FM_8POINT, 0.0, 0.0, 0, &mut core::no_array())?;
    let e = if e8.rows() == 3 && e8.cols() == 3 { e8 } else { e };
    let eye = Mat::from_slice_2d(&[[1.0f64, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])?;
    let mut pose_mask = Mat::default();
    // `recover_pose_estimated` is the (E, p1, p2, K, R, t, mask) overload; `recover_pose` takes focal/pp.
    let good = calib3d::recover_pose_estimated(&e, &nc, &nq, &eye, &mut r, &mut t, &mut pose_mask)?;
    if good <= 0 {
        return Ok((inliers, None));
    }
    Ok((inliers, to_pose(&r, &t)?))
}

fn normalized_inliers(
    pc: &Vector<Point2f>,
    pq: &Vector<Point2f>,
    inliers: &[bool],
    k: &Intrinsics,
) -> opencv::Result<(Vector<Point2f>, Vector<Point2f>)> {
    let norm = |p: Point2f| Point2f::new(((p.x as f64 - k.cx) / k.fx) as f32, ((p.y as f64 - k.cy) / k.fy) as f32);
    let mut nc = Vector::new();
    let mut nq = Vector::new();
    for (i, &keep) in inliers.iter().enumerate() {
        if keep {
            nc.push(norm(pc.get(i)?));
            nq.push(norm(pq.get(i)?));
        }
    }
    Ok((nc, nq))
}

fn undistort(pts: &Vector<Point2f>, kmat: &Mat, d: &[f64; 5]) -> opencv::Result<Vector<Point2f>> {
    let dist = Mat::from_slice(d)?;
    let mut out = Vector::<Point2f>::new();
    // Default is 5 fixed iterations, too few for strong radial distortion (EuRoC k1=-0.28) at the edges.
    let crit = TermCriteria::new(core::TermCriteria_COUNT + core::TermCriteria_EPS, 20, 1e-8)?;
    // P = K keeps the output in pixels, so the RANSAC threshold stays in pixels.
    calib3d::undistort_points_iter(pts, &mut out, kmat, &dist, &core::no_array(), kmat, crit)?;
    Ok(out)
}

fn to_pose(r: &Mat, t: &Mat) -> opencv::Result<Option<RelativePose>> {
    if r.rows() != 3 || r.cols() != 3 || t.total() != 3 {
        return Ok(None);
    }
    let mut m = Matrix3::<f64>::zeros();
    for i in 0..3 {
        for j in 0..3 {
            m[(i, j)] = *r.at_2d::<f64>(i as i32, j as i32)?;
        }
    }
    let tv = [*t.at::<f64>(0)?, *t.at::<f64>(1)?, *t.at::<f64>(2)?];
    if m.iter().chain(tv.iter()).any(|v| !v.is_finite()) {
        return Ok(None);
    }
    let norm = (tv[0] * tv[0] + tv[1] * tv[1] + tv[2] * tv[2]).sqrt();
    if norm <= f64::EPSILON {
        return Ok(None);
    }
    let q = UnitQuaternion::from_matrix(&m);
    // q and -q are the same rotation; fix the sign so results are comparable.
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    Ok(Some(RelativePose {
        qx: s * q.i,
        qy: s * q.j,
        qz: s * q.k,
        qw: s * q.w,
        tx: tv[0] / norm,
        ty: tv[1] / norm,
        tz: tv[2] / norm,
    }))
}
