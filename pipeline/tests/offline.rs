//! The offline pipeline end to end: real images (ViSP's Franka recording), the
//! simulator's rendered two-robot dataset, and bad input.

use b2b_calib::Iso3;
use b2b_calib::estimate::{RobotCaptures, estimate_hand_eye, seed_hand_eye};
use b2b_calib::pose::{left_difference, pose_distance};
use b2b_calib::refine::mahalanobis2;
use b2b_calib::refine::{RefineOptions, RobotNoise};
use b2b_dataset::{Dataset, load_ground_truth, load_reference};
use b2b_pipeline::{
    B2bMethod, HandEyeChoice, PipelineError, base_to_base, hand_eye, observe_robot, pair_transform,
    verify, verify_pair,
};

mod common;
use common::*;

/// ViSP's published hand-eye on its own Franka data (a result of another tool,
/// not the truth). OpenCV's Park lands 0.3 mm / 0.03 deg from it; our Park must be
/// within 1 mm and 0.1 deg. The arm's pose error here is about 2 mm per
/// capture (the residuals show it: 5-6 px RMS), so with 8 captures any
/// estimate is uncertain by millimetres and a degree, and the refinement, which
/// weighs each capture by that noise, differs from the closed form: it must stay
/// within 4 of its own standard deviations of the published result, and
/// predict each capture's corners from the other seven better than Park does
/// (leave-one-out: the one check here that needs no truth).
#[test]
fn visp_hand_eye_matches_the_published_result() {
    let dir = shared_dataset("visp-franka-eye-in-hand");
    let ds = Dataset::load(&dir).unwrap();
    let obs = observe_robot(&ds, "robot1").unwrap();
    assert_eq!(obs.observations.len(), 8, "rejected: {:?}", obs.rejected);
    let reference = load_reference(&dir).unwrap().unwrap().flange_from_camera["robot1"];
    for choice in ["park", "refined"] {
        let run = hand_eye(
            &obs,
            choice.parse::<HandEyeChoice>().unwrap(),
            &RefineOptions::default(),
        )
        .unwrap();
        let est = &run.estimate;
        let (dt, da) = pose_distance(&est.flange_from_camera, &reference);
        let cov = est.flange_from_camera_covariance;
        let sd_t = (cov[(3, 3)] + cov[(4, 4)] + cov[(5, 5)]).sqrt();
        let sd_r = (cov[(0, 0)] + cov[(1, 1)] + cov[(2, 2)]).sqrt();
        eprintln!(
            "{choice}: {:.3} mm, {:.4} deg from ViSP's result (1-sigma {:.3} mm, {:.4} deg); RMS {:.3} px; robot noise {:.2} mm, {:.3} deg ({})",
            dt * 1e3,
            da.to_degrees(),
            sd_t * 1e3,
            sd_r.to_degrees(),
            est.rms_px,
            est.noise.sigma_t_m * 1e3,
            est.noise.sigma_r_rad.to_degrees(),
            est.noise.shape.name()
        );
        // The README says Park 0.055 mm / 0.018 deg, refined 2.9 mm / 0.93 deg:
        // within 1.5x.
        if choice == "park" {
            assert!(
                dt < 0.083e-3 && da.to_degrees() < 0.027,
                "{choice}: {dt} m, {da} rad"
            );
        } else {
            assert!(
                dt < 4.0 * sd_t && da < 4.0 * sd_r,
                "{choice}: {dt} m, {da} rad"
            );
            assert!(
                dt < 4.35e-3 && da.to_degrees() < 1.4,
                "{choice}: {dt} m, {da} rad"
            );
            // The README says 2.0 mm per axis: within 1.5x.
            assert!(
                (2.0e-3 / 1.5..2.0e-3 * 1.5).contains(&est.noise.sigma_t_m),
                "the arm's error: {} mm",
                est.noise.sigma_t_m * 1e3
            );
        }
    }
    // Leave one capture out, fit the rest, predict its corners.
    let boards: Vec<_> = obs.observations.iter().map(|o| o.board.clone()).collect();
    let poses: Vec<_> = obs
        .observations
        .iter()
        .map(|o| o.camera_from_target)
        .collect();
    let n = boards.len();
    let (mut park, mut refined) = (0.0, 0.0);
    for i in 0..n {
        let b: Vec<_> = (0..n)
            .filter(|k| *k != i)
            .map(|k| boards[k].clone())
            .collect();
        let c: Vec<_> = (0..n).filter(|k| *k != i).map(|k| poses[k]).collect();
        let rest = RobotCaptures {
            camera: &obs.camera,
            captures: &b,
            camera_from_target: &c,
        };
        let options = RefineOptions::default();
        let seed = seed_hand_eye(&rest, &options).unwrap();
        let run = estimate_hand_eye(&rest, &options).unwrap();
        let held_out_rms = |x: &Iso3, w: &Iso3| {
            let camera_from_target = (boards[i].base_from_flange * x).inverse() * w;
            let sum: f64 = boards[i]
                .target_points
                .iter()
                .zip(&boards[i].pixels)
                .map(|(p, uv)| {
                    (obs.camera.project(&(camera_from_target * p)).unwrap() - uv).norm_squared()
                })
                .sum();
            (sum / boards[i].pixels.len() as f64).sqrt()
        };
        park += held_out_rms(&seed.flange_from_camera, &seed.base_from_target) / n as f64;
        refined += held_out_rms(
            &run.estimate.flange_from_camera,
            &run.estimate.base_from_target,
        ) / n as f64;
    }
    eprintln!("held-out corner prediction (RMS px): park {park:.2}, refined {refined:.2}");
    // The README says 6.63 px against 7.31 px: each within 1.5x.
    assert!(refined < park, "refined {refined} px, park {park} px");
    assert!(refined < 1.5 * 6.63 && refined > 6.63 / 1.5, "{refined} px");
    assert!(park < 1.5 * 7.31 && park > 7.31 / 1.5, "{park} px");
}

