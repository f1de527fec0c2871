//! The automatic routine end to end in the simulator: two simulated carts (each an FRI
//! server on loopback UDP and a rendering camera publishing into iceoryx2, in a
//! process of its own), two `agent auto` processes driving them through FRI, and a
//! coordinator, all over zenoh on loopback.
//!
//! - The checkerboard scene, with the board's configured position off by 6 cm, so
//!   the first views sit off-centre and the closed loop must re-centre them. Checks:
//!   both arms complete the routine with >= 24 good captures, the result is within
//!   its predicted error of the ground truth, and `coordinator verify` against the
//!   scene's touch pairs is within the predicted bound.
//! - A camera that reports its intrinsics 1% / 2 px off: `coordinator run
//!   --refine-intrinsics` recovers them from what the agents publish.
//! - The ChArUco scene with occluders over the board, ARToolKit's 4x3 multimarker
//!   and the three-face corner (each target given to the agent exactly as its
//!   `dataset.json` gives it: one target model offline and live): the live touch
//!   mean is within 1.5x the offline one on the same scene's dataset.
//! - A checkerboard that looks the same turned by 180°, lying flat: each agent
//!   labels its captures by its setup sheet, and the result is within 1 mm.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use b2b_protocol::{CalibrationResult, Pose};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

fn dataset(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../datasets")
        .join(name)
}

/// How one end-to-end run is set up.
struct Run<'a> {
    dataset: &'a str,
    /// A scene file to run instead of the dataset's own `scene.json` (the same
    /// scene changed; its ground truth and touch pairs are the dataset's).
    scene: Option<PathBuf>,
    /// More `coordinator run` arguments.
    coordinator_args: &'a [&'a str],
    /// Moves the setup sheet's board away from where it is (in the board frame).
    board_off: Option<Isometry3<f64>>,
    count: usize,
    min_good: usize,
    /// `coordinator run --method`.
    method: &'a str,
}

/// The coordinator and two `agent auto --sim` processes on `run`'s scene: each
/// agent's routine summary line (then its camera estimate's line, when it made
/// one) and the result.
fn run_auto(run: &Run<'_>) -> (tempfile::TempDir, PathBuf, Vec<String>, CalibrationResult) {
    run_auto_carts(run, &["robot1", "robot2"])
}

/// [`run_auto`] with one cart per robot of `robots` (robot 1 the reference).
fn run_auto_carts(
    run: &Run<'_>,
    robots: &[&str],
) -> (tempfile::TempDir, PathBuf, Vec<String>, CalibrationResult) {
    // Two end-to-end runs at a time (the test harness's two threads): the carts
    // render at 6 frames per second and a frame exposed while the arm moves cheaply
    // (`b2b-sim-cart`), so four carts and their agents fit two cores; each frame is
    // stamped no later than the arm state it shows, so a late frame is never
    // matched to the wrong pose.
    let net = common::net();
    let (coordinator_cfg, agent_cfg) = (&net.coordinator_cfg, &net.agent_cfg);
    let dir = net.dir;
    let scene = run
        .scene
        .clone()
        .unwrap_or_else(|| dataset(run.dataset).join("scene.json"));
    let result_file = dir.path().join("RESULT.json");
    let sigma = ["--robot-sigma-mm", "0.3", "--robot-sigma-deg", "0.015"];
    let mut coordinator = common::Killed(
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["run", "--robots", &robots.join(","), "--method", run.method])
            .arg("--zenoh")
            .arg(coordinator_cfg)
            .arg("--state-dir")
            .arg(dir.path().join("coordinator-state"))
            .arg("--out")
            .arg(&result_file)
            .args(sigma)
            .args(run.coordinator_args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let mut agents = vec![];
    for &robot in robots {
        let mut setup = common::sim_setup(&scene, robot, dir.path());
        if let Some(off) = run.board_off {
            let board = setup.base_from_target_approx.to_isometry("board").unwrap() * off;
            setup.base_from_target_approx = Pose::from_isometry(&board);
        }
        let setup_file = dir.path().join(format!("setup-{robot}.json"));
        std::fs::write(&setup_file, serde_json::to_string_pretty(&setup).unwrap()).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_agent"))
            .args(["auto", "--quiet", "--robot", robot, "--sim"])
            .arg(&scene)
            .arg("--setup")
            .arg(&setup_file)
            .args(["--min-good", &run.min_good.to_string()])
            .args(["--count", &run.count.to_string()])
            .arg("--zenoh")
            .arg(agent_cfg)
            .arg("--state-dir")
            .arg(dir.path().join(format!("agent-{robot}")))
            .args(["--wait-result-s", "120"])
            .args(sigma)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        agents.push((robot, child));
    }
    let deadline = Instant::now() + Duration::from_secs(400);
    let mut summaries = vec![];
    for (robot, child) in agents {
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.success(),
            "{robot} failed: {stderr}\n{}",
            String::from_utf8_lossy(&out.stdout)
        );
        // "robotN: K captures (...), R retries; ..." - the routine's summary line.
        let summary = stderr
            .lines()
            .find(|l| l.starts_with(&format!("{robot}: ")) && l.contains(" captures ("))
            .unwrap_or_else(|| panic!("{robot}: no summary in {stderr}"));
        eprintln!("{summary}");
        let mut summary = summary.to_owned();
        // The agent's own estimate of a camera that gave no intrinsics.
        if let Some(camera) = stderr
            .lines()
            .find(|l| l.starts_with(&format!("{robot}: camera estimated")))
        {
            eprintln!("{camera}");
            summary = format!("{summary}\n{camera}");
        }
        summaries.push(summary);
    }
    let result = common::wait_for_result(
        &result_file,
        &mut coordinator,
        deadline.saturating_duration_since(Instant::now()),
    );
    (dir, result_file, summaries, result)
}

