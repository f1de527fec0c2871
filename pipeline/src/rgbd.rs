//! The RGB-D feature method: `base1_from_base2` from features seen by both arms'
//! cameras, lifted to 3-D with the aligned depth images. No target is needed in the
//! images themselves; the hand-eyes come from the caller (or, in
//! [`rgbd_base_to_base`], from the dataset's board through [`crate::hand_eye`]).
//!
//! 0. Per robot, its depth against its colour images and its motion
//!    ([`crate::depth_checks`]): depth of another camera, or at another scale (a
//!    wrong depth unit), is refused by name; a depth unit that puts the scene
//!    outside the working range too ([`PipelineError::DepthOutOfRange`]).
//! 1. Per image: features ([`b2b_vision::features`], SIFT by default).
//! 2. Per image pair (robot 1 capture i, robot 2 capture j): ratio-test and
//!    cross-checked matches; each end lifted to 3-D ([`lift_pixel`]: the pixel is
//!    undistorted with the camera model, its z-depth interpolated bilinearly; holes
//!    (0) and depth discontinuities are skipped).
//! 3. RANSAC + Umeyama (`b2b_calib::procrustes::ransac_rigid`) gives
//!    `camera1_from_camera2`; fewer than [`RgbdOptions::min_inliers`] inliers rejects the
//!    pair with the reason. Chained:
//!    `base1_from_base2 = base1_from_flange1 · flange1_from_camera1 · camera1_from_camera2
//!    · (base2_from_flange2 · flange2_from_camera2)⁻¹`.
//! 4. [`combine_pairs`]: the pairs' estimates are screened against their median
//!    (translation: component-wise median; rotation: the medoid) with a MAD rule:
//!    a pair is rejected when its distance exceeds
//!    `max(k · 1.4826 · MAD, floor)` (k = 3, floors 5 mm and 0.5°). The accepted ones
//!    are averaged, weighted by inlier count: rotations by Markley's average,
//!    translations by the weighted mean. Pairs share views (robot 1's view i is in
//!    every pair (i, ·)), and a view's error (its flange pose, its depth) is in all of
//!    them, so the pairs are not independent: the covariance of the mean is
//!    clustered by view (two-way cluster-robust, [`combine_pairs_by_view`]), with a
//!    floor from the RANSAC residuals so a single pair is not reported as exact.
//!    Dividing the pairs' spread by their number instead, as if they were
//!    independent, put only 20–44 % of the touches inside the predicted 95 % bound.
//!    Given the hand-eyes' covariances, their propagation is added (not
//!    divided by the number of pairs: all pairs share the same hand-eye error).

use std::time::Instant;

use b2b_calib::camera::CameraModel;
use b2b_calib::metrics::median;
use b2b_calib::metrics::{predicted_error, workspace_points};
use b2b_calib::pose::{adjoint, average_rotations, geodesic_angle, left_difference};
use b2b_calib::procrustes::{RansacOptions, ransac_rigid};
use b2b_calib::refine::RefineOptions;
use b2b_calib::{CalibError, Iso3};
use b2b_dataset::Dataset;
use b2b_protocol::messages::FeatureSet;
use b2b_protocol::{
    CalibrationResult, CaptureSummary, Pose, PredictedError, RESULT_FORMAT, RejectedCapture,
    Timings,
};
use b2b_vision::features::{
    DepthImage, FeatureKind, FeatureMatch, FeatureOptions, Features, detect_features, load_depth,
    match_features, match_features_among,
};
use nalgebra::{Matrix6, Point2, Point3, Translation3, Vector3};

use crate::depth_checks::{DepthCheck, check_robot_depth};
use crate::{HandEyeChoice, PipelineError, RobotSetup, hand_eye, observe_robot};

/// Settings of the RGB-D method.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RgbdOptions {
    pub features: FeatureOptions,
    /// RANSAC over the lifted matches; `threshold` is the 3-D inlier distance (m).
    pub ransac: RansacOptions,
    /// A pair with fewer RANSAC inliers is rejected.
    pub min_inliers: usize,
    /// A depth sample is a discontinuity when its 3x3 neighbourhood spans more than
    /// `depth_jump_rel · z + depth_jump_abs_m`.
    pub depth_jump_rel: f64,
    pub depth_jump_abs_m: f64,
    /// Depth outside this range (m) is not used.
    pub min_depth_m: f64,
    pub max_depth_m: f64,
    /// MAD rule for pairs: reject beyond `max(k · 1.4826 · MAD, floor)`.
    pub mad_k: f64,
    pub translation_floor_m: f64,
    pub rotation_floor_rad: f64,
}

impl RgbdOptions {
    /// The defaults with another feature kind.
    pub fn with_kind(kind: FeatureKind) -> Self {
        let mut options = RgbdOptions::default();
        options.features.kind = kind;
        options
    }
}

impl Default for RgbdOptions {
    fn default() -> Self {
        RgbdOptions {
            features: FeatureOptions::default(),
            ransac: RansacOptions {
                threshold: 0.005,
                iterations: 2000,
                min_inliers: 3,
                seed: 0,
                confidence: 0.9999,
            },
            min_inliers: 20,
            depth_jump_rel: 0.02,
            depth_jump_abs_m: 0.003,
            min_depth_m: 0.1,
            max_depth_m: 6.0,
            mad_k: 3.0,
            translation_floor_m: 0.005,
            rotation_floor_rad: 0.5f64.to_radians(),
        }
    }
}

/// One capture's colour features, each lifted to 3-D with the aligned depth, with
/// where it came from.
#[derive(Debug)]
pub struct RgbdView {
    /// 1-based row of the robot's `captures.csv` (live: capture index + 1).
    pub row: usize,
    pub image: String,
    pub base_from_flange: Iso3,
    pub features: Features,
    /// Each keypoint in the camera frame ([`lift_pixel`]); `None` where its depth
    /// is not usable.
    pub points: LiftedPoints,
}

/// Features and their lifted points as an agent publishes them.
pub fn feature_set(
    features: &Features,
    points: &LiftedPoints,
) -> Result<FeatureSet, PipelineError> {
    let (descriptor_len, descriptors) = features.descriptor_bytes()?;
    Ok(FeatureSet {
        kind: features.kind.name().to_owned(),
        pixels: features.pixels.iter().map(|p| [p.x, p.y]).collect(),
        responses: features.responses.clone(),
        points_camera: points.iter().map(|p| p.map(|p| [p.x, p.y, p.z])).collect(),
        descriptor_len,
        descriptors,
    })
}

impl RgbdView {
    /// The view as an agent publishes it.
    pub fn to_feature_set(&self) -> Result<FeatureSet, PipelineError> {
        feature_set(&self.features, &self.points)
    }

    /// A view from a published feature set (validated on receipt; checked again
    /// here because the descriptors must make an OpenCV matrix).
    pub fn from_feature_set(
        row: usize,
        image: String,
        base_from_flange: Iso3,
        set: &FeatureSet,
    ) -> Result<RgbdView, PipelineError> {
        let kind = FeatureKind::parse(&set.kind)?;
        if set.points_camera.len() != set.pixels.len() {
            return Err(PipelineError::FeatureCountMismatch {
                row,
                keypoints: set.pixels.len(),
                points: set.points_camera.len(),
            });
        }
        let features = Features::from_parts(
            kind,
            set.pixels.iter().map(|p| Point2::new(p[0], p[1])).collect(),
            set.responses.clone(),
            set.descriptor_len,
            &set.descriptors,
        )?;
        Ok(RgbdView {
            row,
            image,
            base_from_flange,
            features,
            points: set
                .points_camera
                .iter()
                .map(|p| p.map(Point3::from))
                .collect(),
        })
    }
}

