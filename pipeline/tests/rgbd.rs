//! The RGB-D feature method: the simulator's textured RGB-D dataset against its
//! ground truth and touch points, synthetic scenes with known transforms, and
//! degenerate input.

use b2b_calib::Iso3;
use b2b_calib::camera::CameraModel;
use b2b_calib::pose::pose_distance;
use b2b_calib::refine::{RefineOptions, RobotNoise};
use b2b_dataset::{Dataset, load_ground_truth};
use b2b_pipeline::rgbd::{
    NEAR_GATE, RgbdOptions, combine_pairs, fit_camera_pair, lift_matches, lift_pixel, load_views,
    match_views, match_views_near, rgbd_base_to_base, rgbd_base_to_base_with_hand_eyes,
};
use b2b_pipeline::verify;
use b2b_vision::features::{DepthImage, FeatureMatch};
use nalgebra::{Point2, Point3, Translation3, UnitQuaternion, Vector3};

mod common;
use common::*;

/// A small deterministic generator (no rand in this crate's dev-dependencies).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.next()
    }
    fn gauss(&mut self) -> f64 {
        let u = self.next().max(1e-300);
        let v = self.next();
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }
}

/// The dataset through the full method (hand-eyes from the board), against the
/// ground truth (read only here) and the touch points.
#[test]
fn sim_rgbd_boxes_meets_the_touch_goal() {
    let dir = bundled("sim-rgbd-boxes-2x5");
    let ds = Dataset::load(&dir).unwrap();
    // The rendered arms carry DH errors of about 0.3 mm at the flange: the
    // systematic error that makes the covariance honest on this data (README).
    let refine = RefineOptions {
        systematic: RobotNoise {
            sigma_t_m: 0.3e-3,
            sigma_r_rad: 0.015_f64.to_radians(),
        },
        ..RefineOptions::default()
    };
    let run = rgbd_base_to_base(&ds, &refine, &RgbdOptions::default()).unwrap();
    let truth = load_ground_truth(&dir).unwrap().unwrap();
    let est = run.result.base1_from_base2.to_isometry("T").unwrap();
    let (dt, da) = pose_distance(&est, &truth.base1_from_base2.unwrap());
    let accepted = run.pairs.iter().filter(|p| p.accepted).count();
    for p in &run.pairs {
        eprintln!(
            "pair rows {:?}: {} matches, {} lifted, {} inliers, rms {:.2} mm, accepted {}, {}",
            p.rows,
            p.matches,
            p.lifted,
            p.inliers,
            p.rms_m * 1e3,
            p.accepted,
            p.reason.as_deref().unwrap_or("")
        );
    }
    let touches = ds.touch_points.as_ref().expect("touch_points.csv");
    // Each touch carries both pointers' tip noise (the scene's tip_sigma_m).
    let tip_sigma_m = 0.2e-3;
    let (report, metrics) = verify(&run.result, touches, tip_sigma_m).unwrap();
    let sd_t_mm: Vec<f64> = (3..6)
        .map(|i| run.result.covariance[i][i].sqrt() * 1e3)
        .collect();
    eprintln!(
        "rgbd vs ground truth: {:.2} mm, {:.3} deg; {accepted}/{} pairs accepted; touch mean {:.2} mm, rms {:.2}, max {:.2} (n = {}); predicted mean {:.2} mm, within predicted p95 {:.0} %; σ_t {:?} mm",
        dt * 1e3,
        da.to_degrees(),
        run.pairs.len(),
        report.touch_mean_mm,
        report.touch_rms_mm,
        report.touch_max_mm,
        report.n,
        run.result.predicted_touch_error_m.mean * 1e3,
        report.within_predicted_p95 * 100.0,
        sd_t_mm
    );
    // The covariance is honest: touches fall inside the predicted 95% bound about as
    // often as promised, and the bound is not absurdly loose either.
    let mut errors = metrics.errors_m.clone();
    errors.sort_by(f64::total_cmp);
    let observed_p95 = errors[((errors.len() - 1) as f64 * 0.95).round() as usize];
    let predicted_p95 = run.result.predicted_touch_error_m.p95;
    let cov = nalgebra::Matrix6::from_fn(|i, j| run.result.covariance[i][j]);
    let delta = b2b_calib::pose::left_difference(&est, &truth.base1_from_base2.unwrap());
    let m2 = b2b_calib::refine::mahalanobis2(&delta, &cov).unwrap_or(f64::INFINITY);
    let sd_r_deg: Vec<f64> = (0..3)
        .map(|i| run.result.covariance[i][i].sqrt().to_degrees())
        .collect();
    eprintln!(
        "error vs truth: Mahalanobis² {m2:.1} (6 dof: 95% below 12.6); σ_ω {sd_r_deg:.3?} deg"
    );
    eprintln!(
        "covariance check: {:.0} % of {} touches inside their predicted 95% bound; predicted p95 {:.2} mm vs observed p95 {:.2} mm (ratio {:.2})",
        metrics.within_predicted_p95 * 100.0,
        metrics.n,
        predicted_p95 * 1e3,
        observed_p95 * 1e3,
        predicted_p95 / observed_p95
    );
    assert!(
        metrics.within_predicted_p95 >= 0.85,
        "only {:.0} % inside the predicted 95% bound",
        metrics.within_predicted_p95 * 100.0
    );
    assert!(
        predicted_p95 <= 3.0 * observed_p95,
        "predicted p95 {predicted_p95} m vs observed {observed_p95} m"
    );
    assert_eq!(run.result.method, "rgbd");
    assert!(accepted >= 3, "only {accepted} pairs accepted");
    // Every view has its fit under the result, as the board methods give: the
    // report's residual and coverage panels come from it.
    let per = &run.result.captures.per_capture;
    let views: usize = ds.robots.iter().map(|r| r.captures.len()).sum();
    assert_eq!(per.len(), views, "one per_capture entry per view");
    for c in per {
        let used = run
            .pairs
            .iter()
            .any(|p| p.accepted && p.rows[if c.robot == ds.robots[0].id { 0 } else { 1 }] == c.row);
        eprintln!(
            "{} row {}: rms {:?} px, {} outliers, from {:.2?}",
            c.robot, c.row, c.rms_px, c.outlier_corners, c.view_direction
        );
        assert_eq!(c.rms_px.is_some(), used, "{} row {}", c.robot, c.row);
        // Features localise to about a pixel; the arms' errors (0.3 mm at 0.5-1 m)
        // add a fraction of one.
        if let Some(rms) = c.rms_px {
            assert!(
                rms > 0.05 && rms < 3.0,
                "{} row {}: {rms} px",
                c.robot,
                c.row
            );
        }
        let d = nalgebra::Vector3::from(c.view_direction);
        assert!((d.norm() - 1.0).abs() < 1e-9);
        // The cameras look down at the table.
        assert!(d.z > 0.3, "{} row {}: {d:?}", c.robot, c.row);
    }
    assert!(
        report.touch_mean_mm <= 5.0,
        "touch mean {:.2} mm",
        report.touch_mean_mm
    );
    assert!(dt < 0.005 && da.to_degrees() < 0.5, "{dt} m {da} rad");
}

