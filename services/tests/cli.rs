//! The binaries as operators use them: exit codes, one-line errors, no panics.

mod common;
use common::state_beside;

use std::path::Path;
use std::process::Command;

fn agent() -> Command {
    Command::new(env!("CARGO_BIN_EXE_agent"))
}

fn coordinator() -> Command {
    Command::new(env!("CARGO_BIN_EXE_coordinator"))
}

fn fails_cleanly(cmd: &mut Command, needle: &str) {
    let out = cmd.output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "expected failure, got success; stderr: {stderr}"
    );
    assert!(!stderr.contains("panicked"), "panic: {stderr}");
    assert!(
        stderr.contains(needle),
        "stderr does not mention '{needle}': {stderr}"
    );
}

#[test]
fn help_explains_every_command() {
    for (mut cmd, words) in [
        (agent(), vec!["handeye"]),
        (coordinator(), vec!["calibrate", "verify"]),
    ] {
        let out = cmd.arg("--help").output().unwrap();
        assert!(out.status.success());
        let text = String::from_utf8_lossy(&out.stdout);
        for w in words {
            assert!(text.contains(w), "{text}");
        }
    }
}

#[test]
fn missing_dataset_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("nowhere");
    fails_cleanly(
        agent()
            .args(["handeye", "--dataset"])
            .arg(&missing)
            .args(["--robot", "robot1", "--out"])
            .arg(tmp.path().join("h.json")),
        "nowhere",
    );
    fails_cleanly(
        coordinator()
            .args(["calibrate", "--dataset"])
            .arg(&missing)
            .arg("--out")
            .arg(tmp.path().join("r.json"))
            .arg("--state-dir")
            .arg(state_beside(&tmp.path().join("r.json"))),
        "nowhere",
    );
}

#[test]
fn bad_method_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let ds = Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-checkerboard-2x12");
    fails_cleanly(
        agent()
            .args(["handeye", "--dataset"])
            .arg(&ds)
            .args(["--robot", "robot1", "--method", "magic", "--out"])
            .arg(tmp.path().join("h.json")),
        "invalid value 'magic' for '--method <METHOD>'\n  [possible values: tsai, park, horaud, andreff, daniilidis, shah, li, refined]",
    );
    fails_cleanly(
        coordinator()
            .args(["calibrate", "--dataset"])
            .arg(&ds)
            .args(["--method", "magic", "--out"])
            .arg(tmp.path().join("r.json"))
            .arg("--state-dir")
            .arg(state_beside(&tmp.path().join("r.json"))),
        "invalid value 'magic' for '--method <METHOD>'\n  [possible values: board, multimarker, rgbd]",
    );
}

#[test]
fn malformed_result_file_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let result = tmp.path().join("RESULT.json");
    std::fs::write(&result, "{ not json").unwrap();
    let touches = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../datasets/sim-checkerboard-2x12/touch_points.csv");
    fails_cleanly(
        coordinator()
            .args(["verify", "--result"])
            .arg(&result)
            .arg("--touch-points")
            .arg(&touches),
        "RESULT.json",
    );
}

/// `coordinator calibrate` on the committed checkerboard set into `dir`: the
/// dataset folder and the RESULT.json written.
fn calibrate_committed(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let (ds, result, _) = calibrate_bundled(dir, "sim-checkerboard-2x12");
    (ds, result)
}

/// `coordinator calibrate` on the committed set `name` into `dir`: the dataset
/// folder, the RESULT.json written and the printout.
fn calibrate_bundled(dir: &Path, name: &str) -> (std::path::PathBuf, std::path::PathBuf, String) {
    let ds = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../datasets")
        .join(name);
    let (result, printout) = calibrate(dir, &ds);
    (ds, result, printout)
}

/// `coordinator calibrate` on dataset `ds` into `dir`: the RESULT.json written
/// and the printout.
fn calibrate(dir: &Path, ds: &Path) -> (std::path::PathBuf, String) {
    calibrate_with(dir, ds, &[])
}