/// Each keypoint in the camera frame, `None` where its depth is not usable.
pub type LiftedPoints = Vec<Option<Point3<f64>>>;

/// Lifts every keypoint ([`lift_pixel`]); `None` where the depth is not usable.
pub fn lift_features(
    camera: &CameraModel,
    features: &Features,
    depth: &DepthImage,
    unit_m: f64,
    options: &RgbdOptions,
) -> LiftedPoints {
    features
        .pixels
        .iter()
        .map(|p| lift_pixel(camera, depth, unit_m, p, options).ok())
        .collect()
}

/// Detects features in a grey image and lifts them with its aligned depth: what an
/// agent does per capture, and [`load_views`] per dataset row.
pub fn detect_and_lift(
    camera: &CameraModel,
    gray: &b2b_vision::GrayImage,
    depth: &DepthImage,
    unit_m: f64,
    options: &RgbdOptions,
) -> Result<(Features, LiftedPoints), PipelineError> {
    if (depth.width, depth.height) != (camera.width, camera.height) {
        return Err(PipelineError::DepthNotAligned {
            depth_file: None,
            depth_width: depth.width,
            depth_height: depth.height,
            colour_width: camera.width,
            colour_height: camera.height,
        });
    }
    let features = detect_features(gray, &options.features)?;
    let points = lift_features(camera, &features, depth, unit_m, options);
    Ok((features, points))
}

/// What happened to one image pair.
#[derive(Debug, Clone, PartialEq)]
pub struct PairEstimate {
    /// Rows (1-based) of robot 1's and robot 2's `captures.csv`.
    pub rows: [usize; 2],
    pub matches: usize,
    /// Matches with valid depth at both ends.
    pub lifted: usize,
    pub inliers: usize,
    /// RMS 3-D residual of the inliers (m).
    pub rms_m: f64,
    /// RMS distance of the inlier points from their centroid in camera 1 (m).
    pub spread_m: f64,
    pub camera1_from_camera2: Option<Iso3>,
    pub base1_from_base2: Option<Iso3>,
    /// Accepted into the final average.
    pub accepted: bool,
    /// Why not, when rejected.
    pub reason: Option<String>,
}

/// The method's result and what each pair contributed.
#[derive(Debug, Clone)]
pub struct RgbdRun {
    pub result: CalibrationResult,
    pub pairs: Vec<PairEstimate>,
    /// The mean over accepted pairs of their inlier points' centroid, in base 1 (m):
    /// the centre of the workspace over which the touch error is predicted.
    pub scene_centre_in_base1: Point3<f64>,
    /// Each robot's depth against its colour images and its motion
    /// ([`crate::depth_checks`]).
    pub depth_checks: Vec<DepthCheck>,
}

/// Lifts a pixel to a 3-D point in the camera frame, or says why not: outside the
/// image, a hole (0) in its 2x2 interpolation cell or 3x3 neighbourhood, a depth
/// discontinuity, or depth outside the working range.
pub fn lift_pixel(
    camera: &CameraModel,
    depth: &DepthImage,
    unit_m: f64,
    pixel: &Point2<f64>,
    options: &RgbdOptions,
) -> Result<Point3<f64>, &'static str> {
    if !(pixel.x.is_finite() && pixel.y.is_finite()) {
        return Err("non-finite pixel");
    }
    let (u0, v0) = (pixel.x.floor() as i64, pixel.y.floor() as i64);
    let (uc, vc) = (pixel.x.round() as i64, pixel.y.round() as i64);
    let (mut lo, mut hi) = (u16::MAX, 0u16);
    for dv in -1..=1 {
        for du in -1..=1 {
            let d = depth
                .at(uc + du, vc + dv)
                .ok_or("outside the depth image")?;
            if d == 0 {
                return Err("depth hole");
            }
            lo = lo.min(d);
            hi = hi.max(d);
        }
    }
    let mut cell = [0.0f64; 4];
    for (k, (du, dv)) in [(0, 0), (1, 0), (0, 1), (1, 1)].into_iter().enumerate() {
        let d = depth
            .at(u0 + du, v0 + dv)
            .ok_or("outside the depth image")?;
        if d == 0 {
            return Err("depth hole");
        }
        cell[k] = f64::from(d) * unit_m;
    }
    let (fx, fy) = (pixel.x - u0 as f64, pixel.y - v0 as f64);
    let z = (cell[0] * (1.0 - fx) + cell[1] * fx) * (1.0 - fy)
        + (cell[2] * (1.0 - fx) + cell[3] * fx) * fy;
    let span = f64::from(hi - lo) * unit_m;
    if span > options.depth_jump_rel * z + options.depth_jump_abs_m {
        return Err("depth discontinuity");
    }
    if z < options.min_depth_m || z > options.max_depth_m {
        return Err("depth outside the working range");
    }
    let xy = camera.unproject(pixel);
    Ok(Point3::new(xy.x * z, xy.y * z, z))
}

/// Lifts both ends of every match; returns the matched 3-D points in camera 1 and
/// camera 2 (pairs where either end fails are skipped).
pub fn lift_matches(
    cameras: [&CameraModel; 2],
    depths: [(&DepthImage, f64); 2],
    matches: &[FeatureMatch],
    options: &RgbdOptions,
) -> (Vec<Point3<f64>>, Vec<Point3<f64>>) {
    let mut p1 = Vec::with_capacity(matches.len());
    let mut p2 = Vec::with_capacity(matches.len());
    for m in matches {
        let a = lift_pixel(cameras[0], depths[0].0, depths[0].1, &m.pixel1, options);
        let b = lift_pixel(cameras[1], depths[1].0, depths[1].1, &m.pixel2, options);
        if let (Ok(a), Ok(b)) = (a, b) {
            p1.push(a);
            p2.push(b);
        }
    }
    (p1, p2)
}

/// Two views' matched features whose ends both have a lifted point.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewMatches {
    /// Matches before lifting.
    pub matches: usize,
    /// The lifted matches' points in the first view's camera ...
    pub points1: Vec<Point3<f64>>,
    /// ... and in the second's.
    pub points2: Vec<Point3<f64>>,
}

/// Matches two views' features ([`match_features`]) and keeps the matches
/// whose ends both have a lifted point.
pub fn match_views(
    a: &RgbdView,
    b: &RgbdView,
    options: &RgbdOptions,
) -> Result<ViewMatches, PipelineError> {
    let matches = match_features(&a.features, &b.features, &options.features)?;
    Ok(ViewMatches::lifted(a, b, &matches))
}

impl ViewMatches {
    /// `matches` between `a` and `b`, kept where both ends have a lifted point.
    fn lifted(a: &RgbdView, b: &RgbdView, matches: &[FeatureMatch]) -> ViewMatches {
        let (points1, points2) = matches
            .iter()
            .filter_map(|m| match (a.points.get(m.index1), b.points.get(m.index2)) {
                (Some(Some(p)), Some(Some(q))) => Some((*p, *q)),
                _ => None,
            })
            .unzip();
        ViewMatches {
            matches: matches.len(),
            points1,
            points2,
        }
    }
}