#[test]
fn two_carts_run_the_automatic_routine_to_a_verified_result() {
    // Two good captures more than the 24 the result must use: the estimator may
    // rightly leave some out (frames taken while the arm still moved on a loaded
    // machine: a fresh-clone CI run lost two), and that must not fail the run.
    let (_dir, result_file, summaries, result) = run_auto(&Run {
        dataset: "sim-checkerboard-2x12",
        scene: None,
        coordinator_args: &[],
        // The setup sheet puts the board 6 cm and 5 deg away from where it is.
        board_off: Some(Isometry3::from_parts(
            Translation3::new(0.05, 0.035, 0.0),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, 5f64.to_radians())),
        )),
        count: 30,
        min_good: 26,
        method: "board",
    });
    for summary in &summaries {
        let retries: usize = summary
            .split(" retries")
            .next()
            .and_then(|head| head.rsplit(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or(0);
        assert!(
            retries > 0,
            "the off-centre board was never re-centred: {summary}"
        );
    }
    for robot in ["robot1", "robot2"] {
        let used = result.captures.used.get(robot).copied().unwrap_or(0);
        assert!(
            used >= 24,
            "{robot}: only {used} good captures; rejected: {:?}",
            result.captures.rejected
        );
    }
    let (err, _) = common::truth_error(&dataset("sim-checkerboard-2x12"), &result);
    let bound = 3.0 * result.predicted_touch_error_m.p95.max(2e-4);
    eprintln!(
        "live auto result: {:.3} mm from the truth; predicted touch error p95 {:.3} mm",
        err * 1e3,
        result.predicted_touch_error_m.p95 * 1e3
    );
    assert!(err < bound && err < 1e-3, "{err} m from the truth");

    let (printout, v) = common::verify(
        &result_file,
        &dataset("sim-checkerboard-2x12").join("touch_points.csv"),
        &["--tip-sigma-mm", "0.3"],
    );
    eprintln!("{printout}");
    let mean_mm = v["touch_mean_mm"].as_f64().unwrap();
    assert!(mean_mm < 1.5, "touch mean {mean_mm} mm");
}

/// `agent auto` on a committed scene with the target given exactly as its
/// `dataset.json` gives it (one target model offline and live): each arm keeps at
/// least `min_used` captures, and the live touch mean is within 1.5x the offline
/// one on the scene's dataset (the same carts and touch pairs).
fn live_within_offline(name: &str, method: &str, count: usize, min_used: usize) {
    let (dir, result_file, _, result) = run_auto(&Run {
        dataset: name,
        scene: None,
        coordinator_args: &[],
        board_off: None,
        count,
        // Two good captures more than the result must use: the estimator may
        // rightly leave one or two out (a frame taken while the arm still moved
        // on a loaded machine: one run of the three-face corner with one to spare
        // kept fewer than 15).
        min_good: min_used + 2,
        method,
    });
    for robot in ["robot1", "robot2"] {
        let used = result.captures.used.get(robot).copied().unwrap_or(0);
        assert!(
            used >= min_used,
            "{robot}: only {used} good captures; rejected: {:?}",
            result.captures.rejected
        );
    }
    let (err, _) = common::truth_error(&dataset(name), &result);
    eprintln!(
        "live {name}: {:.3} mm from the truth; predicted touch error p95 {:.3} mm",
        err * 1e3,
        result.predicted_touch_error_m.p95 * 1e3
    );
    let touch = dataset(name).join("touch_points.csv");
    let (printout, live) = common::verify(&result_file, &touch, &["--tip-sigma-mm", "0.3"]);
    eprintln!("{printout}");
    let offline_dir = dir.path().join("offline");
    std::fs::create_dir_all(&offline_dir).unwrap();
    common::offline_result_of(&offline_dir, &dataset(name), method);
    let (_, offline) = common::verify(
        &offline_dir.join("OFFLINE.json"),
        &touch,
        &["--tip-sigma-mm", "0.3"],
    );
    let (live_mm, offline_mm) = (
        live["touch_mean_mm"].as_f64().unwrap(),
        offline["touch_mean_mm"].as_f64().unwrap(),
    );
    eprintln!("{name}: touch mean live {live_mm:.3} mm, offline {offline_mm:.3} mm");
    assert!(
        live_mm <= 1.5 * offline_mm,
        "live touch mean {live_mm} mm against offline {offline_mm} mm"
    );
    assert!(err < 1.5e-3, "{err} m from the truth");
}

/// The ChArUco scene with occluders over the board (partial views).
#[test]
fn charuco_with_occluders_runs_the_automatic_routine() {
    live_within_offline("sim-charuco-occluded-2x10", "board", 20, 15);
}

/// ARToolKit's 4x3 multimarker sheet.
#[test]
fn planar_multimarker_runs_the_automatic_routine() {
    live_within_offline("sim-multimarker-4x3-2x10", "multimarker", 20, 15);
}

/// The non-planar three-face corner: viewpoints about the mean of its faces'
/// normals.
#[test]
fn three_face_corner_runs_the_automatic_routine() {
    live_within_offline("sim-multimarker-corner-2x10", "multimarker", 20, 15);
}

/// A board that looks the same turned by 180° (8x6 inner corners) lying flat,
/// so that gravity cannot tell the turn either: each agent labels every capture
/// by where its setup sheet puts the board (off by 5 cm and 5° here), and the
/// result and its touch check are as good as with the asymmetric board.
#[test]
fn a_symmetric_board_is_labelled_live_by_the_setup_sheet() {
    let name = "sim-checkerboard-2x12";
    let tmp = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(dataset(name).join("scene.json")).unwrap();
    let mut scene: serde_json::Value = serde_json::from_str(&text).unwrap();
    scene["board"]["inner_corners"] = serde_json::json!([8, 6]);
    let scene_file = tmp.path().join("scene.json");
    std::fs::write(&scene_file, serde_json::to_string_pretty(&scene).unwrap()).unwrap();
    let (_dir, result_file, summaries, result) = run_auto(&Run {
        dataset: name,
        scene: Some(scene_file),
        coordinator_args: &[],
        board_off: Some(Isometry3::from_parts(
            Translation3::new(0.04, -0.03, 0.0),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, 5f64.to_radians())),
        )),
        count: 20,
        min_good: 16,
        method: "board",
    });
    for robot in ["robot1", "robot2"] {
        let used = result.captures.used.get(robot).copied().unwrap_or(0);
        assert!(
            used >= 14,
            "{robot}: only {used} captures used ({summaries:?}); rejected: {:?}",
            result.captures.rejected
        );
    }
    let (err, angle) = common::truth_error(&dataset(name), &result);
    eprintln!(
        "symmetric board live: {:.3} mm, {:.4} deg from the truth; predicted p95 {:.3} mm",
        err * 1e3,
        angle.to_degrees(),
        result.predicted_touch_error_m.p95 * 1e3
    );
    // A labelling chosen the wrong way on either arm turns base1_from_base2 by
    // 180° about the board normal: metres, not millimetres. Measured 0.60 mm
    // (the README's figure; asserted within 1.5x).
    assert!(err < 0.9e-3, "{err} m from the truth");
    let (printout, v) = common::verify(
        &result_file,
        &dataset(name).join("touch_points.csv"),
        &["--tip-sigma-mm", "0.3"],
    );
    eprintln!("{printout}");
    let mean_mm = v["touch_mean_mm"].as_f64().unwrap();
    // Measured 0.82 mm (README), asserted within 1.5x.
    assert!(mean_mm < 1.2, "touch mean {mean_mm} mm");
}