/// The simulator's rendered two-robot dataset: the result within 1 mm of the
/// ground truth (which calibration never reads) and the touch check consistent
/// with the scene's touch noise.
///
/// The simulated arms carry systematic kinematic (DH) errors of 0.1 mm and
/// 0.005 deg per joint, about 0.3 mm at the flange. The fit estimates the noise
/// it sees in the residuals, but a systematic error is largely common to
/// nearby captures and moves the estimate without showing there: with the
/// default the truth lies outside the 99.9% ellipsoid; with the arm's accuracy
/// given (`systematic`, `--robot-accuracy-mm 0.3 --robot-accuracy-deg 0.015`)
/// it lies inside. The test pins both facts down.
#[test]
fn base_to_base_on_the_simulated_dataset_is_within_its_predicted_error() {
    let dir = bundled("sim-checkerboard-2x12");
    let ds = Dataset::load(&dir).unwrap();
    let truth = load_ground_truth(&dir)
        .unwrap()
        .unwrap()
        .base1_from_base2
        .unwrap();
    let accuracy = RefineOptions {
        systematic: RobotNoise {
            sigma_t_m: 0.3e-3,
            sigma_r_rad: 0.015f64.to_radians(),
        },
        ..Default::default()
    };
    let mut m2s = vec![];
    for opts in [RefineOptions::default(), accuracy] {
        let result = base_to_base(&ds, B2bMethod::Board, &opts).unwrap();
        result.validate().unwrap();
        assert_eq!(
            result.captures.used.values().sum::<usize>(),
            24,
            "{:?}",
            result.captures.rejected
        );
        let est = result.base1_from_base2.to_isometry("T").unwrap();
        let (dt, da) = pose_distance(&est, &truth);
        let cov = nalgebra::Matrix6::from_fn(|i, j| result.covariance[i][j]);
        let m2 = mahalanobis2(&left_difference(&est, &truth), &cov).unwrap();
        // Each touch: tip noise 0.2 mm plus the robot's own positioning error.
        let (report, _) = verify(&result, ds.touch_points.as_ref().unwrap(), 0.3e-3).unwrap();
        eprintln!(
            "systematic error configured {:.2} mm: {:.3} mm, {:.4} deg from the truth; Mahalanobis² {m2:.1}; touch mean {:.3} mm, within predicted p95 {:.2}",
            opts.systematic.sigma_t_m * 1e3,
            dt * 1e3,
            da.to_degrees(),
            report.touch_mean_mm,
            report.within_predicted_p95
        );
        // The README says 0.42 mm and a 0.70 mm touch mean: within 1.5x.
        assert!(dt < 0.63e-3 && da.to_degrees() < 0.027, "{dt} m {da} rad");
        assert_eq!(report.n, 25);
        assert!(report.touch_mean_mm < 1.05);
        assert!(report.within_predicted_p95 >= 0.8);
        m2s.push(m2);
    }
    // The README says Mahalanobis² 50 by default and 0.9 with the accuracy
    // given: within 1.5x, and on either side of the 99.9% limit (22.46).
    assert!(
        m2s[0] > 50.0 / 1.5 && m2s[0] < 50.0 * 1.5,
        "the default Mahalanobis² moved ({}): update the docs",
        m2s[0]
    );
    assert!(
        m2s[1] < 0.9 * 1.5,
        "Mahalanobis² with the robot's accuracy configured: {}",
        m2s[1]
    );
}