/// The checkerboard scene (`datasets/sim-checkerboard-2x12/scene.json`: the board on
/// a plain table, nothing else textured) rendered again with a depth camera, and the
/// RGB-D method with hand-eyes from an earlier calibration (the committed
/// checkerboard dataset's): no board detector touches the base-to-base step, which
/// sees the board only as texture. A checkerboard is a hard scene for local
/// features (its corners look alike; the ratio test drops most of them), so few
/// pairs pass; the test pins how many and that those give the right answer.
#[test]
fn checkerboard_scene_without_a_board_detector() {
    let committed = bundled("sim-checkerboard-2x12");
    let mut scene = b2b_sim::scene::Scene::load(&committed.join("scene.json")).unwrap();
    let depth_scene =
        b2b_sim::scene::Scene::load(&bundled("sim-rgbd-boxes-2x5").join("scene.json")).unwrap();
    assert!(scene.depth.is_none() && scene.boxes.is_empty());
    scene.depth = depth_scene.depth;
    scene.viewpoints.count = 6;
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("checkerboard-depth");
    b2b_sim::generate::generate_scene(
        &scene,
        &committed.join("scene.json"),
        3,
        &out,
        &b2b_sim::generate::GenerateOptions::default(),
    )
    .unwrap();
    // The hand-eyes of an earlier session, from the committed dataset's board.
    let earlier = Dataset::load(&committed).unwrap();
    let mut he = Vec::new();
    let mut cov = Vec::new();
    for robot in ["robot1", "robot2"] {
        let obs = b2b_pipeline::observe_robot(&earlier, robot).unwrap();
        let h = b2b_pipeline::hand_eye(
            &obs,
            b2b_pipeline::HandEyeChoice::Refined,
            &RefineOptions::default(),
        )
        .unwrap();
        he.push(h.estimate.flange_from_camera);
        cov.push(h.estimate.flange_from_camera_covariance);
    }
    let ds = Dataset::load(&out).unwrap();
    let run = rgbd_base_to_base_with_hand_eyes(
        &ds,
        [he[0], he[1]],
        Some([cov[0], cov[1]]),
        &RgbdOptions::default(),
    )
    .unwrap();
    let truth = load_ground_truth(&out).unwrap().unwrap();
    let est = run.result.base1_from_base2.to_isometry("T").unwrap();
    let (dt, da) = pose_distance(&est, &truth.base1_from_base2.unwrap());
    let (report, _) = verify(&run.result, ds.touch_points.as_ref().unwrap(), 0.0).unwrap();
    let accepted: Vec<_> = run.pairs.iter().filter(|p| p.accepted).collect();
    eprintln!(
        "checkerboard scene, rgbd without a board detector: {}/{} pairs accepted ({:?} inliers), {:.2} mm / {:.3} deg from the truth, touch mean {:.2} mm, max {:.2} mm",
        accepted.len(),
        run.pairs.len(),
        accepted.iter().map(|p| p.inliers).collect::<Vec<_>>(),
        dt * 1e3,
        da.to_degrees(),
        report.touch_mean_mm,
        report.touch_max_mm
    );
    assert!(accepted.len() >= 2, "{} pairs accepted", accepted.len());
    assert!(
        report.touch_mean_mm <= 5.0,
        "touch mean {:.2} mm",
        report.touch_mean_mm
    );
    assert!(dt < 0.005 && da.to_degrees() < 0.5, "{dt} m {da} rad");
}