/// How far from its predicted place [`match_views_near`] looks for a feature:
/// 0.05 on the normalised image plane, about 2.9° of view at the image's
/// centre (29 px at a 580 px focal length; 3 cm sideways at 0.6 m).
pub const NEAR_GATE: f64 = 0.05;

/// [`match_views`] where `b_from_a` predicts where `a`'s camera stands in
/// `b`'s: each of `a`'s lifted features is compared only with `b`'s lifted
/// features whose viewing direction lies within `gate` of its predicted one
/// (distance on the normalised image plane, `x/z, y/z`). Only features with
/// a lifted point take part (the others cannot enter a fit). The tests are
/// [`match_features`]'s, among those candidates. Cost: a few descriptor
/// distances per feature instead of one per pair of features; and a pattern
/// repeated further apart than the gate cannot be confused.
pub fn match_views_near(
    a: &RgbdView,
    b: &RgbdView,
    b_from_a: &Iso3,
    gate: f64,
    options: &RgbdOptions,
) -> Result<ViewMatches, PipelineError> {
    if !(gate.is_finite() && gate > 0.0) {
        return Err(PipelineError::Unsupported(format!(
            "the matching gate must be positive, got {gate}"
        )));
    }
    let direction = |p: &Option<Point3<f64>>| -> Option<(f64, f64)> {
        let p = p.filter(|p| p.z > 0.0)?;
        let (x, y) = (p.x / p.z, p.y / p.z);
        (x.is_finite() && y.is_finite()).then_some((x, y))
    };
    let grid = DirectionGrid::new(
        b.points
            .iter()
            .enumerate()
            .filter_map(|(j, p)| direction(p).map(|(x, y)| (j, x, y)))
            .collect(),
        gate,
    );
    let candidates: Vec<Vec<usize>> = a
        .points
        .iter()
        .map(|p| match direction(&p.map(|p| b_from_a * p)) {
            Some((x, y)) => grid.within(x, y),
            None => Vec::new(),
        })
        .collect();
    let matches = match_features_among(&a.features, &b.features, &candidates, &options.features)?;
    Ok(ViewMatches::lifted(a, b, &matches))
}

/// Points of the normalised image plane in square cells at least `gate`
/// wide (a dense grid over the points' extent, widened where the extent would
/// need too many cells), so that the points within `gate` of any place lie in
/// its cell and the eight around it.
struct DirectionGrid {
    /// `(index, x, y)` ordered by cell.
    points: Vec<(usize, f64, f64)>,
    /// Where each cell's points start in `points` (one more entry than cells).
    starts: Vec<usize>,
    origin: (f64, f64),
    size: f64,
    dims: (usize, usize),
    /// How near a point must be to count.
    gate: f64,
}

impl DirectionGrid {
    fn new(points: Vec<(usize, f64, f64)>, gate: f64) -> Self {
        let (mut lo, mut hi) = (
            (f64::INFINITY, f64::INFINITY),
            (f64::NEG_INFINITY, f64::NEG_INFINITY),
        );
        for &(_, x, y) in &points {
            lo = (lo.0.min(x), lo.1.min(y));
            hi = (hi.0.max(x), hi.1.max(y));
        }
        if points.is_empty() {
            (lo, hi) = ((0.0, 0.0), (0.0, 0.0));
        }
        let most = (4 * points.len()).max(1 << 12);
        let mut size = gate;
        let dims = loop {
            let nx = ((hi.0 - lo.0) / size).floor() + 1.0;
            let ny = ((hi.1 - lo.1) / size).floor() + 1.0;
            if nx * ny <= most as f64 {
                break (nx as usize, ny as usize);
            }
            size *= 2.0;
        };
        let cell_of = |x: f64, y: f64| {
            let cx = (((x - lo.0) / size) as usize).min(dims.0 - 1);
            let cy = (((y - lo.1) / size) as usize).min(dims.1 - 1);
            cy * dims.0 + cx
        };
        let mut starts = vec![0usize; dims.0 * dims.1 + 1];
        for &(_, x, y) in &points {
            starts[cell_of(x, y) + 1] += 1;
        }
        for k in 1..starts.len() {
            starts[k] += starts[k - 1];
        }
        let mut fill = starts.clone();
        let mut ordered = vec![(0, 0.0, 0.0); points.len()];
        for p in points {
            let c = cell_of(p.1, p.2);
            ordered[fill[c]] = p;
            fill[c] += 1;
        }
        DirectionGrid {
            points: ordered,
            starts,
            origin: lo,
            size,
            dims,
            gate,
        }
    }

    /// The indices of the points within the gate of `(x, y)`.
    fn within(&self, x: f64, y: f64) -> Vec<usize> {
        // Cells as floats first: a place far outside the grid must not overflow.
        let (nx, ny) = (self.dims.0 as f64, self.dims.1 as f64);
        let cx = ((x - self.origin.0) / self.size).floor();
        let cy = ((y - self.origin.1) / self.size).floor();
        let (x0, x1) = ((cx - 1.0).max(0.0), (cx + 1.0).min(nx - 1.0));
        let (y0, y1) = ((cy - 1.0).max(0.0), (cy + 1.0).min(ny - 1.0));
        let mut near = Vec::with_capacity(32);
        if !(x0 <= x1 && y0 <= y1) {
            return near;
        }
        let (x0, x1) = (x0 as usize, x1 as usize);
        for gy in y0 as usize..=y1 as usize {
            let row = gy * self.dims.0;
            // The cells (x0..=x1, gy) are one run of the ordered points.
            for &(j, u, v) in &self.points[self.starts[row + x0]..self.starts[row + x1 + 1]] {
                if (u - x).powi(2) + (v - y).powi(2) <= self.gate * self.gate {
                    near.push(j);
                }
            }
        }
        near
    }
}

/// A robust `camera1_from_camera2` from matched 3-D points.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraPairFit {
    pub camera1_from_camera2: Iso3,
    pub inliers: usize,
    pub rms_m: f64,
    pub spread_m: f64,
    /// Inlier points in camera 1.
    pub inlier_points1: Vec<Point3<f64>>,
    /// The same inliers' points in camera 2.
    pub inlier_points2: Vec<Point3<f64>>,
}

/// RANSAC + Umeyama over matched 3-D points; fewer than `options.min_inliers`
/// inliers (or no consensus at all) is an error that says how many there were.
pub fn fit_camera_pair(
    points1: &[Point3<f64>],
    points2: &[Point3<f64>],
    options: &RgbdOptions,
) -> Result<CameraPairFit, PipelineError> {
    let need = options.min_inliers.max(3);
    if points1.len() < need {
        return Err(PipelineError::TooFewDepthMatches {
            matches: points1.len(),
            need,
        });
    }
    let ransac = RansacOptions {
        min_inliers: need,
        ..options.ransac
    };
    let fit = ransac_rigid(points1, points2, &ransac).map_err(|e| match e {
        CalibError::NoConsensus { best, total, need } => PipelineError::NoRansacConsensus {
            best,
            total,
            threshold_mm: options.ransac.threshold * 1e3,
            need,
        },
        other => PipelineError::Calib {
            robot: "camera pair".into(),
            source: other,
        },
    })?;
    let inliers_of = |points: &[Point3<f64>]| -> Vec<Point3<f64>> {
        points
            .iter()
            .zip(&fit.inliers)
            .filter(|(_, k)| **k)
            .map(|(p, _)| *p)
            .collect()
    };
    let inlier_points1 = inliers_of(points1);
    let inlier_points2 = inliers_of(points2);
    let inliers = inlier_points1.len();
    if inliers < need {
        return Err(PipelineError::TooFewRansacInliers { inliers, need });
    }
    let c: Vector3<f64> = inlier_points1
        .iter()
        .map(|p| p.coords)
        .sum::<Vector3<f64>>()
        / inliers as f64;
    let spread_m = (inlier_points1
        .iter()
        .map(|p| (p.coords - c).norm_squared())
        .sum::<f64>()
        / inliers as f64)
        .sqrt();
    Ok(CameraPairFit {
        camera1_from_camera2: fit.a_from_b,
        inliers,
        rms_m: fit.rms,
        spread_m,
        inlier_points1,
        inlier_points2,
    })
}