/// The committed three-robot set: every pair from the one joint solve against
/// the truth and against its own touch pairs, and against the same pair solved
/// alone (a two-robot dataset of just those robots). With one target the joint
/// problem separates (calib's `three_robots_jointly_are_no_worse_per_pair`), so
/// per pair the joint error is the pair's own to within the shared noise
/// estimate; it must be no worse.
#[test]
fn three_robots_solved_jointly_are_no_worse_per_pair_than_pairs_alone() {
    let dir = bundled("sim-checkerboard-3x12");
    let ds = Dataset::load(&dir).unwrap();
    let truth = load_ground_truth(&dir).unwrap().unwrap();
    let ids: Vec<String> = ds.manifest.robots.iter().map(|r| r.id.clone()).collect();
    assert_eq!(ids.len(), 3);
    let joint = base_to_base(&ds, B2bMethod::Board, &RefineOptions::default()).unwrap();
    joint.validate().unwrap();
    assert_eq!(joint.captures.used.values().sum::<usize>(), 36);
    // The README's figures per pair: mm and degrees from the truth.
    let readme = [(0.486, 0.027), (0.610, 0.048), (0.370, 0.050)];
    for (k, (a, b)) in [(0usize, 1usize), (0, 2), (1, 2)].into_iter().enumerate() {
        let true_pair =
            truth.base1_from_base(a + 1).unwrap().inverse() * truth.base1_from_base(b + 1).unwrap();
        let (est, cov) = pair_transform(&joint, &ids[a], &ids[b]).unwrap();
        let (dt, da) = pose_distance(&est, &true_pair);
        let m2 = mahalanobis2(&left_difference(&est, &true_pair), &cov).unwrap();
        let touches = ds.touches_between(&ids[a], &ids[b]).unwrap();
        let (report, _) = verify_pair(&joint, Some((&ids[a], &ids[b])), touches, 0.3e-3).unwrap();
        // The same two robots alone.
        let mut two = ds.clone();
        two.manifest.robots = vec![ds.manifest.robots[a].clone(), ds.manifest.robots[b].clone()];
        two.robots = vec![ds.robots[a].clone(), ds.robots[b].clone()];
        two.pair_touch_points.clear();
        let alone = base_to_base(&two, B2bMethod::Board, &RefineOptions::default()).unwrap();
        assert!(alone.bases.is_empty() && alone.pairs.is_empty());
        let (alone_t, alone_r) = pose_distance(
            &alone.base1_from_base2.to_isometry("T").unwrap(),
            &true_pair,
        );
        eprintln!(
            "{}-{}: joint {:.3} mm {:.4} deg (Mahalanobis² {m2:.1}), alone {:.3} mm {:.4} deg; touch mean {:.3} mm, within predicted p95 {:.2}",
            ids[a],
            ids[b],
            dt * 1e3,
            da.to_degrees(),
            alone_t * 1e3,
            alone_r.to_degrees(),
            report.touch_mean_mm,
            report.within_predicted_p95
        );
        assert!(
            dt <= alone_t * 1.02 + 1e-6 && da <= alone_r * 1.02 + 1e-6,
            "{}-{}: joint {dt} m {da} rad, alone {alone_t} m {alone_r} rad",
            ids[a],
            ids[b]
        );
        // Within 1.5x of the README's figures for this pair.
        let (mm, deg) = readme[k];
        assert!(
            dt * 1e3 < 1.5 * mm && da.to_degrees() < 1.5 * deg,
            "{}-{}: {dt} m {da} rad",
            ids[a],
            ids[b]
        );
        assert_eq!(report.n, 25);
        assert!(report.within_predicted_p95 >= 0.8);
    }
    // With the robots' accuracy configured (as for two robots, above), every
    // pair's covariance explains its error, the pair without the reference too:
    // the common part of the reference robot's error moves both bases alike and
    // cancels in their pair.
    let accuracy = RefineOptions {
        systematic: RobotNoise {
            sigma_t_m: 0.3e-3,
            sigma_r_rad: 0.015f64.to_radians(),
        },
        ..Default::default()
    };
    let joint = base_to_base(&ds, B2bMethod::Board, &accuracy).unwrap();
    for (a, b) in [(0usize, 1usize), (0, 2), (1, 2)] {
        let true_pair =
            truth.base1_from_base(a + 1).unwrap().inverse() * truth.base1_from_base(b + 1).unwrap();
        let (est, cov) = pair_transform(&joint, &ids[a], &ids[b]).unwrap();
        let m2 = mahalanobis2(&left_difference(&est, &true_pair), &cov).unwrap();
        eprintln!(
            "{}-{} with the accuracy configured: Mahalanobis² {m2:.2}",
            ids[a], ids[b]
        );
        // The README says 1.1-3.4: within 1.5x of the largest.
        assert!(m2 < 5.1, "{}-{}: Mahalanobis² {m2}", ids[a], ids[b]);
    }
}