/// With the true hand-eyes, what is left is the feature/depth part alone.
#[test]
fn sim_rgbd_boxes_with_true_hand_eyes() {
    let dir = bundled("sim-rgbd-boxes-2x5");
    let ds = Dataset::load(&dir).unwrap();
    let truth = load_ground_truth(&dir).unwrap().unwrap();
    let he = [
        truth.flange_from_camera["robot1"],
        truth.flange_from_camera["robot2"],
    ];
    let run = rgbd_base_to_base_with_hand_eyes(&ds, he, None, &RgbdOptions::default()).unwrap();
    let est = run.result.base1_from_base2.to_isometry("T").unwrap();
    let (dt, da) = pose_distance(&est, &truth.base1_from_base2.unwrap());
    let (report, _) = verify(&run.result, ds.touch_points.as_ref().unwrap(), 0.0).unwrap();
    eprintln!(
        "true hand-eyes: {:.2} mm, {:.3} deg; touch mean {:.2} mm",
        dt * 1e3,
        da.to_degrees(),
        report.touch_mean_mm
    );
    assert!(dt < 0.005 && da.to_degrees() < 0.5, "{dt} m {da} rad");
}

/// Matching near a prediction (the robot's poses and the true hand-eye say
/// where each camera stood) keeps what brute-force matching finds between a
/// robot's rendered views: a fit as close to the kinematics, at least 90% of
/// its inliers (2-3x as many here: candidates near the prediction pass the
/// ratio test where the whole image holds look-alikes). A prediction
/// turned by 10° (beyond the gate) leaves too few matches to fit, and a gate
/// that is not positive is refused.
#[test]
fn matching_near_a_prediction_keeps_the_fit() {
    let dir = bundled("sim-rgbd-boxes-2x5");
    let ds = Dataset::load(&dir).unwrap();
    let truth = load_ground_truth(&dir).unwrap().unwrap();
    let options = RgbdOptions::default();
    let views = load_views(&ds, "robot1", &options).unwrap().views;
    let flange_from_camera = truth.flange_from_camera["robot1"];
    let mut compared = 0;
    for pair in views.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        let b_from_a = (b.base_from_flange * flange_from_camera).inverse()
            * (a.base_from_flange * flange_from_camera);
        let full = match_views(a, b, &options).unwrap();
        let Ok(full_fit) = fit_camera_pair(&full.points1, &full.points2, &options) else {
            continue;
        };
        let near = match_views_near(a, b, &b_from_a, NEAR_GATE, &options).unwrap();
        let near_fit = fit_camera_pair(&near.points1, &near.points2, &options).unwrap();
        // Against the kinematics' camera motion.
        let a_from_b = b_from_a.inverse();
        let (dt, da) = pose_distance(&near_fit.camera1_from_camera2, &a_from_b);
        let (ft, fa) = pose_distance(&full_fit.camera1_from_camera2, &a_from_b);
        eprintln!(
            "rows {} -> {}: brute force {} matches, {} inliers, {:.3} mm {:.4} deg from the kinematics; near {} matches, {} inliers, {:.3} mm {:.4} deg",
            a.row,
            b.row,
            full.matches,
            full_fit.inliers,
            ft * 1e3,
            fa.to_degrees(),
            near.matches,
            near_fit.inliers,
            dt * 1e3,
            da.to_degrees()
        );
        // The kinematics carry the arm's DH errors (about 0.3 mm at the
        // flange) and the depth its noise: both fits sit 0.3-2.1 mm from them.
        assert!(dt < 2.5e-3 && da < 0.2f64.to_radians(), "{dt} m, {da} rad");
        assert!(
            near_fit.inliers * 10 >= full_fit.inliers * 9,
            "{} of {}",
            near_fit.inliers,
            full_fit.inliers
        );
        let turned = Iso3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_euler_angles(0.0, 10f64.to_radians(), 0.0),
        ) * b_from_a;
        let off = match_views_near(a, b, &turned, NEAR_GATE, &options).unwrap();
        assert!(
            fit_camera_pair(&off.points1, &off.points2, &options).is_err(),
            "10 deg off: {} matches",
            off.matches
        );
        compared += 1;
    }
    assert!(compared >= 2, "{compared} pairs of views fitted");
    let err = match_views_near(&views[0], &views[1], &Iso3::identity(), 0.0, &options)
        .unwrap_err()
        .to_string();
    assert!(err.contains("gate"), "{err}");
}