/// The robust combination of per-pair `base1_from_base2` estimates.
#[derive(Debug, Clone, PartialEq)]
pub struct Combined {
    pub base1_from_base2: Iso3,
    /// Left-perturbation covariance `[ω, v]`.
    pub covariance: Matrix6<f64>,
    /// Per input: accepted, or the reason it was rejected.
    pub verdicts: Vec<Result<(), String>>,
}

/// Combines per-pair estimates `(base1_from_base2, inliers, rms_m, spread_m)`: MAD
/// screening against the median, then the inlier-weighted average (see the module
/// docs for the rule and thresholds). Every estimate is taken as coming from its own
/// two views (independent pairs); see [`combine_pairs_by_view`] for pairs that share
/// views.
pub fn combine_pairs(
    estimates: &[(Iso3, usize, f64, f64)],
    options: &RgbdOptions,
) -> Result<Combined, PipelineError> {
    let views: Vec<[usize; 2]> = (0..estimates.len()).map(|k| [k, k]).collect();
    combine_pairs_by_view(estimates, &views, options)
}

/// [`combine_pairs`] for pairs that share views: `views[k]` names the two views
/// (robot 1's, robot 2's) estimate `k` was made from. The covariance of the mean is
/// clustered by view (see the module docs).
pub fn combine_pairs_by_view(
    estimates: &[(Iso3, usize, f64, f64)],
    views: &[[usize; 2]],
    options: &RgbdOptions,
) -> Result<Combined, PipelineError> {
    let n = estimates.len();
    if views.len() != n {
        return Err(PipelineError::PairLabelsMismatch {
            estimates: n,
            labels: views.len(),
        });
    }
    if n == 0 {
        return Err(PipelineError::NoPairEstimate);
    }
    let t: Vec<Vector3<f64>> = estimates.iter().map(|e| e.0.translation.vector).collect();
    let t_med = Vector3::from_fn(|i, _| median(&mut t.iter().map(|v| v[i]).collect::<Vec<_>>()));
    // The rotation medoid: least summed angle to the others.
    let medoid = (0..n)
        .min_by(|&a, &b| {
            let s = |i: usize| -> f64 {
                estimates
                    .iter()
                    .map(|e| geodesic_angle(&estimates[i].0.rotation, &e.0.rotation))
                    .sum()
            };
            s(a).total_cmp(&s(b))
        })
        .unwrap_or(0);
    let r_ref = estimates[medoid].0.rotation;
    let dt: Vec<f64> = t.iter().map(|v| (v - t_med).norm()).collect();
    let dr: Vec<f64> = estimates
        .iter()
        .map(|e| geodesic_angle(&e.0.rotation, &r_ref))
        .collect();
    let gate_t =
        (options.mad_k * 1.4826 * median(&mut dt.clone())).max(options.translation_floor_m);
    let gate_r = (options.mad_k * 1.4826 * median(&mut dr.clone())).max(options.rotation_floor_rad);
    let verdicts: Vec<Result<(), String>> = (0..n)
        .map(|i| {
            if dt[i] > gate_t {
                Err(format!(
                    "translation {:.1} mm from the median, gate {:.1} mm",
                    dt[i] * 1e3,
                    gate_t * 1e3
                ))
            } else if dr[i] > gate_r {
                Err(format!(
                    "rotation {:.2}° from the medoid, gate {:.2}°",
                    dr[i].to_degrees(),
                    gate_r.to_degrees()
                ))
            } else {
                Ok(())
            }
        })
        .collect();
    let kept: Vec<usize> = (0..n).filter(|i| verdicts[*i].is_ok()).collect();
    if kept.is_empty() {
        return Err(PipelineError::AllPairsOutliers);
    }
    let w: Vec<f64> = kept.iter().map(|&i| estimates[i].1 as f64).collect();
    let wsum: f64 = w.iter().sum();
    let rots: Vec<_> = kept.iter().map(|&i| estimates[i].0.rotation).collect();
    let r = average_rotations(&rots, Some(&w)).map_err(|source| PipelineError::Calib {
        robot: "rgbd pairs".into(),
        source,
    })?;
    let t_mean: Vector3<f64> = kept
        .iter()
        .zip(&w)
        .map(|(&i, wi)| estimates[i].0.translation.vector * *wi)
        .sum::<Vector3<f64>>()
        / wsum;
    let mean = Iso3::from_parts(Translation3::from(t_mean), r);
    let k = kept.len() as f64;
    let mut floor = Matrix6::zeros();
    // Weighted residual sums per view of each robot, and per pair.
    let mut by_view: [std::collections::BTreeMap<usize, nalgebra::Vector6<f64>>; 2] =
        Default::default();
    let mut pair_level = Matrix6::zeros();
    for (&i, wi) in kept.iter().zip(&w) {
        let d = left_difference(&estimates[i].0, &mean);
        let wd = d * *wi;
        pair_level += wd * wd.transpose();
        for (side, map) in by_view.iter_mut().enumerate() {
            *map.entry(views[i][side])
                .or_insert_with(nalgebra::Vector6::zeros) += wd;
        }
        // A single pair's own precision: σ_t = rms/√inliers, σ_ω = σ_t / spread.
        let (_, inl, rms, sp) = estimates[i];
        let st2 = rms * rms / inl.max(1) as f64;
        let sr2 = st2 / (sp * sp).max(1e-6);
        let mut f = Matrix6::zeros();
        for a in 0..3 {
            f[(a, a)] = sr2;
            f[(a + 3, a + 3)] = st2;
        }
        floor += f * *wi;
    }
    // The covariance of the mean, clustered by view: pairs that share a view share
    // its error (its flange pose, its depth), so they are not independent. Two-way
    // cluster-robust (Cameron, Gelbach & Miller 2011): V = V₁ + V₂ − V₁₂, with Vₛ the
    // sum over robot s's views of the outer products of their summed weighted
    // residuals (× G/(G−1) for G views), V₁₂ the same per pair; negative eigenvalues
    // (a rare small-sample artefact) are clamped, and never below the pairs' own
    // residual precision. With every pair on its own views this is the spread of the
    // pairs divided by their number.
    let cluster = |map: &std::collections::BTreeMap<usize, nalgebra::Vector6<f64>>| {
        let g = map.len() as f64;
        let sum: Matrix6<f64> = map.values().map(|s| s * s.transpose()).sum();
        if g > 1.0 { sum * (g / (g - 1.0)) } else { sum }
    };
    let kf = if k > 1.0 { k / (k - 1.0) } else { 1.0 };
    let v = (cluster(&by_view[0]) + cluster(&by_view[1]) - pair_level * kf) / (wsum * wsum);
    let v = (v + v.transpose()) * 0.5;
    let eig = v.symmetric_eigen();
    let clamped = eig.eigenvalues.map(|l| l.max(0.0));
    let v = eig.eigenvectors * Matrix6::from_diagonal(&clamped) * eig.eigenvectors.transpose();
    let covariance = v + floor / wsum / k;
    Ok(Combined {
        base1_from_base2: mean,
        covariance,
        verdicts,
    })
}

