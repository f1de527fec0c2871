//! The board's pose from its corners: OpenCV's IPPE, refined by Levenberg–Marquardt.
//!
//! IPPE (Collins & Bartoli) is the planar PnP solver: closed form, and it returns the
//! better of the two planar solutions. `solvePnPRefineLM` then minimises the
//! reprojection error with the distortion model. Residuals are recomputed with
//! [`CameraModel::project`], not OpenCV's `projectPoints`, so the reported RMS also
//! checks that OpenCV and the math core agree on the camera model.

use b2b_calib::camera::CameraModel;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::calib3d;
use opencv::core::{Mat, Point2d, Point3d, TermCriteria, Vector};
use opencv::prelude::*;

use crate::checkerboard::BoardDetection;
use crate::error::{CvContext, VisionError};

/// The pose of a target seen by a camera, with its fit quality.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseEstimate {
    /// `T_camera_target`: maps target-frame points into the camera frame.
    pub camera_from_target: Isometry3<f64>,
    /// Reprojection error of each corner, in pixels, in the detection's order.
    pub residuals_px: Vec<f64>,
    /// Root mean square of `residuals_px`.
    pub rms_px: f64,
}

/// Estimates `camera_from_target` for a planar board detection.
pub fn board_pose(det: &BoardDetection, camera: &CameraModel) -> Result<PoseEstimate, VisionError> {
    let n = det.pixels.len();
    if det.target_points.len() != n || det.corner_ids.len() != n {
        return Err(VisionError::Pose(format!(
            "detection has {} target points, {} ids and {n} pixels",
            det.target_points.len(),
            det.corner_ids.len()
        )));
    }
    if n < 4 {
        return Err(VisionError::TooFewCorners {
            found: n,
            needed: 4,
        });
    }
    if det
        .target_points
        .iter()
        .any(|p| p.z != 0.0 || !p.coords.iter().all(|v| v.is_finite()))
        || det
            .pixels
            .iter()
            .any(|p| !p.coords.iter().all(|v| v.is_finite()))
    {
        return Err(VisionError::Pose(
            "IPPE needs finite points on the target's z = 0 plane".into(),
        ));
    }
    let object: Vector<Point3d> = det
        .target_points
        .iter()
        .map(|p| Point3d::new(p.x, p.y, p.z))
        .collect();
    let image: Vector<Point2d> = det.pixels.iter().map(|p| Point2d::new(p.x, p.y)).collect();
    let (k, dist) = camera_matrices(camera)?;
    let mut rvec = Mat::default();
    let mut tvec = Mat::default();
    let ok = calib3d::solve_pnp(
        &object,
        &image,
        &k,
        &dist,
        &mut rvec,
        &mut tvec,
        false,
        calib3d::SOLVEPNP_IPPE,
    )
    .cv("solvePnP(IPPE)")?;
    if !ok {
        return Err(VisionError::Pose(
            "solvePnP (IPPE) found no solution".into(),
        ));
    }
    let criteria = TermCriteria::new(
        opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
        50,
        1e-12,
    )
    .cv("TermCriteria")?;
    calib3d::solve_pnp_refine_lm(&object, &image, &k, &dist, &mut rvec, &mut tvec, criteria)
        .cv("solvePnPRefineLM")?;
    let r = vec3(&rvec)?;
    let t = vec3(&tvec)?;
    let camera_from_target =
        Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_scaled_axis(r));
    let mut residuals_px = Vec::with_capacity(n);
    for (p, uv) in det.target_points.iter().zip(&det.pixels) {
        let projected = camera.project(&(camera_from_target * p)).ok_or_else(|| {
            VisionError::Pose("the estimated pose puts a corner behind the camera".into())
        })?;
        residuals_px.push((projected - uv).norm());
    }
    let rms_px = (residuals_px.iter().map(|r| r * r).sum::<f64>() / n as f64).sqrt();
    Ok(PoseEstimate {
        camera_from_target,
        residuals_px,
        rms_px,
    })
}

/// OpenCV's camera matrix and distortion vector for a camera model. OpenCV accepts
/// 4, 5, 8, 12 or 14 coefficients in the same order as [`CameraModel`].
pub(crate) fn camera_matrices(camera: &CameraModel) -> Result<(Mat, Vector<f64>), VisionError> {
    let k = Mat::from_slice_2d(&[
        [camera.fx, 0.0, camera.cx],
        [0.0, camera.fy, camera.cy],
        [0.0, 0.0, 1.0],
    ])
    .cv("camera matrix")?;
    let n_dist = if camera.dist[5..].iter().all(|&d| d == 0.0) {
        5
    } else {
        8
    };
    Ok((k, Vector::<f64>::from_slice(&camera.dist[..n_dist])))
}

/// Reads a 3-vector that OpenCV returned as a 3x1 or 1x3 `CV_64F` Mat.
fn vec3(m: &Mat) -> Result<Vector3<f64>, VisionError> {
    let v = m.data_typed::<f64>().cv("pose vector")?;
    match v {
        [x, y, z] if [x, y, z].iter().all(|c| c.is_finite()) => Ok(Vector3::new(*x, *y, *z)),
        _ => Err(VisionError::Pose(format!(
            "solver returned a non-finite or malformed vector {v:?}"
        ))),
    }
}