/// A camera that reports its intrinsics slightly wrong (a factory calibration off by
/// 1% in focal length and 2 px in the centre; the images are rendered through the
/// true ones, `reported_camera` in the scene): `coordinator run --refine-intrinsics`
/// refines them with the hand-eyes and base-to-base from what the agents publish.
/// Without it the hand-eyes absorb the error (millimetres along the optical axis).
#[test]
fn slightly_wrong_reported_intrinsics_are_refined_live() {
    let name = "sim-checkerboard-2x12";
    let tmp = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(dataset(name).join("scene.json")).unwrap();
    let mut scene: serde_json::Value = serde_json::from_str(&text).unwrap();
    for robot in scene["robots"].as_array_mut().unwrap() {
        let mut reported = robot["camera"].clone();
        for (key, change) in [("fx", 1.01), ("fy", 1.01)] {
            reported[key] = (reported[key].as_f64().unwrap() * change).into();
        }
        for (key, shift) in [("cx", 2.0), ("cy", -2.0)] {
            reported[key] = (reported[key].as_f64().unwrap() + shift).into();
        }
        robot["reported_camera"] = reported;
    }
    let scene_file = tmp.path().join("scene.json");
    std::fs::write(&scene_file, serde_json::to_string_pretty(&scene).unwrap()).unwrap();
    let mut errors = vec![];
    for args in [&["--refine-intrinsics"][..], &[][..]] {
        let (_dir, _, _, result) = run_auto(&Run {
            dataset: name,
            scene: Some(scene_file.clone()),
            coordinator_args: args,
            board_off: None,
            count: 20,
            min_good: 16,
            method: "board",
        });
        let (err, angle) = common::truth_error(&dataset(name), &result);
        let truth = b2b_dataset::load_ground_truth(&dataset(name))
            .unwrap()
            .unwrap();
        // The hand-eyes take what the intrinsics get wrong: a focal length 1% long
        // puts every board 1% further along the optical axis.
        let hand_eye: f64 = ["robot1", "robot2"]
            .iter()
            .map(|r| {
                let est = result.hand_eye[*r].to_isometry("hand_eye").unwrap();
                (truth.flange_from_camera[*r].inverse() * est)
                    .translation
                    .vector
                    .norm()
            })
            .fold(0.0, f64::max);
        eprintln!(
            "reported intrinsics off, coordinator {args:?}: base1_from_base2 {:.3} mm, {:.4} deg \
             from the truth; hand-eyes up to {:.3} mm",
            err * 1e3,
            angle.to_degrees(),
            hand_eye * 1e3
        );
        errors.push((err, hand_eye));
    }
    // Measured: base1_from_base2 0.54-0.57 mm from the truth refined, 0.57-0.59 mm
    // not (the two arms see one board, so a scale error of both cameras mostly
    // cancels); the hand-eyes 0.56 mm refined, 4.8 mm not.
    assert!(errors[0].0 < 0.85e-3, "refined: {:?}", errors[0]);
    assert!(
        errors[1].1 > 2.0 * errors[0].1,
        "hand-eyes not refined {:?}, refined {:?}",
        errors[1],
        errors[0]
    );
}

