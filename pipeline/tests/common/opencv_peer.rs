//! What a user of OpenCV gets on a split (`super::split`): every pair of one of
//! OpenCV's chessboard detectors and one of its hand-eye solvers, the way its
//! tutorials put them together, with nothing of ours in between.
//!
//! Per detector: OpenCV's corners in each image (no refinement of ours); the
//! camera the dataset gives, or else `calibrateCamera` (k1, k2, p1, p2, k3) on
//! every view that detector found; each view's pose by PnP; then each of the
//! seven closed forms of [`super::split::CLOSED_FORMS`] (OpenCV's five
//! `calibrateHandEye` methods, then the board's pose in the base by least
//! squares, and its two `calibrateRobotWorldHandEye` methods). Ours agree with
//! OpenCV's to 1e-4 m and rad (`tests/tests/opencv_agreement.rs`) and do not
//! have OpenCV 4.6's quaternion sign flips, so the figures are, if anything,
//! kind to OpenCV.
//!
//! A symmetric board (Tabb's 9x7 squares) has two labellings no image tells
//! apart, and OpenCV picks either: each view takes the labelling nearer the
//! pipeline's own for that capture (captures the pipeline could not label are
//! left out), so the OpenCV user is given the labelling problem solved.

use std::collections::HashMap;
use std::sync::{LazyLock, Mutex};

use b2b_calib::Iso3;
use b2b_calib::camera::CameraModel;
use b2b_pipeline::{CalibrationRun, RobotSetup, target_of};
use b2b_vision::BoardDetection;
use b2b_vision::checkerboard::{CornerMethod, find_corners, orient_corners};
use b2b_vision::intrinsics::{DistortionTerms, IntrinsicsOptions, calibrate_from_detections};
use nalgebra::Point2;
use opencv_flags::*;

use super::split::{CLOSED_FORMS, Split, closed_form_board, mean, touch_errors};

/// OpenCV's `CALIB_CB_*` flags (calib3d.hpp), so that this test needs no
/// OpenCV binding of its own.
mod opencv_flags {
    pub const ADAPTIVE_THRESH: i32 = 1;
    pub const NORMALIZE_IMAGE: i32 = 2;
}

/// The chessboard detectors a user of OpenCV picks from: the classic one with
/// `cornerSubPix` (11x11, as in OpenCV's calibration tutorial), and the
/// sector-based one.
pub const DETECTORS: [(&str, CornerMethod); 2] = [
    (
        "findChessboardCorners + cornerSubPix",
        CornerMethod::Classic {
            flags: ADAPTIVE_THRESH | NORMALIZE_IMAGE,
            half_window: Some(5),
        },
    ),
    (
        "findChessboardCornersSB",
        CornerMethod::SectorBased { flags: 0 },
    ),
];