fn camera() -> CameraModel {
    CameraModel::new(
        424,
        240,
        [307.6, 307.4, 212.9, 119.4],
        &[0.06, -0.12, 0.0, 0.0, 0.03],
    )
    .unwrap()
}

/// A depth image that is 0 everywhere except 5x5 patches at the given pixels, each
/// at its point's z (quantised to 1 mm, plus noise).
fn patch_depth(
    cam: &CameraModel,
    pts: &[Point3<f64>],
    rng: &mut Rng,
    noise_m: f64,
) -> (DepthImage, Vec<Option<Point2<f64>>>) {
    let (w, h) = (cam.width, cam.height);
    let mut data = vec![0u16; (w * h) as usize];
    let mut px = Vec::new();
    for p in pts {
        let uv = cam.project(p).filter(|uv| {
            uv.x >= 3.0 && uv.y >= 3.0 && uv.x <= w as f64 - 4.0 && uv.y <= h as f64 - 4.0
        });
        if let Some(uv) = uv {
            let z = ((p.z + noise_m * rng.gauss()) * 1000.0).round() as u16;
            let (uc, vc) = (uv.x.round() as i64, uv.y.round() as i64);
            for dv in -2..=2 {
                for du in -2..=2 {
                    data[((vc + dv) * w as i64 + uc + du) as usize] = z;
                }
            }
        }
        px.push(uv);
    }
    (
        DepthImage {
            width: w,
            height: h,
            data,
        },
        px,
    )
}