/// One dataset capture as a view: its colour image's features lifted with its depth
/// image (what `load_views` does per row and a replaying agent per capture).
pub fn capture_view(
    ds: &Dataset,
    robot: &str,
    camera: &CameraModel,
    unit_m: f64,
    cap: &b2b_dataset::Capture,
    options: &RgbdOptions,
) -> Result<RgbdView, PipelineError> {
    let (Some(ip), Some(dp)) = (ds.image_path(robot, cap), ds.depth_path(robot, cap)) else {
        return Err(PipelineError::NoDepthImage);
    };
    let gray = b2b_vision::load_gray_sized(&ip, camera.width, camera.height)?;
    b2b_vision::check_image_file(&dp, camera.width, camera.height)?;
    let depth = load_depth(&dp)?;
    let (features, points) =
        detect_and_lift(camera, &gray, &depth, unit_m, options).map_err(|e| match e {
            PipelineError::DepthNotAligned {
                depth_file: None,
                depth_width,
                depth_height,
                colour_width,
                colour_height,
            } => PipelineError::DepthNotAligned {
                depth_file: Some(dp.clone()),
                depth_width,
                depth_height,
                colour_width,
                colour_height,
            },
            other => other,
        })?;
    Ok(RgbdView {
        row: cap.row,
        image: cap
            .image
            .as_ref()
            .map(|p| p.display().to_string())
            .unwrap_or_default(),
        base_from_flange: cap.base_from_flange,
        features,
        points,
    })
}

/// Loads one robot's colour features and depth, capture by capture; captures without
/// depth or with unreadable files become rejected captures.
pub fn load_views(
    ds: &Dataset,
    robot: &str,
    options: &RgbdOptions,
) -> Result<RobotViews, PipelineError> {
    let data = ds
        .robot(robot)
        .ok_or_else(|| crate::unknown_robot(ds, robot))?;
    let unit = ds
        .robot_manifest(robot)
        .and_then(|m| m.depth_unit_m)
        .ok_or_else(|| PipelineError::NoDepthUnit {
            robot: robot.to_owned(),
            manifest: ds.root.join("dataset.json"),
        })?;
    let camera = RobotSetup::from_dataset(ds, robot)?.camera;
    crate::check_image_sizes(ds, robot, &camera)?;
    let mut views = Vec::new();
    let mut rejected = Vec::new();
    for cap in &data.captures {
        let image = cap.image.as_ref().map(|p| p.display().to_string());
        let reject = |reason: String| RejectedCapture {
            robot: robot.to_owned(),
            image: image.clone(),
            row: Some(cap.row),
            reason,
        };
        let loaded = capture_view(ds, robot, &camera, unit, cap, options);
        match loaded {
            Ok(view) => views.push(view),
            Err(e) => rejected.push(reject(crate::error_chain(&e))),
        }
    }
    check_depth_range(ds, robot, unit, &views, options)?;
    Ok(RobotViews {
        views,
        rejected,
        camera,
    })
}

/// A robot's views lift fewer than this fraction of their keypoints ...
pub const RANGE_MIN_LIFTED: f64 = 0.05;

/// ... and the median of its depth images' valid samples, in metres by the
/// dataset's unit, lies outside the working range: the unit is wrong (a depth
/// unit slip), refused with the depth the images give (and what it would be
/// in millimetres, the RealSense default). Reads the depth images again only
/// then.
fn check_depth_range(
    ds: &Dataset,
    robot: &str,
    unit_m: f64,
    views: &[RgbdView],
    options: &RgbdOptions,
) -> Result<(), PipelineError> {
    let keypoints: usize = views.iter().map(|v| v.points.len()).sum();
    let lifted: usize = views
        .iter()
        .map(|v| v.points.iter().filter(|p| p.is_some()).count())
        .sum();
    if keypoints == 0 || lifted as f64 >= RANGE_MIN_LIFTED * keypoints as f64 {
        return Ok(());
    }
    let Some(data) = ds.robot(robot) else {
        return Ok(());
    };
    let mut samples: Vec<f64> = Vec::new();
    let mut files = 0usize;
    for cap in &data.captures {
        let Some(path) = ds.depth_path(robot, cap) else {
            continue;
        };
        let Ok(depth) = load_depth(&path) else {
            continue;
        };
        files += 1;
        // Every 7th sample is plenty for a median.
        samples.extend(
            depth
                .data
                .iter()
                .step_by(7)
                .filter(|d| **d != 0)
                .map(|d| f64::from(*d) * unit_m),
        );
    }
    if samples.is_empty() {
        return Ok(());
    }
    let median_m = median(&mut samples);
    if median_m >= options.min_depth_m && median_m <= options.max_depth_m {
        return Ok(());
    }
    Err(PipelineError::DepthOutOfRange {
        robot: robot.to_owned(),
        manifest: ds.root.join("dataset.json"),
        unit_m,
        median_m,
        files,
        lifted,
        keypoints,
        min_m: options.min_depth_m,
        max_m: options.max_depth_m,
    })
}

/// The folder of `robot`'s first depth image in the dataset.
fn depth_folder(ds: &Dataset, robot: &str) -> Option<std::path::PathBuf> {
    let data = ds.robot(robot)?;
    data.captures
        .iter()
        .find_map(|cap| ds.depth_path(robot, cap))
        .and_then(|p| p.parent().map(std::path::Path::to_path_buf))
}

/// One robot's views ([`load_views`]), the captures that gave none, and the
/// camera model they were lifted with.
#[derive(Debug)]
pub struct RobotViews {
    pub views: Vec<RgbdView>,
    pub rejected: Vec<RejectedCapture>,
    pub camera: CameraModel,
}

/// The RGB-D method with given hand-eyes (`flange_from_camera` of robot 1 and 2)
/// and, when known, their covariances (left perturbations `[ω, v]` in the flange, as
/// [`b2b_calib::refine::HandEyeEstimate::flange_from_camera_covariance`]). The
/// hand-eye covariances are propagated into the result's covariance unreduced by the
/// number of pairs (every pair shares the same hand-eye error).
pub fn rgbd_base_to_base_with_hand_eyes(
    ds: &Dataset,
    flange_from_camera: [Iso3; 2],
    hand_eye_covariance: Option<[Matrix6<f64>; 2]>,
    options: &RgbdOptions,
) -> Result<RgbdRun, PipelineError> {
    let start = Instant::now();
    if ds.manifest.robots.len() != 2 {
        return Err(crate::rgbd_not_two_robots(ds));
    }
    let ids: Vec<String> = ds.manifest.robots.iter().map(|r| r.id.clone()).collect();
    let r1 = load_views(ds, &ids[0], options)?;
    let r2 = load_views(ds, &ids[1], options)?;
    let mut rejected = r1.rejected;
    rejected.extend(r2.rejected);
    let detect_ms = start.elapsed().as_secs_f64() * 1e3;
    let mut run = rgbd_from_views(
        [&ids[0], &ids[1]],
        [&r1.views, &r2.views],
        [&r1.camera, &r2.camera],
        rejected,
        flange_from_camera,
        hand_eye_covariance,
        options,
    )
    .map_err(|e| match e {
        PipelineError::DepthNotOfColour {
            robot,
            depth_folder: None,
            evidence,
        } => PipelineError::DepthNotOfColour {
            depth_folder: depth_folder(ds, &robot),
            robot,
            evidence,
        },
        PipelineError::DepthScale {
            robot,
            scale,
            scale_sigma,
            evidence,
            unit: None,
        } => PipelineError::DepthScale {
            unit: ds
                .robot_manifest(&robot)
                .and_then(|m| m.depth_unit_m)
                .map(|u| (ds.root.join("dataset.json"), u)),
            robot,
            scale,
            scale_sigma,
            evidence,
        },
        other => other,
    })?;
    run.result.timings_ms.detect = detect_ms;
    run.result.timings_ms.total = start.elapsed().as_secs_f64() * 1e3;
    Ok(run)
}