/// A camera that reports no intrinsics at all (`reports_intrinsics: false` in the
/// scene: the frames carry zeros, as from a camera without a factory
/// calibration). Each agent detects with a guess until it has five views, then
/// fits the camera to its captures' corners and refines it with its hand-eye
/// after every capture; the captures say their intrinsics are estimated, and
/// the coordinator fits each camera again from all of them and refines it
/// jointly with the hand-eyes and the bases. The coordinator is given the
/// simulated arms' accuracy, so its covariance must hold the truth.
#[test]
fn cameras_without_intrinsics_are_calibrated_from_the_routine() {
    let name = "sim-checkerboard-2x12";
    let tmp = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(dataset(name).join("scene.json")).unwrap();
    let mut scene: serde_json::Value = serde_json::from_str(&text).unwrap();
    let mut truth_fx = vec![];
    for robot in scene["robots"].as_array_mut().unwrap() {
        truth_fx.push(robot["camera"]["fx"].as_f64().unwrap());
        robot["reports_intrinsics"] = false.into();
    }
    let scene_file = tmp.path().join("scene.json");
    std::fs::write(&scene_file, serde_json::to_string_pretty(&scene).unwrap()).unwrap();
    let (_dir, result_file, summaries, result) = run_auto(&Run {
        dataset: name,
        scene: Some(scene_file),
        coordinator_args: &[
            "--robot-accuracy-mm",
            "0.3",
            "--robot-accuracy-deg",
            "0.015",
        ],
        board_off: None,
        count: 24,
        min_good: 20,
        method: "board",
    });
    // Each agent's own estimate, made during its routine ("robotN: camera
    // estimated (...): fx F fy ..."): good enough to plan and label with.
    for (summary, truth) in summaries.iter().zip(&truth_fx) {
        let fx: f64 = summary
            .split("camera estimated")
            .nth(1)
            .and_then(|t| t.split("fx ").nth(1))
            .and_then(|t| t.split(' ').next())
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("no camera estimate in {summary}"));
        // The agent's provisional estimate, from the captures its live routine
        // happened to take (they move with the machine's load): measured 0.14-0.51
        // px off, asserted within 1.5x of the worst (a gate run on a busy machine
        // had 0.51 px).
        assert!((fx - truth).abs() < 0.765, "agent: fx {fx} against {truth}");
    }
    // "camera robotN: fx F fy ...: ESTIMATED from K images (...)", one per robot.
    for (robot, truth) in ["robot1", "robot2"].iter().zip(&truth_fx) {
        let w = result
            .warnings
            .iter()
            .find(|w| w.starts_with(&format!("camera {robot}:")) && w.contains("ESTIMATED"))
            .unwrap_or_else(|| panic!("no estimated camera for {robot}: {:?}", result.warnings));
        let fx: f64 = w
            .split("fx ")
            .nth(1)
            .and_then(|t| t.split(' ').next())
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("no fx in {w}"));
        eprintln!("{w}");
        eprintln!("{robot}: fx {fx:.2} against the true {truth:.2}");
        // Measured 0.14-0.27 px off (README), asserted within 1.5x of 0.3 px.
        assert!(
            (fx - truth).abs() < 0.45,
            "{robot}: fx {fx} against {truth}"
        );
    }
    let (err, angle) = common::truth_error(&dataset(name), &result);
    eprintln!(
        "no intrinsics given: base1_from_base2 {:.3} mm, {:.4} deg from the truth; predicted \
         touch error p95 {:.3} mm",
        err * 1e3,
        angle.to_degrees(),
        result.predicted_touch_error_m.p95 * 1e3
    );
    let truth = b2b_dataset::load_ground_truth(&dataset(name))
        .unwrap()
        .unwrap()
        .base1_from_base2
        .unwrap();
    let m2 = common::truth_m2(&result, "robot1", "robot2", &truth);
    eprintln!("no intrinsics given: the truth at Mahalanobis² {m2:.2}");
    assert!(m2 < common::CHI2_6_999, "the truth at Mahalanobis² {m2}");
    let (printout, v) = common::verify(
        &result_file,
        &dataset(name).join("touch_points.csv"),
        &["--tip-sigma-mm", "0.3"],
    );
    eprintln!("{printout}");
    let mean_mm = v["touch_mean_mm"].as_f64().unwrap();
    let inside = v["within_predicted_p95"].as_f64().unwrap();
    // Measured 0.48 mm from the truth, touch mean 0.74 mm, all 25 touches inside
    // the bound (README), asserted within 1.5x.
    assert!(err < 0.72e-3, "{err} m from the truth");
    assert!(mean_mm < 1.11, "touch mean {mean_mm} mm");
    assert!(
        inside >= 0.9,
        "{inside} of the touches inside the predicted bound"
    );
}