/// OpenCV's corners per (recording, detector, image): the same images are
/// dealt to pseudo robots by more than one split.
type RawCorners = HashMap<(String, &'static str, String), Option<Vec<Point2<f64>>>>;
static RAW: LazyLock<Mutex<RawCorners>> = LazyLock::new(Default::default);

/// One robot's views a detector found (named, as `calibrateCamera` takes
/// them) and their flange poses.
type Found = (Vec<(String, BoardDetection)>, Vec<Iso3>);

/// One detector and solver pair's error: the mean over the touch locations.
#[derive(Debug, Clone)]
pub struct PeerFigure {
    pub detector: &'static str,
    /// Where the camera came from: `given`, or `calibrateCamera` with its flags.
    pub intrinsics: &'static str,
    pub solver: &'static str,
    pub error_m: f64,
}

/// Every detector and solver pair on the split, `f64::INFINITY` where a pair
/// gives no answer (too few views found, a solver failing).
pub fn opencv_pairs(
    s: &Split,
    run: &CalibrationRun,
    points: &[nalgebra::Point3<f64>],
) -> Vec<PeerFigure> {
    let b2b_vision::Target::Checkerboard(spec) = target_of(&s.dataset).unwrap() else {
        panic!("the real splits are checkerboards");
    };
    let mut out = vec![];
    for (detector, method) in DETECTORS {
        // Per robot: the views this detector found and their flange poses.
        let mut found: Vec<Found> = vec![];
        for (k, robot) in s.dataset.robots.iter().enumerate() {
            let ours = &run.observations[k];
            let mut views: Vec<(String, BoardDetection)> = vec![];
            let mut flanges = vec![];
            for cap in &robot.captures {
                let path = s.dataset.image_path(&robot.id, cap).expect("an image");
                let img = b2b_vision::load_gray(&path).unwrap();
                let key = (
                    s.dataset.manifest.name.clone(),
                    detector,
                    cap.image.clone().expect("an image").display().to_string(),
                );
                let raw = {
                    let mut cache = RAW.lock().unwrap();
                    cache
                        .entry(key)
                        .or_insert_with(|| find_corners(&img, &spec, method).unwrap())
                        .clone()
                };
                let Some(raw) = raw else {
                    continue;
                };
                let reference = ours.observations.iter().find(|o| o.row == cap.row);
                let pixels = match reference {
                    Some(o) => match nearer_labelling(raw, &o.board.pixels) {
                        Some(p) => p,
                        None => continue,
                    },
                    None if spec.orientation_is_unambiguous() => {
                        match orient_corners(&img, &spec, raw) {
                            Ok(p) => p,
                            Err(_) => continue,
                        }
                    }
                    None => continue,
                };
                let n = spec.corner_count();
                views.push((
                    format!("{} row {}", robot.id, cap.row),
                    BoardDetection {
                        target_points: (0..n).map(|i| spec.target_point(i)).collect(),
                        corner_ids: (0..n).collect(),
                        pixels,
                        method,
                        refined: false,
                    },
                ));
                flanges.push(cap.base_from_flange);
            }
            eprintln!(
                "  {detector}: {} found the board in {} of {} images",
                robot.id,
                views.len(),
                robot.captures.len()
            );
            found.push((views, flanges));
        }
        // The dataset's cameras, or calibrateCamera on each robot's views, and
        // on every view of the recording (both pseudo robots carry one camera:
        // a user calibrating it would take all its images), each with OpenCV's
        // default terms (k1, k2, p1, p2, k3) and with k3 fixed at zero.
        let given = s
            .dataset
            .robots
            .iter()
            .map(|r| given_camera(s, &r.id))
            .collect::<Option<Vec<_>>>();
        let (w, h) = (
            run.observations[0].camera.width,
            run.observations[0].camera.height,
        );
        let calibrate = |views: &[(String, BoardDetection)], terms: DistortionTerms| {
            let all_views = IntrinsicsOptions {
                outlier_factor: f64::INFINITY,
                max_image_rms_px: f64::INFINITY,
                fit_k3: terms == DistortionTerms::K1K2P1P2K3,
                ..IntrinsicsOptions::default()
            };
            calibrate_from_detections(views, w, h, &all_views, terms, None)
                .inspect_err(|e| eprintln!("  {detector}: calibrateCamera failed: {e}"))
                .ok()
                .map(|r| r.camera)
        };
        let intrinsics: Vec<(&'static str, Vec<Option<CameraModel>>)> = match given {
            Some(cameras) => vec![("given", cameras.into_iter().map(Some).collect())],
            None => {
                let every: Vec<(String, BoardDetection)> =
                    found.iter().flat_map(|(v, _)| v.iter().cloned()).collect();
                let mut variants = vec![];
                for (name, name_all, terms) in [
                    (
                        "calibrateCamera per robot",
                        "calibrateCamera on all images",
                        DistortionTerms::K1K2P1P2K3,
                    ),
                    (
                        "calibrateCamera FIX_K3 per robot",
                        "calibrateCamera FIX_K3 on all images",
                        DistortionTerms::K1K2P1P2,
                    ),
                ] {
                    variants.push((
                        name,
                        found.iter().map(|(v, _)| calibrate(v, terms)).collect(),
                    ));
                    variants.push((name_all, vec![calibrate(&every, terms); found.len()]));
                }
                variants
            }
        };
        for (camera_name, cameras) in intrinsics {
            // Per robot: (base_from_flange, camera_from_target) of every view.
            let per_robot: Vec<(Vec<Iso3>, Vec<Iso3>)> = found
                .iter()
                .zip(&cameras)
                .map(|((views, flanges), camera)| {
                    let mut b = vec![];
                    let mut c = vec![];
                    if let Some(camera) = camera {
                        for ((_, d), f) in views.iter().zip(flanges) {
                            if let Ok(pose) = b2b_vision::board_pose(d, camera) {
                                b.push(*f);
                                c.push(pose.camera_from_target);
                            }
                        }
                    }
                    (b, c)
                })
                .collect();
            for (k, solver) in CLOSED_FORMS.iter().enumerate() {
                let board = |(b, c): &(Vec<Iso3>, Vec<Iso3>)| {
                    (b.len() >= 3).then(|| closed_form_board(b, c, k)).flatten()
                };
                let error_m = match (board(&per_robot[0]), board(&per_robot[1])) {
                    (Some(t1), Some(t2)) => mean(&touch_errors(
                        &(t1 * t2.inverse()),
                        &s.base1_from_base2,
                        points,
                    )),
                    _ => f64::INFINITY,
                };
                out.push(PeerFigure {
                    detector,
                    intrinsics: camera_name,
                    solver,
                    error_m,
                });
            }
        }
    }
    out
}

/// The dataset's camera for `robot`, `None` when it gives none (the
/// pipeline's own reading of `dataset.json`).
fn given_camera(s: &Split, robot: &str) -> Option<CameraModel> {
    RobotSetup::from_dataset(&s.dataset, robot)
        .ok()
        .map(|setup| setup.camera)
}

/// OpenCV's row-major corners as they are or turned by 180° (the list
/// reversed), whichever lies nearer `reference` (in target order); `None`
/// when neither lies within 5 px of it on average (another board, or OpenCV's
/// rows running the other way: the view is left out).
fn nearer_labelling(raw: Vec<Point2<f64>>, reference: &[Point2<f64>]) -> Option<Vec<Point2<f64>>> {
    if raw.len() != reference.len() {
        return None;
    }
    let distance = |p: &[Point2<f64>]| -> f64 {
        p.iter()
            .zip(reference)
            .map(|(a, b)| (a - b).norm())
            .sum::<f64>()
            / p.len() as f64
    };
    let turned: Vec<_> = raw.iter().rev().copied().collect();
    let best = if distance(&turned) < distance(&raw) {
        turned
    } else {
        raw
    };
    (distance(&best) < 5.0).then_some(best)
}