/// [`calibrate`] with further arguments.
fn calibrate_with(dir: &Path, ds: &Path, args: &[&str]) -> (std::path::PathBuf, String) {
    let result = dir.join("RESULT.json");
    let out = coordinator()
        .args(["calibrate", "--dataset"])
        .arg(ds)
        .args(args)
        .arg("--out")
        .arg(&result)
        .arg("--state-dir")
        .arg(state_beside(&result))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (result, String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The operator is told when the covariance had to be widened beyond what
/// chance gives: on the heavily occluded ChArUco set a few captures carry
/// much of the fit and the captures' spread needs 2.71x in σ (measured;
/// asserted within 1.5x), where 19 captures give about 1.58x by chance.
#[test]
fn calibrate_says_when_the_covariance_was_widened_beyond_chance() {
    let tmp = tempfile::tempdir().unwrap();
    let (_, _, printout) = calibrate_bundled(tmp.path(), "sim-charuco-occluded-2x10");
    let line = printout
        .lines()
        .find_map(|l| l.strip_prefix("covariance widened by up to "))
        .unwrap_or_else(|| panic!("no widening line: {printout}"));
    let factor: f64 = line.split("x in σ").next().unwrap().parse().unwrap();
    assert!((2.71 / 1.5..2.71 * 1.5).contains(&factor), "{line}");
    assert!(
        line.contains("beyond the about 1.58x chance gives with 19"),
        "{line}"
    );
}

#[test]
fn calibrate_then_verify_writes_conforming_files() {
    let tmp = tempfile::tempdir().unwrap();
    let (ds, result, printout) = calibrate_bundled(tmp.path(), "sim-checkerboard-2x12");
    // Each arm's pose error as the joint fit saw it: the README says 0.08 and
    // 0.07 mm (within 1.5x).
    for robot in ["robot1", "robot2"] {
        let prefix = format!("{robot}: robot pose error as the residuals show it: ");
        let line = printout
            .lines()
            .find_map(|l| l.strip_prefix(prefix.as_str()))
            .unwrap_or_else(|| panic!("no pose error line for {robot}: {printout}"));
        let mm: f64 = line.split(" mm").next().unwrap().parse().unwrap();
        assert!((0.067 / 1.5..0.082 * 1.5).contains(&mm), "{robot}: {line}");
    }
    // The rendered set's robot noise is of a shape the model has: the
    // captures' spread needs no widening beyond chance (1.07x in σ against
    // 1.51x, README; within 1.5x), and the operator is told so.
    let line = printout
        .lines()
        .find_map(|l| {
            l.strip_prefix(
                "covariance: the captures' own spread fits the noise model (widened by up to ",
            )
        })
        .unwrap_or_else(|| panic!("no spread line: {printout}"));
    let factor: f64 = line.split("x in σ").next().unwrap().parse().unwrap();
    assert!((1.0..1.07 * 1.5).contains(&factor), "{line}");
    assert!(line.contains("about 1.51x with 24 captures"), "{line}");
    // The model selection: the default kept (the rendered arms err in shapes
    // the noise model has), every candidate's held-out figure printed.
    let line = printout
        .lines()
        .find(|l| l.starts_with("estimator: "))
        .unwrap_or_else(|| panic!("no estimator line: {printout}"));
    assert!(
        line.starts_with("estimator: refined (")
            && line.contains("park ")
            && line.contains("shah "),
        "{line}"
    );
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    assert_eq!(written["model_selection"]["chosen"], "refined", "{written}");
    let json = tmp.path().join("VERIFY.json");
    // `coordinator verify` of the result against the set's touches, with
    // `tip` (mm) given, expecting exit status `code`; its printout.
    let verify = |tip: &str, code: i32| {
        let out = coordinator()
            .args(["verify", "--tip-sigma-mm", tip, "--result"])
            .arg(&result)
            .arg("--touch-points")
            .arg(ds.join("touch_points.csv"))
            .arg("--json")
            .arg(&json)
            .output()
            .unwrap();
        assert_eq!(
            out.status.code(),
            Some(code),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    // Without the tips' noise the touches see the result off by more than its
    // covariance allows: FAIL (exit status 4) by design.
    let printout = verify("0", 4);
    assert!(
        printout.lines().last().unwrap_or_default().starts_with(
            "VERDICT: FAIL the touches see the result off by more than its covariance allows"
        ),
        "{printout}"
    );
    let r: b2b_protocol::CalibrationResult =
        serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    r.validate().unwrap();
    let v: b2b_protocol::VerifyReport =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v.n, 25);
    // Every capture the fit saw is in the result with its RMS and viewing
    // direction, so a report from RESULT.json alone has its per-capture panels
    // (issue 16).
    let per = &r.captures.per_capture;
    for robot in ["robot1", "robot2"] {
        let mine: Vec<_> = per.iter().filter(|c| c.robot == robot).collect();
        let used = r.captures.used[robot];
        assert!(
            mine.len() >= used,
            "{robot}: {} fits for {used} used captures",
            mine.len()
        );
        assert_eq!(
            mine.iter()
                .filter(|c| c.rms_px.is_some_and(|e| e > 0.0 && e < 2.0))
                .count(),
            used,
            "{robot}: {mine:?}"
        );
        for c in &mine {
            let n = c.view_direction.iter().map(|x| x * x).sum::<f64>().sqrt();
            assert!((n - 1.0).abs() < 1e-9, "{c:?}");
        }
    }
    // The touches against the result's error model, with the set's tip noise
    // (0.2 mm) given: the result's error as the touches see it fits its
    // covariance (p = 0.04), but the touches scatter about it by about 0.199 mm
    // per axis per arm beyond the tips (README; within 1.5x): the simulated
    // arms' DH errors at the touch poses.
    let printout = verify("0.2", 0);
    let v: b2b_protocol::VerifyReport =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let check = v.bound_check.expect("the touch check in the JSON");
    assert_eq!((check.offset_dof, check.scatter_dof), (6, 69), "{check:?}");
    assert!(
        (0.005..0.2).contains(&check.offset_p)
            && !check.offset_beyond_chance
            && check.scatter_p < 0.005
            && check.scatter_beyond_chance,
        "{check:?}"
    );
    assert!(
        (0.199 / 1.5..0.199 * 1.5).contains(&check.scatter_sigma_mm),
        "{check:?}"
    );
    assert!(
        printout.contains("each touch carries about")
            && printout.contains("which no base calibration removes")
            && !printout.contains("the result is off by more than its covariance allows"),
        "{printout}"
    );
    let inputs = b2b_report::ReportInputs::from_files(&result, Some(&json)).unwrap();
    assert_eq!(
        inputs
            .captures
            .iter()
            .filter(|c| c.rms_px.is_some())
            .count(),
        r.captures.used.values().sum::<usize>()
    );
    inputs.validate().unwrap();
}

/// `coordinator calibrate` on the committed three-robot set: every base in
/// robot 1's base, the pair without it, and `verify --pair` for each pair
/// against its own touch file; pairs the result does not hold, and robots it
/// does not know, are named.
#[test]
fn three_robots_calibrate_and_every_pair_verifies() {
    let tmp = tempfile::tempdir().unwrap();
    let (ds, result, printout) = calibrate_bundled(tmp.path(), "sim-checkerboard-3x12");
    // Every base and the pair without the reference are printed.
    for name in ["T_robot1_robot2", "T_robot1_robot3", "T_robot2_robot3"] {
        assert!(printout.contains(name), "{name}: {printout}");
    }
    let r: b2b_protocol::CalibrationResult =
        serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    r.validate().unwrap();
    assert_eq!(r.reference.as_deref(), Some("robot1"));
    assert_eq!(r.bases.keys().collect::<Vec<_>>(), ["robot2", "robot3"]);
    // The first two robots' fields are robot 2's base.
    assert_eq!(r.bases["robot2"].ref_from_base, r.base1_from_base2);
    assert_eq!(r.bases["robot2"].covariance, r.covariance);
    assert_eq!(r.hand_eye.len(), 3);
    // With the touch mean the README gives for each pair (mm).
    for (pair, file, readme_mm) in [
        (None, "touch_points.csv", 0.513),
        (Some("robot1,robot2"), "touch_points.csv", 0.513),
        (
            Some("robot1,robot3"),
            "touch_points_robot1_robot3.csv",
            0.541,
        ),
        (
            Some("robot2,robot3"),
            "touch_points_robot2_robot3.csv",
            0.620,
        ),
    ] {
        // Each touch: tip noise 0.2 mm plus the robot's own positioning error.
        let mut extra = vec!["--tip-sigma-mm", "0.3"];
        extra.extend(pair.map(|p| ["--pair", p]).into_iter().flatten());
        let (_, v) = common::verify(&result, &ds.join(file), &extra);
        let mean = v["touch_mean_mm"].as_f64().unwrap();
        let inside = v["within_predicted_p95"].as_f64().unwrap();
        eprintln!("{pair:?}: touch mean {mean:.3} mm, {inside:.2} within the predicted p95");
        assert_eq!(v["n"].as_u64(), Some(25), "{pair:?}");
        // Within 1.5x of the README's figure for this pair.
        assert!(mean < 1.5 * readme_mm, "{pair:?}: {mean} mm");
        assert!(inside >= 0.8, "{pair:?}: {inside}");
    }
    // The pair turned round: robot 2's touches in robot 3's base.
    let swapped = tmp.path().join("touch_points_robot3_robot2.csv");
    let text = std::fs::read_to_string(ds.join("touch_points_robot2_robot3.csv")).unwrap();
    let mut lines = text.lines();
    let mut swapped_text = format!("{}\n", lines.next().unwrap());
    for line in lines {
        let v: Vec<&str> = line.split(',').collect();
        let n = v.len();
        let (head, tips) = v.split_at(n - 6);
        let row: Vec<&str> = head
            .iter()
            .chain(&tips[3..])
            .chain(&tips[..3])
            .copied()
            .collect();
        swapped_text.push_str(&row.join(","));
        swapped_text.push('\n');
    }
    std::fs::write(&swapped, swapped_text).unwrap();
    let (_, v) = common::verify(&result, &swapped, &["--pair", "robot3,robot2"]);
    assert!(v["touch_mean_mm"].as_f64().unwrap() < 0.93, "{v}");
    fails_cleanly(
        coordinator()
            .args(["verify", "--result"])
            .arg(&result)
            .arg("--touch-points")
            .arg(ds.join("touch_points.csv"))
            .args(["--pair", "robot1,robot9"]),
        "robot9",
    );
    fails_cleanly(
        coordinator()
            .args(["verify", "--result"])
            .arg(&result)
            .arg("--touch-points")
            .arg(ds.join("touch_points.csv"))
            .args(["--pair", "robot1"]),
        "two robot ids",
    );
}

/// `coordinator calibrate` on robots that do not all see one target: robot 3
/// sees only a second board and is placed through robot 2, which sees both;
/// without robot 2's views of it, robot 3 is named as cut off.
#[test]
fn robots_seeing_different_targets_calibrate_or_are_named_cut_off() {
    let tmp = tempfile::tempdir().unwrap();
    let linked = tmp.path().join("linked");
    b2b_sim::pose_only::write_two_targets(&linked, 41, true).unwrap();
    // The generated pose-only set's noise gives a predicted p95 of 4-8 mm,
    // above the default tolerance (2 mm: exit status 4); the graph is what
    // is tested here.
    let (result, printout) = calibrate_with(tmp.path(), &linked, &["--tolerance-mm", "10"]);
    for name in ["T_robot1_robot2", "T_robot1_robot3", "T_robot2_robot3"] {
        assert!(printout.contains(name), "{name}: {printout}");
    }
    let r: b2b_protocol::CalibrationResult =
        serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    r.validate().unwrap();
    assert_eq!(r.bases.keys().collect::<Vec<_>>(), ["robot2", "robot3"]);
    let cut = tmp.path().join("cut");
    b2b_sim::pose_only::write_two_targets(&cut, 41, false).unwrap();
    fails_cleanly(
        coordinator()
            .args(["calibrate", "--dataset"])
            .arg(&cut)
            .arg("--out")
            .arg(tmp.path().join("CUT.json"))
            .arg("--state-dir")
            .arg(state_beside(&result)),
        "robot3 cannot be placed in robot1's base",
    );
    assert!(!tmp.path().join("CUT.json").exists());
}

/// `calibrate --method rgbd --hand-eye`: hand-eyes from earlier `agent handeye` runs
/// replace the dataset's target; the result carries them, and misuse is named.
#[test]
fn rgbd_with_hand_eye_files() {
    let tmp = tempfile::tempdir().unwrap();
    let ds = Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-rgbd-boxes-2x5");
    let mut files = vec![];
    for robot in ["robot1", "robot2"] {
        let f = tmp.path().join(format!("HANDEYE-{robot}.json"));
        let out = agent()
            .args(["handeye", "--robot", robot, "--dataset"])
            .arg(&ds)
            .arg("--out")
            .arg(&f)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        files.push(f);
    }
    let result = tmp.path().join("RESULT.json");
    let calibrate = |method: &str, hand_eyes: &[&std::path::PathBuf]| {
        let mut cmd = coordinator();
        cmd.args(["calibrate", "--method", method, "--dataset"])
            .arg(&ds);
        for f in hand_eyes {
            cmd.arg("--hand-eye").arg(f);
        }
        cmd.arg("--out").arg(&result);
        cmd.arg("--state-dir").arg(state_beside(&result));
        cmd
    };
    let out = calibrate("rgbd", &[&files[1], &files[0]]).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: b2b_protocol::CalibrationResult =
        serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    assert_eq!(r.method, "rgbd");
    let he: b2b_protocol::HandEyeResult =
        serde_json::from_str(&std::fs::read_to_string(&files[0]).unwrap()).unwrap();
    for i in 0..3 {
        assert!((r.hand_eye["robot1"].t[i] - he.flange_from_camera.t[i]).abs() < 1e-12);
    }
    // Each view's fit is in the result, so its report draws every panel.
    assert_eq!(r.captures.per_capture.len(), 10, "{:?}", r.captures);
    let inputs = b2b_report::ReportInputs::from_files(&result, None).unwrap();
    inputs.validate().unwrap();
    let report_dir = tempfile::tempdir().unwrap();
    let written = b2b_report::write_report(&inputs, report_dir.path()).unwrap();
    let html = std::fs::read_to_string(&written.index).unwrap();
    assert!(!html.contains("No per-capture details"), "{html}");
    // One robot's file only: the missing robot is named.
    fails_cleanly(&mut calibrate("rgbd", &[&files[0]]), "robot2");
    // The same robot twice.
    fails_cleanly(
        &mut calibrate("rgbd", &[&files[0], &files[0]]),
        "a second hand-eye for robot 'robot1'",
    );
    // Hand-eye files with a target method.
    fails_cleanly(
        &mut calibrate("board", &[&files[0]]),
        "--hand-eye is for --method rgbd",
    );
}

/// A copy of a dataset with every robot's `camera` block deleted from
/// `dataset.json`.
fn without_camera(dir: &Path) -> tempfile::TempDir {
    let tmp = tempfile::tempdir().unwrap();
    common::copy_dir(dir, tmp.path());
    let text = std::fs::read_to_string(dir.join("dataset.json")).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    for robot in json["robots"].as_array_mut().unwrap() {
        assert!(robot.as_object_mut().unwrap().remove("camera").is_some());
    }
    std::fs::write(tmp.path().join("dataset.json"), json.to_string()).unwrap();
    tmp
}

/// Datasets without intrinsics: `coordinator calibrate` and `agent handeye`
/// estimate them, say so, and write their results; the RGB-D method refuses.
#[test]
fn calibrate_and_handeye_without_intrinsics() {
    let ds = without_camera(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-checkerboard-2x12"),
    );
    let out_dir = tempfile::tempdir().unwrap();
    let result = out_dir.path().join("RESULT.json");
    let out = coordinator()
        .args(["calibrate", "--dataset"])
        .arg(ds.path())
        .arg("--out")
        .arg(&result)
        .arg("--state-dir")
        .arg(state_beside(&result))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{stdout}");
    assert!(
        stdout.contains("camera robot1") && stdout.contains("ESTIMATED"),
        "{stdout}"
    );
    let r: b2b_protocol::CalibrationResult =
        serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    r.validate().unwrap();
    fails_cleanly(
        coordinator()
            .args(["calibrate", "--method", "rgbd", "--dataset"])
            .arg(ds.path())
            .arg("--out")
            .arg(out_dir.path().join("rgbd.json"))
            .arg("--state-dir")
            .arg(state_beside(&out_dir.path().join("rgbd.json"))),
        "no camera intrinsics",
    );

    let visp = without_camera(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/datasets/visp-franka-eye-in-hand"),
    );
    let he = out_dir.path().join("HANDEYE.json");
    let out = agent()
        .args(["handeye", "--robot", "robot1", "--dataset"])
        .arg(visp.path())
        .arg("--out")
        .arg(&he)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("ESTIMATED from 8 images"), "{stdout}");
    // The arm's pose error as the fit saw it: the README says 2.6 mm here
    // (within 1.5x).
    let noise = stdout
        .lines()
        .find_map(|l| l.strip_prefix("robot pose error as the residuals show it: "))
        .unwrap_or_else(|| panic!("no robot pose error line: {stdout}"));
    let mm: f64 = noise.split(" mm").next().unwrap().parse().unwrap();
    eprintln!("ViSP without intrinsics: {noise}");
    assert!((2.6 / 1.5..2.6 * 1.5).contains(&mm), "{noise}");
    let h: b2b_protocol::HandEyeResult =
        serde_json::from_str(&std::fs::read_to_string(&he).unwrap()).unwrap();
    assert_eq!(h.per_capture.len(), 8);
}

/// Logs written to a pipe or a file carry no terminal colour codes (they did: a
/// log file full of `ESC[2m`).
#[test]
fn logs_to_a_pipe_have_no_colour_codes() {
    // Without intrinsics, calibrate logs (info) the camera it estimated.
    let ds = without_camera(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-checkerboard-2x12"),
    );
    // The result goes beside the dataset: an output inside it is refused.
    let out_dir = tempfile::tempdir().unwrap();
    let result = out_dir.path().join("RESULT.json");
    let out = coordinator()
        .env("RUST_LOG", "info")
        .args(["calibrate", "--dataset"])
        .arg(ds.path())
        .arg("--out")
        .arg(&result)
        .arg("--state-dir")
        .arg(state_beside(&result))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("INFO"), "no log lines to check: {stderr}");
    assert!(
        !stderr.contains('\u{1b}'),
        "colour codes in a piped log: {stderr}"
    );
}

/// A touch file whose `location` column repeats locations: `verify` reports ISO 9283
/// AP and RP per location, printed and in its JSON (the committed touches, each
/// touched twice).
#[test]
fn verify_reports_iso_9283_for_repeated_locations() {
    let tmp = tempfile::tempdir().unwrap();
    let (ds, result) = calibrate_committed(tmp.path());
    let text = std::fs::read_to_string(ds.join("touch_points.csv")).unwrap();
    let mut lines = text.lines();
    let mut csv = format!("location,{}\n", lines.next().unwrap());
    let rows: Vec<&str> = lines.filter(|l| !l.trim().is_empty()).collect();
    for (k, row) in rows.iter().enumerate() {
        csv.push_str(&format!("point {k},{row}\npoint {k},{row}\n"));
    }
    let touches = tmp.path().join("touch_points.csv");
    std::fs::write(&touches, csv).unwrap();
    let json = tmp.path().join("VERIFY.json");
    let out = coordinator()
        .args(["verify", "--result"])
        .arg(&result)
        .arg("--touch-points")
        .arg(&touches)
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    // No tip noise given: the touch check fails the verdict by design (exit
    // status 4, as the touches without their tips' noise in
    // `calibrate_then_verify_writes_conforming_files`); the ISO 9283 figures
    // are printed and written all the same.
    assert_eq!(
        out.status.code(),
        Some(4),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("ISO 9283, location point 0 (2 touches): AP "),
        "{stdout}"
    );
    let v: b2b_protocol::VerifyReport =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v.iso9283.len(), rows.len());
    for l in &v.iso9283 {
        // Both touches of a location are the same row: no spread, and the accuracy
        // is that row's touch error.
        assert!(l.repeatability_mm.abs() < 1e-9, "{l:?}");
        assert!(
            l.accuracy_mm > 0.0 && l.accuracy_mm < v.touch_max_mm + 1e-9,
            "{l:?}"
        );
    }
}