/// Random points seen from two cameras with a known `camera1_from_camera2`, depth
/// noise and 30 % wrong matches: lifted and fitted, the transform comes back.
#[test]
fn synthetic_pair_with_outliers_is_recovered() {
    let mut rng = Rng(0x9e3779b97f4a7c15);
    let cam = camera();
    let truth = Iso3::from_parts(
        Translation3::new(0.12, -0.05, 0.03),
        UnitQuaternion::from_euler_angles(0.05, -0.2, 0.1),
    );
    // Points in camera 1's view, 0.5-0.8 m away, spread apart so patches do not overlap.
    let mut pts1 = Vec::new();
    while pts1.len() < 60 {
        let p = Point3::new(
            rng.range(-0.3, 0.3),
            rng.range(-0.18, 0.18),
            rng.range(0.5, 0.8),
        );
        let p2 = truth.inverse() * p;
        let ok = cam.project(&p).is_some_and(|uv| cam.contains(&uv))
            && cam.project(&p2).is_some_and(|uv| cam.contains(&uv))
            && pts1.iter().all(|q: &Point3<f64>| {
                (cam.project(q).unwrap() - cam.project(&p).unwrap()).norm() > 8.0
                    && (cam.project(&(truth.inverse() * q)).unwrap() - cam.project(&p2).unwrap())
                        .norm()
                        > 8.0
            });
        if ok {
            pts1.push(p);
        }
    }
    let pts2: Vec<_> = pts1.iter().map(|p| truth.inverse() * p).collect();
    let (d1, px1) = patch_depth(&cam, &pts1, &mut rng, 0.0007);
    let (d2, px2) = patch_depth(&cam, &pts2, &mut rng, 0.0007);
    let valid: Vec<usize> = (0..pts1.len())
        .filter(|&i| px1[i].is_some() && px2[i].is_some())
        .collect();
    assert!(valid.len() >= 40, "{}", valid.len());
    // 30 % of the matches pair a point with a different one.
    let n_out = valid.len() * 3 / 10;
    let matches: Vec<FeatureMatch> = valid
        .iter()
        .enumerate()
        .map(|(k, &i)| {
            let j = if k < n_out {
                valid[(k + 7) % valid.len()]
            } else {
                i
            };
            let jitter = |p: Point2<f64>, r: &mut Rng| {
                p + nalgebra::Vector2::new(0.2 * r.gauss(), 0.2 * r.gauss())
            };
            FeatureMatch {
                index1: i,
                index2: j,
                pixel1: jitter(px1[i].unwrap(), &mut rng),
                pixel2: jitter(px2[j].unwrap(), &mut rng),
                distance: 0.0,
                ratio: 0.5,
            }
        })
        .collect();
    let opts = RgbdOptions::default();
    let (p1, p2) = lift_matches([&cam, &cam], [(&d1, 0.001), (&d2, 0.001)], &matches, &opts);
    assert_eq!(p1.len(), matches.len());
    let fit = fit_camera_pair(&p1, &p2, &opts).unwrap();
    let (dt, da) = pose_distance(&fit.camera1_from_camera2, &truth);
    eprintln!(
        "synthetic pair: {} inliers of {}, {:.2} mm, {:.3} deg",
        fit.inliers,
        p1.len(),
        dt * 1e3,
        da.to_degrees()
    );
    assert!(dt < 0.003 && da.to_degrees() < 0.3, "{dt} {da}");
    assert!(fit.inliers >= matches.len() - n_out - 2 && fit.inliers <= matches.len() - n_out + 2);
    // A plain fit on the same matches is far off: the outliers matter.
    let plain = b2b_calib::procrustes::fit_rigid(&p1, &p2).unwrap();
    assert!(pose_distance(&plain, &truth).0 > 5.0 * dt.max(0.001));
}