#[test]
fn a_one_robot_dataset_is_not_a_base_to_base_dataset() {
    let ds = Dataset::load(&shared_dataset("visp-franka-eye-in-hand")).unwrap();
    let err = base_to_base(&ds, B2bMethod::Board, &RefineOptions::default()).unwrap_err();
    assert!(matches!(err, PipelineError::NotTwoRobots { .. }), "{err}");
    assert!(err.to_string().contains("dataset.json"), "{err}");
}

#[test]
fn unknown_robot_and_methods_are_named() {
    let ds = Dataset::load(&shared_dataset("visp-franka-eye-in-hand")).unwrap();
    let err = observe_robot(&ds, "robot9").unwrap_err();
    assert!(err.to_string().contains("robot9"), "{err}");
    let err = "bogus".parse::<HandEyeChoice>().unwrap_err();
    assert!(err.contains("tsai") && err.contains("refined"), "{err}");
    assert!("nope".parse::<B2bMethod>().is_err());
}

/// One mistyped row (tx off by 65 cm) is left out with its reason, named by
/// row and image; the rest give the same result as the clean dataset.
#[test]
fn a_mistyped_row_is_rejected_with_its_reason_and_the_rest_used() {
    let src = bundled("sim-checkerboard-2x12");
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    copy_dir(&src, &dir);
    let csv = dir.join("robot1/captures.csv");
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    let mut cols: Vec<String> = lines[4].split(',').map(str::to_owned).collect();
    let tx: f64 = cols[2].parse().unwrap();
    cols[2] = format!("{}", tx + 0.65);
    lines[4] = cols.join(",");
    std::fs::write(&csv, lines.join("\n") + "\n").unwrap();
    let truth = load_ground_truth(&src)
        .unwrap()
        .unwrap()
        .base1_from_base2
        .unwrap();
    let clean = base_to_base(
        &Dataset::load(&src).unwrap(),
        B2bMethod::Board,
        &RefineOptions::default(),
    )
    .unwrap();
    let result = base_to_base(
        &Dataset::load(&dir).unwrap(),
        B2bMethod::Board,
        &RefineOptions::default(),
    )
    .unwrap();
    eprintln!("rejected: {:?}", result.captures.rejected);
    assert_eq!(result.captures.used["robot1"], 11);
    assert_eq!(result.captures.used["robot2"], 12);
    let rejected = &result.captures.rejected;
    assert_eq!(rejected.len(), 1, "{rejected:?}");
    assert_eq!(rejected[0].row, Some(4));
    assert_eq!(rejected[0].image.as_deref(), Some("images/003.png"));
    // The pre-fit screen (motion invariants) or the seed's screen (board
    // position) names it, whichever sees it first.
    let reason = &rejected[0].reason;
    assert!(
        reason.contains("typo") || reason.contains("mistyped"),
        "{rejected:?}"
    );
    let est = result.base1_from_base2.to_isometry("T").unwrap();
    let (dt, da) = pose_distance(&est, &truth);
    let (ct, _) = pose_distance(&clean.base1_from_base2.to_isometry("T").unwrap(), &truth);
    eprintln!(
        "with the typo row: {:.3} mm, {:.4} deg from the truth (clean: {:.3} mm)",
        dt * 1e3,
        da.to_degrees(),
        ct * 1e3
    );
    // README: below 0.59 mm (the bound as stated).
    assert!(dt < 0.59e-3 && dt < 2.0 * ct.max(0.2e-3), "{dt} m");
}