/// The RGB-D method on views already made (a dataset's, or what the agents
/// published): every pair of robot 1's and robot 2's views, then the robust
/// combination. `rejected` are captures the caller already could not use; they are
/// reported with the ones no accepted pair used. `cameras` are the views' camera
/// models, for each view's reprojection RMS under the result
/// ([`CaptureSummary::per_capture`], see [`view_fits`]).
///
/// First each robot's depth is checked against its colour images and its
/// motion ([`crate::depth_checks`]): depth of another camera is refused
/// ([`PipelineError::DepthNotOfColour`]), depth at another scale too
/// ([`PipelineError::DepthScale`]); the checks are kept in
/// [`RgbdRun::depth_checks`].
pub fn rgbd_from_views(
    ids: [&str; 2],
    views: [&[RgbdView]; 2],
    cameras: [&CameraModel; 2],
    rejected: Vec<RejectedCapture>,
    flange_from_camera: [Iso3; 2],
    hand_eye_covariance: Option<[Matrix6<f64>; 2]>,
    options: &RgbdOptions,
) -> Result<RgbdRun, PipelineError> {
    let [v1, v2] = views;
    let start = Instant::now();
    let solve_start = start;
    // Each robot's depth against its colour images and its motion: depth of
    // another camera is refused, depth at another scale named.
    let mut depth_checks = Vec::with_capacity(2);
    for (k, v) in [v1, v2].into_iter().enumerate() {
        let check = check_robot_depth(
            ids[k],
            v,
            &flange_from_camera[k],
            hand_eye_covariance.as_ref().map(|c| &c[k]),
            options,
        )?;
        tracing::debug!(robot = ids[k], scale = ?check.scale, "rgbd depth self-check");
        if check.mismatch() {
            return Err(PipelineError::DepthNotOfColour {
                robot: ids[k].to_owned(),
                depth_folder: None,
                evidence: check.describe_mismatch(),
            });
        }
        if let Some(s) = check.scale.filter(crate::causes::is_depth_scaled) {
            return Err(PipelineError::DepthScale {
                robot: ids[k].to_owned(),
                scale: s.scale,
                scale_sigma: s.scale_sigma,
                evidence: s.describe(),
                unit: None,
            });
        }
        depth_checks.push(check);
    }
    let mut pairs = Vec::new();
    let mut estimates = Vec::new();
    let mut pair_views = Vec::new();
    let mut inlier_centres = Vec::new();
    let mut flanges = Vec::new();
    let mut inlier_points = Vec::new();
    for (ia, a) in v1.iter().enumerate() {
        for (ib, b) in v2.iter().enumerate() {
            let mut pe = PairEstimate {
                rows: [a.row, b.row],
                matches: 0,
                lifted: 0,
                inliers: 0,
                rms_m: 0.0,
                spread_m: 0.0,
                camera1_from_camera2: None,
                base1_from_base2: None,
                accepted: false,
                reason: None,
            };
            let bad = [
                depth_checks[0].mismatched_view(a.row),
                depth_checks[1].mismatched_view(b.row),
            ];
            if let Some((k, why)) = bad
                .iter()
                .enumerate()
                .find_map(|(k, w)| w.as_ref().map(|w| (k, w)))
            {
                pe.reason = Some(format!(
                    "{} row {}: {why}",
                    ids[k],
                    if k == 0 { a.row } else { b.row }
                ));
                pairs.push(pe);
                continue;
            }
            let ViewMatches {
                matches,
                points1: p1,
                points2: p2,
            } = match_views(a, b, options)?;
            pe.matches = matches;
            pe.lifted = p1.len();
            match fit_camera_pair(&p1, &p2, options) {
                Ok(fit) => {
                    let base1_from_camera1 = a.base_from_flange * flange_from_camera[0];
                    let base2_from_camera2 = b.base_from_flange * flange_from_camera[1];
                    let b1b2 = base1_from_camera1
                        * fit.camera1_from_camera2
                        * base2_from_camera2.inverse();
                    pe.inliers = fit.inliers;
                    pe.rms_m = fit.rms_m;
                    pe.spread_m = fit.spread_m;
                    pe.camera1_from_camera2 = Some(fit.camera1_from_camera2);
                    pe.base1_from_base2 = Some(b1b2);
                    let c: Vector3<f64> = fit
                        .inlier_points1
                        .iter()
                        .map(|p| (base1_from_camera1 * p).coords)
                        .sum::<Vector3<f64>>()
                        / fit.inliers as f64;
                    estimates.push((b1b2, fit.inliers, fit.rms_m, fit.spread_m));
                    pair_views.push([a.row, b.row]);
                    inlier_centres.push((pairs.len(), c));
                    flanges.push((a.base_from_flange, b.base_from_flange));
                    inlier_points.push(PairInliers {
                        views: [ia, ib],
                        points1: fit.inlier_points1,
                        points2: fit.inlier_points2,
                        outliers: pe.lifted - fit.inliers,
                    });
                }
                Err(e) => pe.reason = Some(crate::error_chain(&e)),
            }
            tracing::debug!(
                rows = ?pe.rows,
                matches = pe.matches,
                lifted = pe.lifted,
                inliers = pe.inliers,
                "rgbd pair"
            );
            pairs.push(pe);
        }
    }
    if estimates.is_empty() {
        let reasons: Vec<String> = pairs
            .iter()
            .map(|p| {
                format!(
                    "rows {}/{}: {}",
                    p.rows[0],
                    p.rows[1],
                    p.reason.as_deref().unwrap_or("?")
                )
            })
            .collect();
        return Err(PipelineError::NoPairWithInliers {
            min_inliers: options.min_inliers,
            pairs: pairs.len(),
            robot1: ids[0].to_owned(),
            views1: v1.len(),
            robot2: ids[1].to_owned(),
            views2: v2.len(),
            reasons,
        });
    }
    let mut combined = combine_pairs_by_view(&estimates, &pair_views, options)?;
    if let Some([c1, c2]) = hand_eye_covariance {
        // base1_from_base2 = A·X1·C·(B·X2)⁻¹: a left perturbation δ1 of X1 moves it by
        // adjoint(A)·δ1, one of X2 by -adjoint(base1_from_base2·B)·δ2 (first order);
        // the weighted mean of the pairs moves by the weighted mean of those maps.
        let mut j1 = Matrix6::zeros();
        let mut j2 = Matrix6::zeros();
        let mut wsum = 0.0;
        for ((est, (a, b)), verdict) in estimates.iter().zip(&flanges).zip(&combined.verdicts) {
            if verdict.is_ok() {
                let w = est.1 as f64;
                j1 += adjoint(a) * w;
                j2 -= adjoint(&(combined.base1_from_base2 * b)) * w;
                wsum += w;
            }
        }
        let (j1, j2) = (j1 / wsum, j2 / wsum);
        combined.covariance += j1 * c1 * j1.transpose() + j2 * c2 * j2.transpose();
    }
    // A robot's depth scale off 1 beyond its noise, short of a refusal: the
    // covariance holds the whole measured deviation, propagated through the
    // accepted pairs.
    let mut findings = Vec::new();
    for (k, check) in depth_checks.iter().enumerate() {
        let Some(s) = check.scale else { continue };
        let off2 = (s.scale - 1.0).powi(2);
        if off2 <= (DEPTH_SCALE_NOISE_SIGMAS * s.scale_sigma).powi(2) {
            continue;
        }
        let Some(j) = depth_scale_jacobian(
            k,
            &inlier_points,
            &estimates,
            &combined.verdicts,
            views,
            &flange_from_camera,
        ) else {
            continue;
        };
        let before = translation_sigma_mm(&combined.covariance);
        combined.covariance += j * j.transpose() * off2;
        findings.push(crate::causes::depth_scale_held(
            ids[k],
            &s,
            off2.sqrt(),
            before,
            translation_sigma_mm(&combined.covariance),
        ));
    }
    let mut centre = Vector3::zeros();
    let mut n_centre = 0.0f64;
    for ((idx, c), verdict) in inlier_centres.iter().zip(&combined.verdicts) {
        match verdict {
            Ok(()) => {
                pairs[*idx].accepted = true;
                centre += c;
                n_centre += 1.0;
            }
            Err(reason) => pairs[*idx].reason = Some(format!("outlier pair: {reason}")),
        }
    }
    let centre = Point3::from(centre / n_centre.max(1.0));
    let (mean, p95) = predicted_error(&combined.covariance, &workspace_points(&centre), 0.0);
    let used_rows = |k: usize| -> std::collections::BTreeSet<usize> {
        pairs
            .iter()
            .filter(|p| p.accepted)
            .map(|p| p.rows[k])
            .collect()
    };
    let (used1, used2) = (used_rows(0), used_rows(1));
    let accepted_inliers: Vec<&PairInliers> = inlier_points
        .iter()
        .zip(&combined.verdicts)
        .filter(|(_, v)| v.is_ok())
        .map(|(p, _)| p)
        .collect();
    let per_capture = view_fits(
        ids,
        views,
        cameras,
        flange_from_camera,
        &combined.base1_from_base2,
        &centre,
        &accepted_inliers,
    );
    let mut rejected = rejected;
    for (k, (views, used)) in [(v1, &used1), (v2, &used2)].into_iter().enumerate() {
        for v in views.iter().filter(|v| !used.contains(&v.row)) {
            rejected.push(RejectedCapture {
                robot: ids[k].to_owned(),
                image: Some(v.image.clone()),
                row: Some(v.row),
                reason: depth_checks[k].mismatched_view(v.row).unwrap_or_else(|| "no accepted image pair (too few inliers with every image of the other robot, or outlier pairs)".into()),
            });
        }
    }
    let solve_ms = solve_start.elapsed().as_secs_f64() * 1e3;
    let mut cov = [[0.0; 6]; 6];
    let sym = (combined.covariance + combined.covariance.transpose()) * 0.5;
    for (i, row) in cov.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = sym[(i, j)];
        }
    }
    let result = CalibrationResult {
        format: RESULT_FORMAT.to_owned(),
        method: "rgbd".to_owned(),
        base1_from_base2: Pose::from_isometry(&combined.base1_from_base2),
        covariance: cov,
        predicted_touch_error_m: PredictedError { mean, p95 },
        hand_eye: [
            (
                ids[0].to_owned(),
                Pose::from_isometry(&flange_from_camera[0]),
            ),
            (
                ids[1].to_owned(),
                Pose::from_isometry(&flange_from_camera[1]),
            ),
        ]
        .into_iter()
        .collect(),
        captures: CaptureSummary {
            used: [
                (ids[0].to_owned(), used1.len()),
                (ids[1].to_owned(), used2.len()),
            ]
            .into_iter()
            .collect(),
            rejected,
            per_capture,
        },
        timings_ms: Timings {
            detect: 0.0,
            solve: solve_ms,
            total: start.elapsed().as_secs_f64() * 1e3,
        },
        reference: Some(ids[0].to_owned()),
        bases: Default::default(),
        pairs: Vec::new(),
        hand_eye_covariance: Default::default(),
        warnings: Vec::new(),
        findings,
        verdict: None,
        model_selection: None,
    };
    Ok(RgbdRun {
        result,
        pairs,
        scene_centre_in_base1: centre,
        depth_checks,
    })
}