/// Three carts, each its own `agent auto --sim` on the three-cart scene
/// (`datasets/sim-checkerboard-3x12`), and `coordinator run --robots
/// robot1,robot2,robot3`: every base in robot 1's, each against the truth, and
/// every pair verified against its touch file.
///
/// The coordinator is given the simulated arms' accuracy (their DH errors come
/// to about 0.3 mm and 0.015 deg at the flange), as an operator gives an arm's
/// (`--robot-accuracy-mm/-deg`): without it the covariance leaves out an error
/// no residual shows (docs/accuracy.md, Mahalanobis² 50 offline).
#[test]
fn three_carts_run_the_automatic_routine() {
    let name = "sim-checkerboard-3x12";
    let (_dir, result_file, _, result) = run_auto_carts(
        &Run {
            dataset: name,
            scene: None,
            coordinator_args: &[
                "--robot-accuracy-mm",
                "0.3",
                "--robot-accuracy-deg",
                "0.015",
            ],
            board_off: None,
            count: 20,
            min_good: 16,
            method: "board",
        },
        &["robot1", "robot2", "robot3"],
    );
    assert_eq!(result.reference.as_deref(), Some("robot1"));
    assert_eq!(
        result.bases.keys().collect::<Vec<_>>(),
        ["robot2", "robot3"]
    );
    let truth = b2b_dataset::load_ground_truth(&dataset(name))
        .unwrap()
        .unwrap();
    let true_base = |k: usize| truth.base1_from_base(k).unwrap();
    // Measured (README): robot2's base 0.54-0.57 mm from the truth, robot3's
    // 0.37-0.56 mm; asserted within 1.5x of 0.6 and 0.5 mm.
    for (k, (robot, measured_mm)) in [("robot2", 0.6), ("robot3", 0.5)].into_iter().enumerate() {
        let est = result.bases[robot]
            .ref_from_base
            .to_isometry("base")
            .unwrap();
        let d = true_base(k + 2).inverse() * est;
        let mm = d.translation.vector.norm() * 1e3;
        eprintln!(
            "live, three carts: {robot}'s base {mm:.3} mm, {:.4} deg from the truth",
            d.rotation.angle().to_degrees()
        );
        assert!(
            mm < 1.5 * measured_mm,
            "{robot}: base {mm} mm from the truth"
        );
    }
    // Each pair's covariance against the truth.
    for (a, b) in [(1, 2), (1, 3), (2, 3)] {
        let (ra, rb) = (format!("robot{a}"), format!("robot{b}"));
        let m2 = common::truth_m2(&result, &ra, &rb, &(true_base(a).inverse() * true_base(b)));
        eprintln!("live, three carts, {ra},{rb}: Mahalanobis² of the truth {m2:.2}");
        assert!(
            m2 < common::CHI2_6_999,
            "{ra},{rb}: the truth at Mahalanobis² {m2}"
        );
    }
    // Measured touch means per pair (README), asserted within 1.5x; offline
    // on the dataset's own 12 captures the same touches give 0.513, 0.541 and
    // 0.620 mm.
    // Coverage: one calibration's error is shared by all 25 touches of a pair,
    // so how many fall outside moves together from run to run; the covariance
    // itself is checked above. Each pair must keep at least 80% inside.
    for (pair, file, measured_mm) in [
        ("robot1,robot2", "touch_points.csv", 0.79),
        ("robot1,robot3", "touch_points_robot1_robot3.csv", 0.57),
        ("robot2,robot3", "touch_points_robot2_robot3.csv", 1.02),
    ] {
        let (_, v) = common::verify(
            &result_file,
            &dataset(name).join(file),
            &["--tip-sigma-mm", "0.3", "--pair", pair],
        );
        let mean = v["touch_mean_mm"].as_f64().unwrap();
        let inside = v["within_predicted_p95"].as_f64().unwrap();
        eprintln!(
            "live, three carts, {pair}: touch mean {mean:.3} mm, {inside:.2} inside the bound"
        );
        assert!(mean < 1.5 * measured_mm, "{pair}: touch mean {mean} mm");
        assert!(
            inside >= 0.8,
            "{pair}: {inside} of the touches inside the bound"
        );
    }
}