#[test]
fn lifting_skips_holes_edges_and_out_of_range() {
    let cam = camera();
    let opts = RgbdOptions::default();
    let (w, h) = (424u32, 240u32);
    let mut data = vec![600u16; (w * h) as usize];
    // A hole at (100, 100) and a depth step at column 300.
    data[(100 * w + 100) as usize] = 0;
    for v in 0..h {
        for u in 300..w {
            data[(v * w + u) as usize] = 900;
        }
    }
    let d = DepthImage {
        width: w,
        height: h,
        data,
    };
    let p = lift_pixel(&cam, &d, 0.001, &Point2::new(50.3, 60.7), &opts).unwrap();
    assert!((p.z - 0.6).abs() < 1e-12);
    let back = cam.project(&p).unwrap();
    assert!((back - Point2::new(50.3, 60.7)).norm() < 1e-6);
    assert_eq!(
        lift_pixel(&cam, &d, 0.001, &Point2::new(100.2, 100.0), &opts),
        Err("depth hole")
    );
    assert_eq!(
        lift_pixel(&cam, &d, 0.001, &Point2::new(299.6, 50.0), &opts),
        Err("depth discontinuity")
    );
    assert_eq!(
        lift_pixel(&cam, &d, 0.001, &Point2::new(0.2, 50.0), &opts),
        Err("outside the depth image")
    );
    let far = DepthImage {
        width: w,
        height: h,
        data: vec![9000; (w * h) as usize],
    };
    assert!(lift_pixel(&cam, &far, 0.001, &Point2::new(50.0, 50.0), &opts).is_err());
}

/// All depth zero: nothing lifts, and the fit says so.
#[test]
fn all_zero_depth_and_no_matches_are_clear_errors() {
    let cam = camera();
    let opts = RgbdOptions::default();
    let zero = DepthImage {
        width: 424,
        height: 240,
        data: vec![0; 424 * 240],
    };
    let matches: Vec<FeatureMatch> = (0..50)
        .map(|i| FeatureMatch {
            index1: i,
            index2: i,
            pixel1: Point2::new(20.0 + 5.0 * i as f64, 100.0),
            pixel2: Point2::new(20.0 + 5.0 * i as f64, 120.0),
            distance: 0.0,
            ratio: 0.5,
        })
        .collect();
    let (p1, p2) = lift_matches(
        [&cam, &cam],
        [(&zero, 0.001), (&zero, 0.001)],
        &matches,
        &opts,
    );
    assert!(p1.is_empty());
    let err = fit_camera_pair(&p1, &p2, &opts).unwrap_err().to_string();
    assert!(err.contains("0 matches with valid depth"), "{err}");
    let err = fit_camera_pair(&[], &[], &opts).unwrap_err().to_string();
    assert!(err.contains("need at least 20"), "{err}");
    let err = combine_pairs(&[], &opts).unwrap_err().to_string();
    assert!(err.contains("no image pair"), "{err}");
}

/// Unrelated point sets: RANSAC finds no 20-point consensus and says so.
#[test]
fn unrelated_points_have_no_consensus() {
    let mut rng = Rng(7);
    let a: Vec<_> = (0..80)
        .map(|_| {
            Point3::new(
                rng.range(-0.3, 0.3),
                rng.range(-0.3, 0.3),
                rng.range(0.4, 0.9),
            )
        })
        .collect();
    let b: Vec<_> = (0..80)
        .map(|_| {
            Point3::new(
                rng.range(-0.3, 0.3),
                rng.range(-0.3, 0.3),
                rng.range(0.4, 0.9),
            )
        })
        .collect();
    let err = fit_camera_pair(&a, &b, &RgbdOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("RANSAC"), "{err}");
}