/// A depth scale off 1 by more than this many of its standard errors widens
/// the result's covariance by the deviation (`(s − 1)²` as a variance of the
/// scale: the measured deviation is the best estimate of the error; holding
/// only its excess over `k σ` left a 0.5% scale error at m² 42): within it, the
/// depth is taken at its scale.
pub const DEPTH_SCALE_NOISE_SIGMAS: f64 = 2.0;

/// The RMS of the translation's standard deviations (mm).
fn translation_sigma_mm(covariance: &Matrix6<f64>) -> f64 {
    ((covariance[(3, 3)] + covariance[(4, 4)] + covariance[(5, 5)]) / 3.0)
        .max(0.0)
        .sqrt()
        * 1e3
}

/// How the result moves per unit of robot `k`'s depth scale (left
/// perturbation `[ω, v]` of `base1_from_base2`): each accepted pair's inliers
/// refitted (Umeyama) with robot `k`'s points scaled by 1%, the pairs' changes
/// averaged with the combination's weights. `None` without an accepted pair.
fn depth_scale_jacobian(
    k: usize,
    inliers: &[PairInliers],
    estimates: &[(Iso3, usize, f64, f64)],
    verdicts: &[Result<(), String>],
    views: [&[RgbdView]; 2],
    flange_from_camera: &[Iso3; 2],
) -> Option<nalgebra::Vector6<f64>> {
    const STEP: f64 = 0.01;
    let mut sum = nalgebra::Vector6::zeros();
    let mut wsum = 0.0;
    for ((p, est), verdict) in inliers.iter().zip(estimates).zip(verdicts) {
        if verdict.is_err() {
            continue;
        }
        let scaled: Vec<Point3<f64>> = if k == 0 { &p.points1 } else { &p.points2 }
            .iter()
            .map(|q| Point3::from(q.coords * (1.0 + STEP)))
            .collect();
        let (a, b) = if k == 0 {
            (&scaled, &p.points2)
        } else {
            (&p.points1, &scaled)
        };
        let (Ok(c0), Ok(c1)) = (
            b2b_calib::procrustes::fit_rigid(&p.points1, &p.points2),
            b2b_calib::procrustes::fit_rigid(a, b),
        ) else {
            continue;
        };
        let base1_from_camera1 = views[0][p.views[0]].base_from_flange * flange_from_camera[0];
        let camera2_from_base2 =
            (views[1][p.views[1]].base_from_flange * flange_from_camera[1]).inverse();
        let d = left_difference(
            &(base1_from_camera1 * c1 * camera2_from_base2),
            &(base1_from_camera1 * c0 * camera2_from_base2),
        );
        let w = est.1 as f64;
        sum += d * w;
        wsum += w;
    }
    (wsum > 0.0).then(|| sum / (wsum * STEP))
}