/// A result whose covariance has positive variances but is not positive
/// semi-definite (tx and ty correlated beyond 1) is refused by `verify`, which
/// would otherwise report touches "within" an imaginary bound.
#[test]
fn verify_refuses_a_covariance_that_is_not_positive_semi_definite() {
    let tmp = tempfile::tempdir().unwrap();
    let (ds, result) = calibrate_committed(tmp.path());
    let mut json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    let c = &mut json["covariance"];
    let cross = 2.0 * (c[3][3].as_f64().unwrap() * c[4][4].as_f64().unwrap()).sqrt();
    c[3][4] = cross.into();
    c[4][3] = cross.into();
    let forged = tmp.path().join("FORGED.json");
    std::fs::write(&forged, serde_json::to_string_pretty(&json).unwrap()).unwrap();
    let out = coordinator()
        .args(["verify", "--result"])
        .arg(&forged)
        .arg("--touch-points")
        .arg(ds.join("touch_points.csv"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("covariance") && stderr.contains("not positive semi-definite"),
        "{stderr}"
    );
}

/// One easy_handeye2 sample: `robot` and `tracking` as tf gives them.
fn easy_handeye_sample(
    base_from_flange: &nalgebra::Isometry3<f64>,
    camera_from_target: &nalgebra::Isometry3<f64>,
) -> String {
    let block = |name: &str, p: &nalgebra::Isometry3<f64>| {
        let (t, q) = (p.translation.vector, p.rotation.coords);
        format!(
            "  {name}:\n    translation:\n      x: {:?}\n      y: {:?}\n      z: {:?}\n    \
             rotation:\n      x: {:?}\n      y: {:?}\n      z: {:?}\n      w: {:?}\n",
            t.x, t.y, t.z, q.x, q.y, q.z, q.w
        )
    };
    let robot = block("robot", base_from_flange);
    format!(
        "- {}{}",
        robot.trim_start(),
        block("tracking", camera_from_target)
    )
}

/// A small rigid motion, uniform in each axis within `t` (m) and `r` (rad), from
/// a xorshift state.
fn jitter(state: &mut u64, t: f64, r: f64) -> nalgebra::Isometry3<f64> {
    let mut next = || {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        (*state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    let v = nalgebra::Vector3::new(next() * t, next() * t, next() * t);
    let w = nalgebra::Vector3::new(next() * r, next() * r, next() * r);
    nalgebra::Isometry3::from_parts(v.into(), nalgebra::UnitQuaternion::from_scaled_axis(w))
}

/// One MoveIt Calibration sample: two 4x4 matrices, row-major.
fn moveit_sample(
    base_from_flange: &nalgebra::Isometry3<f64>,
    camera_from_target: &nalgebra::Isometry3<f64>,
) -> String {
    let rows = |p: &nalgebra::Isometry3<f64>| {
        let m = p.to_homogeneous();
        (0..4)
            .flat_map(|i| (0..4).map(move |j| format!("{:?}", m[(i, j)])))
            .collect::<Vec<_>>()
            .join(", ")
    };
    format!(
        "- effector_wrt_world: [{}]\n  object_wrt_sensor: [{}]\n",
        rows(base_from_flange),
        rows(camera_from_target)
    )
}

#[test]
fn easy_handeye_samples_are_imported_and_calibrated() {
    use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
    let tmp = tempfile::tempdir().unwrap();
    // The truth: a camera on the flange, a board on the table.
    let flange_from_camera = Isometry3::from_parts(
        Translation3::new(0.03, -0.02, 0.08),
        UnitQuaternion::from_euler_angles(0.05, -0.1, 1.5),
    );
    let base_from_target = Isometry3::from_parts(
        Translation3::new(0.6, -0.1, 0.0),
        UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.3),
    );
    let centre = base_from_target * Point3::new(0.1, 0.0625, 0.0);
    let mut samples = String::from(
        "parameters:\n  name: cell\n  calibration_type: eye_in_hand\n  robot_base_frame: base\n\
         samples:\n",
    );
    let mut moveit = String::new();
    let mut rng = 0x2545_f491_4f6c_dd1d_u64;
    for k in 0..12 {
        let a = k as f64 * std::f64::consts::TAU / 12.0;
        let eye =
            centre + Vector3::new(0.25 * a.cos(), 0.25 * a.sin(), 0.45 + 0.03 * (k % 3) as f64);
        let base_from_camera =
            b2b_calib::pose::look_at(&eye, &centre, &Vector3::z(), 0.2 * (k % 4) as f64 - 0.3);
        // What the arm and the tracker report: each off by a little, as real
        // samples are (about 0.05 mm / 0.01° and 0.1 mm / 0.02°).
        let base_from_flange =
            base_from_camera * flange_from_camera.inverse() * jitter(&mut rng, 5e-5, 1.7e-4);
        let camera_from_target =
            base_from_camera.inverse() * base_from_target * jitter(&mut rng, 1e-4, 3.5e-4);
        samples += &easy_handeye_sample(&base_from_flange, &camera_from_target);
        moveit += &moveit_sample(&base_from_flange, &camera_from_target);
    }
    let file = tmp.path().join("cell.samples");
    std::fs::write(&file, samples).unwrap();
    let target = tmp.path().join("target.json");
    std::fs::write(
        &target,
        r#"{"kind": "checkerboard", "inner_corners": [9, 6], "square_m": 0.025}"#,
    )
    .unwrap();
    let camera = tmp.path().join("camera.json");
    std::fs::write(
        &camera,
        r#"{"width": 640, "height": 480, "fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0, "dist": [0, 0, 0, 0, 0]}"#,
    )
    .unwrap();
    let dataset = tmp.path().join("imported");
    // `coordinator import FORMAT FILE` of `robot` into the dataset.
    let import = |format: &str, samples: &Path, robot: &str| {
        let mut cmd = coordinator();
        cmd.args(["import", format])
            .arg(samples)
            .args(["--robot", robot, "--target"])
            .arg(&target)
            .arg("--camera")
            .arg(&camera)
            .arg("--out")
            .arg(&dataset);
        cmd
    };
    let out = import("--easy-handeye", &file, "robot1").output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("robot1: 12 samples imported"));
    // A second robot joins the same dataset; the first one is never replaced.
    assert!(
        import("--easy-handeye", &file, "robot2")
            .status()
            .unwrap()
            .success()
    );
    fails_cleanly(
        &mut import("--easy-handeye", &file, "robot1"),
        "robot `robot1` is already in the dataset",
    );
    // The same samples as MoveIt Calibration saves them, for a third arm.
    let moveit_file = tmp.path().join("moveit.yaml");
    std::fs::write(&moveit_file, &moveit).unwrap();
    let out = import("--moveit", &moveit_file, "robot3").output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The imported rows calibrate to the truth: the directions of both transforms
    // are the ones tf gave, in both formats.
    for robot in ["robot2", "robot3"] {
        let he = tmp.path().join(format!("HANDEYE-{robot}.json"));
        let out = agent()
            .args(["handeye", "--dataset"])
            .arg(&dataset)
            .args(["--robot", robot, "--out"])
            .arg(&he)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let text = std::fs::read_to_string(&he).unwrap();
        let result: b2b_protocol::HandEyeResult =
            serde_json::from_str(&text).unwrap_or_else(|e| panic!("{robot}: {e}: {text}"));
        let x = result.flange_from_camera.to_isometry("x").unwrap();
        let d = flange_from_camera.inverse() * x;
        eprintln!(
            "{robot}: imported hand-eye {:.3} mm, {:.4} deg from the truth",
            d.translation.vector.norm() * 1e3,
            d.rotation.angle().to_degrees()
        );
        // A direction taken the wrong way round misses by centimetres and tens
        // of degrees; the noise above leaves 0.25 mm / 0.008° (the README's
        // figures, asserted within 1.5x).
        assert!(d.translation.vector.norm() < 0.375e-3, "{robot}: {d}");
        assert!(d.rotation.angle() < 0.012f64.to_radians(), "{robot}: {d}");
    }
    // A matrix that is not a rigid transform is refused by name.
    let sheared = moveit.replacen(
        "effector_wrt_world: [",
        "effector_wrt_world: [1.5, 0, 0, 0, ",
        1,
    );
    let sheared = sheared.replacen(", 0.0, 0.0, 0.0, 1.0]", "]", 0);
    let bad_moveit = tmp.path().join("bad-moveit.yaml");
    std::fs::write(&bad_moveit, sheared).unwrap();
    fails_cleanly(
        &mut import("--moveit", &bad_moveit, "robot4"),
        "[0].effector_wrt_world",
    );

    // An eye-on-base file is refused by name; so is a rotation that is not one.
    let eob = tmp.path().join("eob.samples");
    std::fs::write(
        &eob,
        std::fs::read_to_string(&file)
            .unwrap()
            .replace("eye_in_hand", "eye_on_base"),
    )
    .unwrap();
    fails_cleanly(
        &mut import("--easy-handeye", &eob, "robot3"),
        "`eye_on_base`: only eye-in-hand samples",
    );
    let text = std::fs::read_to_string(&file).unwrap();
    let at = text.find("    rotation:\n      x: ").unwrap() + "    rotation:\n      x: ".len();
    let rest = text[at..].split_once('\n').unwrap().1;
    let bad = format!("{}7.0\n{rest}", &text[..at]);
    let bad_file = tmp.path().join("bad.samples");
    std::fs::write(&bad_file, bad).unwrap();
    fails_cleanly(
        &mut import("--easy-handeye", &bad_file, "robot3"),
        "samples[0].robot",
    );
}

/// `calibrate` and `verify` end with their verdict against the tolerance: PASS
/// on the committed set at the default (2 mm), FAIL with exit status 4 and the
/// reason at a tolerance the result cannot meet (flag or environment); the
/// verdict is in RESULT.json, which still conforms to the interface.
#[test]
fn calibrate_and_verify_end_with_a_verdict() {
    let tmp = tempfile::tempdir().unwrap();
    let (ds, result, printout) = calibrate_bundled(tmp.path(), "sim-checkerboard-2x12");
    let last = printout.lines().last().unwrap_or_default();
    assert!(
        last.starts_with("VERDICT: PASS (predicted p95 touch error ")
            && last.ends_with("within the tolerance of 2.00 mm)"),
        "{printout}"
    );
    let r: b2b_protocol::CalibrationResult =
        serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    let v = r.verdict.expect("the verdict in RESULT.json");
    assert!(
        v.pass && v.tolerance_mm == 2.0 && v.reasons.is_empty(),
        "{v:?}"
    );
    if let Ok(out) = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/tools/check_result.py"))
        .arg(&result)
        .output()
        && !String::from_utf8_lossy(&out.stderr).contains("numpy")
    {
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stdout)
        );
    }
    // A tolerance below the predicted p95: FAIL, exit status 4, the file written.
    let strict = tmp.path().join("STRICT.json");
    for (flag, env) in [(Some("0.1"), None), (None, Some("0.1"))] {
        let mut cmd = coordinator();
        cmd.args(["calibrate", "--dataset"])
            .arg(&ds)
            .arg("--out")
            .arg(&strict)
            .arg("--state-dir")
            .arg(state_beside(&strict));
        if let Some(t) = flag {
            cmd.args(["--tolerance-mm", t]);
        }
        if let Some(t) = env {
            cmd.env("B2B_TOLERANCE_MM", t);
        }
        let out = cmd.output().unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert_eq!(out.status.code(), Some(4), "{stdout}");
        let last = stdout.lines().last().unwrap_or_default();
        assert!(
            last.starts_with("VERDICT: FAIL predicted p95 touch error of T_base1_base2 ")
                && last.ends_with("mm is above the tolerance of 0.10 mm"),
            "{stdout}"
        );
        let r: b2b_protocol::CalibrationResult =
            serde_json::from_str(&std::fs::read_to_string(&strict).unwrap()).unwrap();
        assert!(!r.verdict.unwrap().pass);
    }
    fails_cleanly(
        coordinator()
            .args(["calibrate", "--dataset"])
            .arg(&ds)
            .arg("--out")
            .arg(&strict)
            .env("B2B_TOLERANCE_MM", "two"),
        "B2B_TOLERANCE_MM",
    );
    // verify: the touches against the tolerance.
    let json = tmp.path().join("VERIFY.json");
    let verify = |tolerance: &str| {
        coordinator()
            .args([
                "verify",
                "--tip-sigma-mm",
                "0.3",
                "--tolerance-mm",
                tolerance,
            ])
            .arg("--result")
            .arg(&result)
            .arg("--touch-points")
            .arg(ds.join("touch_points.csv"))
            .arg("--json")
            .arg(&json)
            .output()
            .unwrap()
    };
    let out = verify("2");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}");
    assert!(
        stdout
            .lines()
            .last()
            .unwrap_or_default()
            .starts_with("VERDICT: PASS (touch error p95 "),
        "{stdout}"
    );
    let out = verify("0.1");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(4), "{stdout}");
    assert!(
        stdout
            .lines()
            .last()
            .unwrap_or_default()
            .starts_with("VERDICT: FAIL the touches' p95 error "),
        "{stdout}"
    );
    let v: b2b_protocol::VerifyReport =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert!(!v.verdict.unwrap().pass);
}