/// The combination: one wild pair among consistent ones is rejected with a reason;
/// the mean is near the truth, not dragged towards the outlier as a plain mean is.
#[test]
fn combination_rejects_outlier_pairs() {
    let mut rng = Rng(42);
    let truth = Iso3::from_parts(
        Translation3::new(1.04, 0.035, 0.012),
        UnitQuaternion::from_euler_angles(0.005, -0.003, 3.1),
    );
    let mut est = Vec::new();
    for _ in 0..8 {
        let d = Iso3::from_parts(
            Translation3::new(
                0.001 * rng.gauss(),
                0.001 * rng.gauss(),
                0.001 * rng.gauss(),
            ),
            UnitQuaternion::from_scaled_axis(
                Vector3::new(rng.gauss(), rng.gauss(), rng.gauss()) * 0.001,
            ),
        );
        est.push((d * truth, 100, 0.001, 0.1));
    }
    let wild = Iso3::from_parts(
        Translation3::new(0.05, 0.0, 0.0),
        UnitQuaternion::identity(),
    ) * truth;
    est.push((wild, 400, 0.001, 0.1));
    let c = combine_pairs(&est, &RgbdOptions::default()).unwrap();
    assert!(c.verdicts[..8].iter().all(|v| v.is_ok()));
    let reason = c.verdicts[8].clone().unwrap_err();
    assert!(reason.contains("translation"), "{reason}");
    let (dt, da) = pose_distance(&c.base1_from_base2, &truth);
    assert!(dt < 0.002 && da < 0.002, "{dt} {da}");
    // Covariance: positive, of the order of the spread / n.
    let sd = c.covariance[(3, 3)].sqrt();
    assert!(sd > 1e-4 && sd < 2e-3, "{sd}");
    let plain: Vector3<f64> = est
        .iter()
        .map(|e| e.0.translation.vector)
        .sum::<Vector3<f64>>()
        / est.len() as f64;
    assert!((plain - truth.translation.vector).norm() > 0.004);
}

/// A dataset without depth images is refused with the file and the reason.
#[test]
fn dataset_without_depth_is_refused() {
    let ds = Dataset::load(&bundled("sim-checkerboard-2x12")).unwrap();
    let err = rgbd_base_to_base_with_hand_eyes(
        &ds,
        [Iso3::identity(), Iso3::identity()],
        None,
        &RgbdOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("dataset.json") && err.contains("depth_unit_m"),
        "{err}"
    );
}

/// AKAZE and ORB instead of SIFT, with the true hand-eyes: the feature options are
/// honoured and each still lands within the touch goal.
#[test]
fn sim_rgbd_boxes_with_akaze_and_orb() {
    use b2b_vision::features::{FeatureKind, FeatureOptions};
    let dir = bundled("sim-rgbd-boxes-2x5");
    let ds = Dataset::load(&dir).unwrap();
    let truth = load_ground_truth(&dir).unwrap().unwrap();
    let he = [
        truth.flange_from_camera["robot1"],
        truth.flange_from_camera["robot2"],
    ];
    for kind in [FeatureKind::Akaze, FeatureKind::Orb] {
        let opts = RgbdOptions {
            features: FeatureOptions {
                kind,
                ..Default::default()
            },
            ..Default::default()
        };
        let run = rgbd_base_to_base_with_hand_eyes(&ds, he, None, &opts).unwrap();
        let est = run.result.base1_from_base2.to_isometry("T").unwrap();
        let (dt, da) = pose_distance(&est, &truth.base1_from_base2.unwrap());
        let (report, _) = verify(&run.result, ds.touch_points.as_ref().unwrap(), 0.0).unwrap();
        let accepted = run.pairs.iter().filter(|p| p.accepted).count();
        eprintln!(
            "{} (true hand-eyes): {:.2} mm, {:.3} deg, {accepted}/{} pairs; touch mean {:.2} mm",
            kind.name(),
            dt * 1e3,
            da.to_degrees(),
            run.pairs.len(),
            report.touch_mean_mm
        );
        assert!(
            report.touch_mean_mm <= 5.0,
            "{}: {}",
            kind.name(),
            report.touch_mean_mm
        );
    }
}