/// One fitted pair's inlier matches: which views (indices into robot 1's and robot
/// 2's views), their 3-D points in either camera, and the lifted matches RANSAC
/// left out.
struct PairInliers {
    views: [usize; 2],
    points1: Vec<Point3<f64>>,
    points2: Vec<Point3<f64>>,
    outliers: usize,
}

/// Each view's fit under the result, as `RESULT.json`'s `per_capture` carries it
/// for the board methods:
/// - `rms_px`: over the accepted pairs the view is in, each inlier's point seen by
///   the other camera, carried into this camera through the result
///   (`camera_from_other = (base_from_flange · flange_from_camera)⁻¹ ·
///   base1_from_base2 (or its inverse) · other_base_from_flange ·
///   other_flange_from_camera`) and projected, against the projection of its own
///   point (its feature, undistorted and lifted). `None` when no accepted pair
///   used the view;
/// - `outlier_corners`: the lifted matches RANSAC rejected in those pairs;
/// - `view_direction`: from the scene centre (the accepted inliers' mean) to the
///   camera, in base 1's axes (robot 2's cameras carried there by the result),
///   the RGB-D method's stand-in for the target frame.
fn view_fits(
    ids: [&str; 2],
    views: [&[RgbdView]; 2],
    cameras: [&CameraModel; 2],
    flange_from_camera: [Iso3; 2],
    base1_from_base2: &Iso3,
    centre_in_base1: &Point3<f64>,
    pairs: &[&PairInliers],
) -> Vec<b2b_protocol::CaptureFit> {
    // Each camera in base 1.
    let in_base1 = |k: usize, v: &RgbdView| -> Iso3 {
        let base_from_camera = v.base_from_flange * flange_from_camera[k];
        if k == 0 {
            base_from_camera
        } else {
            base1_from_base2 * base_from_camera
        }
    };
    let mut sums: [Vec<(f64, usize, usize)>; 2] = [
        vec![(0.0, 0, 0); views[0].len()],
        vec![(0.0, 0, 0); views[1].len()],
    ];
    for p in pairs {
        let [a, b] = p.views;
        let camera1_from_camera2 = in_base1(0, &views[0][a]).inverse() * in_base1(1, &views[1][b]);
        let camera2_from_camera1 = camera1_from_camera2.inverse();
        for (p1, p2) in p.points1.iter().zip(&p.points2) {
            let through = [
                (
                    0,
                    a,
                    cameras[0].project(p1),
                    cameras[0].project(&(camera1_from_camera2 * p2)),
                ),
                (
                    1,
                    b,
                    cameras[1].project(p2),
                    cameras[1].project(&(camera2_from_camera1 * p1)),
                ),
            ];
            for (k, i, seen, predicted) in through {
                if let (Some(s), Some(q)) = (seen, predicted) {
                    sums[k][i].0 += (s - q).norm_squared();
                    sums[k][i].1 += 1;
                }
            }
        }
        sums[0][a].2 += p.outliers;
        sums[1][b].2 += p.outliers;
    }
    let mut fits = Vec::with_capacity(views[0].len() + views[1].len());
    for k in 0..2 {
        for (v, (sq, n, outliers)) in views[k].iter().zip(&sums[k]) {
            let d = (in_base1(k, v).translation.vector - centre_in_base1.coords)
                .try_normalize(1e-12)
                .unwrap_or_else(Vector3::z);
            fits.push(b2b_protocol::CaptureFit {
                robot: ids[k].to_owned(),
                row: v.row,
                image: (!v.image.is_empty()).then(|| v.image.clone()),
                rms_px: (*n > 0).then(|| (sq / *n as f64).sqrt()),
                outlier_corners: *outliers,
                view_direction: [d.x, d.y, d.z],
            });
        }
    }
    fits
}

/// Each robot's hand-eye for the RGB-D method (offline and live alike): the
/// pipeline's refined hand-eye from its target observations
/// ([`crate::hand_eye`]), with the covariance the features see. Features reach the
/// base through `base_from_flange * flange_from_camera`, so an error of the flange
/// pose common to the views (the arm's systematic error, `refine.systematic`,
/// about the flange) acts exactly like an error of the hand-eye: it is added to
/// the hand-eye covariance, once, whatever the number of views. Without it, a
/// live run (8 views an arm) put the truth at Mahalanobis² 25-34 on 6 dof.
pub fn rgbd_hand_eyes(
    observations: [&crate::RobotObservations; 2],
    refine: &RefineOptions,
) -> Result<[(Iso3, Matrix6<f64>); 2], PipelineError> {
    let common = refine.systematic.covariance();
    let one = |obs: &crate::RobotObservations| -> Result<(Iso3, Matrix6<f64>), PipelineError> {
        let he = hand_eye(obs, HandEyeChoice::Refined, refine)?;
        Ok((
            he.estimate.flange_from_camera,
            he.estimate.flange_from_camera_covariance + common,
        ))
    };
    Ok([one(observations[0])?, one(observations[1])?])
}

/// The RGB-D method on a dataset, with each robot's hand-eye from the dataset's
/// target (the pipeline's refined hand-eye, [`crate::hand_eye`]).
pub fn rgbd_base_to_base(
    ds: &Dataset,
    refine: &RefineOptions,
    options: &RgbdOptions,
) -> Result<RgbdRun, PipelineError> {
    let start = Instant::now();
    if ds.manifest.robots.len() != 2 {
        return Err(crate::rgbd_not_two_robots(ds));
    }
    let ids: Vec<String> = ds.manifest.robots.iter().map(|r| r.id.clone()).collect();
    let obs1 = observe_robot(ds, &ids[0])?;
    let obs2 = observe_robot(ds, &ids[1])?;
    let [he1, he2] = rgbd_hand_eyes([&obs1, &obs2], refine)?;
    let hand_eye_ms = start.elapsed().as_secs_f64() * 1e3;
    let mut run =
        rgbd_base_to_base_with_hand_eyes(ds, [he1.0, he2.0], Some([he1.1, he2.1]), options)?;
    run.result.timings_ms.detect += hand_eye_ms;
    run.result.timings_ms.total = start.elapsed().as_secs_f64() * 1e3;
    Ok(run)
}

#[cfg(test)]
mod tests {
    use super::DirectionGrid;
    use proptest::prelude::*;

    proptest! {
        /// The grid finds exactly the points within the gate, wherever the
        /// points and the place are (points far out widen its cells).
        #[test]
        fn the_direction_grid_finds_exactly_the_points_within_the_gate(
            points in proptest::collection::vec((-1.0f64..1.0, -1.0f64..1.0), 0..300),
            far in proptest::collection::vec((-1e6f64..1e6, -1e6f64..1e6), 0..3),
            place in (-1.2f64..1.2, -1.2f64..1.2),
            gate in 0.001f64..0.2,
        ) {
            let all: Vec<(usize, f64, f64)> = points
                .iter()
                .chain(&far)
                .enumerate()
                .map(|(j, (x, y))| (j, *x, *y))
                .collect();
            let grid = DirectionGrid::new(all.clone(), gate);
            let mut found = grid.within(place.0, place.1);
            found.sort_unstable();
            let expected: Vec<usize> = all
                .iter()
                .filter(|(_, x, y)| (x - place.0).powi(2) + (y - place.1).powi(2) <= gate * gate)
                .map(|(j, _, _)| *j)
                .collect();
            prop_assert_eq!(found, expected);
        }
    }
}
