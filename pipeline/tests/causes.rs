//! The operator's real mistakes, built from the committed datasets: each is
//! refused by name, or named in the result's findings (and fails its verdict),
//! or held by the result's covariance (the truth's Mahalanobis² at most 22.5).
//! And the real arms' recordings are accused of none of them.

mod common;

use b2b_calib::Iso3;
use b2b_calib::pose::left_difference;
use b2b_calib::refine::{RefineOptions, mahalanobis2};
use b2b_dataset::{Dataset, load_ground_truth};
use b2b_pipeline::causes::{self, DEFAULT_TOLERANCE_MM, kind, result_verdict};
use b2b_pipeline::{B2bMethod, base_to_base_run, observe_robot, screen_observations};
use common::{bundled, copy_dir, shared_dataset};
use nalgebra::{Quaternion, Translation3, UnitQuaternion, Vector3};

/// A copy of a committed dataset in a temporary folder.
fn copy(name: &str) -> (tempfile::TempDir, std::path::PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    copy_dir(&bundled(name), &dir);
    (tmp, dir)
}

/// Rewrites each data row of `robot`'s captures.csv (1-based row, the pose
/// `T_base_flange` of columns tx..qw) with `f`.
fn map_poses(dir: &std::path::Path, robot: &str, f: impl Fn(usize, Iso3) -> Iso3) {
    let csv = dir.join(robot).join("captures.csv");
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    for (row, line) in lines.iter_mut().enumerate().skip(1) {
        let mut cols: Vec<String> = line.split(',').map(str::to_owned).collect();
        let v: Vec<f64> = cols[2..9].iter().map(|c| c.parse().unwrap()).collect();
        let q = UnitQuaternion::from_quaternion(Quaternion::new(v[6], v[3], v[4], v[5]));
        let pose = f(
            row,
            Iso3::from_parts(Translation3::new(v[0], v[1], v[2]), q),
        );
        let (t, q) = (pose.translation.vector, pose.rotation.coords);
        for (k, x) in [t.x, t.y, t.z, q.x, q.y, q.z, q.w].iter().enumerate() {
            cols[2 + k] = format!("{x}");
        }
        *line = cols.join(",");
    }
    std::fs::write(&csv, lines.join("\n") + "\n").unwrap();
}

fn truth(name: &str) -> Iso3 {
    load_ground_truth(&bundled(name))
        .unwrap()
        .unwrap()
        .base1_from_base2
        .unwrap()
}

/// The truth's Mahalanobis² in the result's own covariance.
fn m2(result: &b2b_protocol::CalibrationResult, truth: &Iso3) -> f64 {
    let est = result.base1_from_base2.to_isometry("T").unwrap();
    let cov = nalgebra::Matrix6::from_fn(|i, j| result.covariance[i][j]);
    mahalanobis2(&left_difference(&est, truth), &cov).unwrap()
}

/// The calibration of the dataset in `dir`, or its error as one line.
fn run(dir: &std::path::Path) -> Result<b2b_pipeline::CalibrationRun, String> {
    let ds = Dataset::load(dir).unwrap();
    let method = B2bMethod::default_for(&ds.manifest.target);
    base_to_base_run(&ds, method, &RefineOptions::default())
        .map_err(|e| b2b_pipeline::error_chain(&e))
}

#[test]
fn poses_written_inverted_are_refused_by_name() {
    let (_tmp, dir) = copy("sim-checkerboard-2x12");
    map_poses(&dir, "robot1", |_, p| p.inverse());
    let text = run(&dir).unwrap_err();
    eprintln!("{text}");
    assert!(
        text.contains("robot1's poses look inverted (T_flange_base instead of T_base_flange)"),
        "{text}"
    );
    // The one-robot path (agent handeye) screens the same way.
    let ds = Dataset::load(&dir).unwrap();
    let err = observe_robot(&ds, "robot1").unwrap_err();
    assert!(err.to_string().contains("look inverted"), "{err}");
}

#[test]
fn a_change_mid_run_is_named_with_its_row() {
    let (_tmp, dir) = copy("sim-checkerboard-2x12");
    // From row 7 on, robot1's flange poses are 5 cm off (a tool changed).
    map_poses(&dir, "robot1", |row, p| {
        if row >= 7 {
            Iso3::from_parts(
                Translation3::from(p.translation.vector + Vector3::new(0.05, 0.0, 0.0)),
                p.rotation,
            )
        } else {
            p
        }
    });
    let r = run(&dir).unwrap().result;
    eprintln!("{:#?}", r.findings);
    let found = r
        .findings
        .iter()
        .find(|f| f.kind == kind::CHANGE_POINT)
        .expect("the change is named");
    assert_eq!(found.robot.as_deref(), Some("robot1"));
    assert_eq!(found.row, Some(7));
    assert!(found.message.contains("row 7"), "{}", found.message);
    let v = result_verdict(&r, DEFAULT_TOLERANCE_MM);
    assert!(!v.pass, "{v:?}");
    eprintln!(
        "error {:.1} mm, m² {:.0}",
        (r.base1_from_base2
            .to_isometry("T")
            .unwrap()
            .translation
            .vector
            - truth("sim-checkerboard-2x12").translation.vector)
            .norm()
            * 1e3,
        m2(&r, &truth("sim-checkerboard-2x12"))
    );
}

#[test]
fn a_board_printed_at_another_scale_is_named_with_its_scale() {
    for scale in [1.02, 1.04, 1.10] {
        let (_tmp, dir) = copy("sim-checkerboard-2x12");
        // Declared smaller than printed: the board is `scale` of its declared size.
        let manifest = dir.join("dataset.json");
        let text = std::fs::read_to_string(&manifest).unwrap();
        let text = text.replace(
            "\"square_m\": 0.025",
            &format!("\"square_m\": {}", 0.025 / scale),
        );
        std::fs::write(&manifest, text).unwrap();
        let r = run(&dir).unwrap().result;
        eprintln!(
            "{scale}: {:#?}, m² {:.1}",
            r.findings,
            m2(&r, &truth("sim-checkerboard-2x12"))
        );
        let named: Vec<_> = r
            .findings
            .iter()
            .filter(|f| f.kind == kind::BOARD_SCALE)
            .collect();
        assert!(!named.is_empty(), "{scale}: not named");
        for f in named {
            assert!(
                f.message
                    .contains(&format!("the board measures {scale:.2}")),
                "{scale}: {}",
                f.message
            );
        }
        assert!(!result_verdict(&r, DEFAULT_TOLERANCE_MM).pass);
    }
}

#[test]
fn marker_widths_in_metres_are_refused_by_their_unit() {
    let (_tmp, dir) = copy("sim-multimarker-4x3-2x10");
    let file = dir.join("multimarker.dat");
    let text = std::fs::read_to_string(&file).unwrap();
    std::fs::write(&file, text.replace("\n40.000000\n", "\n0.040000\n")).unwrap();
    let err = match run(&dir) {
        Ok(_) => panic!("widths in metres accepted"),
        Err(e) => e,
    };
    eprintln!("{err}");
    assert!(err.contains("the widths look like metres"), "{err}");
    assert!(err.contains("multimarker.dat"), "{err}");
}

/// The committed sets pass at the default tolerance with no finding that
/// fails them.
#[test]
fn the_committed_sets_pass_at_the_default_tolerance() {
    for name in [
        "sim-checkerboard-2x12",
        "sim-charuco-occluded-2x10",
        "sim-multimarker-4x3-2x10",
    ] {
        let r = run(&bundled(name)).unwrap().result;
        let v = result_verdict(&r, DEFAULT_TOLERANCE_MM);
        eprintln!(
            "{name}: predicted p95 {:.2} mm, findings {:?}, verdict {v:?}",
            r.predicted_touch_error_m.p95 * 1e3,
            r.findings
        );
        assert!(v.pass, "{name}: {v:?}");
    }
}

/// Real arms (ViSP's Franka, Tabb's Denso) are accused of nothing: not
/// inverted, no change mid-run, the board at its declared scale.
#[test]
fn real_arms_are_not_accused() {
    for name in ["visp-franka-eye-in-hand", "tabb-denso-ds1"] {
        let ds = Dataset::load(&shared_dataset(name)).unwrap();
        let obs = observe_robot(&ds, "robot1").unwrap();
        let (screened, _) = screen_observations(&obs, "robot1/captures.csv").unwrap();
        let fit = causes::position_fit(&screened);
        eprintln!("{name}: {fit:#?}");
        let findings = causes::robot_findings(&screened);
        assert!(findings.is_empty(), "{name}: {findings:#?}");
    }
}

/// Edits robot `index`'s camera block in dataset.json.
fn edit_camera(dir: &std::path::Path, f: impl Fn(&mut serde_json::Value)) {
    let manifest = dir.join("dataset.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&manifest).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(&manifest, serde_json::to_string_pretty(&v).unwrap()).unwrap();
}

#[test]
fn intrinsics_that_do_not_fit_the_images_are_named_with_the_images_values() {
    for (what, key, value) in [
        ("fx 10% off", "fx", 615.2 * 1.1),
        ("cx outside the image", "cx", 700.0),
    ] {
        let (_tmp, dir) = copy("sim-checkerboard-2x12");
        edit_camera(&dir, |v| {
            v["robots"][0]["camera"][key] = serde_json::json!(value)
        });
        let r = run(&dir).unwrap().result;
        eprintln!("{what}: {:#?}", r.findings);
        let f = r
            .findings
            .iter()
            .find(|f| f.kind == kind::INTRINSICS)
            .unwrap_or_else(|| panic!("{what}: not named"));
        assert_eq!(f.robot.as_deref(), Some("robot1"), "{what}");
        assert!(
            f.message
                .contains("robot1's intrinsics do not fit its images: its")
                && f.message.contains("views give fx 61"),
            "{what}: {}",
            f.message
        );
        assert!(!result_verdict(&r, DEFAULT_TOLERANCE_MM).pass);
    }
}

/// The two robots' camera blocks swapped (their cameras differ by 0.4% in
/// focal length and 3 px in the principal point): named as swapped, with the
/// values each robot's views give.
#[test]
fn swapped_camera_blocks_are_named() {
    let (_tmp, dir) = copy("sim-checkerboard-2x12");
    edit_camera(&dir, |v| {
        let a = v["robots"][0]["camera"].clone();
        v["robots"][0]["camera"] = v["robots"][1]["camera"].clone();
        v["robots"][1]["camera"] = a;
    });
    let r = run(&dir).unwrap().result;
    let m2 = m2(&r, &truth("sim-checkerboard-2x12"));
    eprintln!("{:#?}, m² {m2:.1}", r.findings);
    let named = r
        .findings
        .iter()
        .find(|f| f.kind == kind::INTRINSICS && f.fails)
        .unwrap_or_else(|| panic!("not named; m² {m2}"));
    assert!(
        named.message.contains(
            "the camera blocks of robot1 and robot2 look swapped: robot1's views give fx 61"
        ),
        "{}",
        named.message
    );
    assert!(!result_verdict(&r, DEFAULT_TOLERANCE_MM).pass);
}

/// The robot folders of robot1 and robot3 swapped (their camera blocks left
/// where they were): the result's `T_robot1_robot3` is then the inverse of
/// what the touch file (columns: robot1's base, robot3's) measures. `verify`
/// names the swap and fails; the same check on the unswapped set says
/// nothing. (Robots 1 and 3 stand at a quarter turn, far from a transform
/// that is its own inverse.)
#[test]
fn robot_folders_swapped_are_named_by_the_touches() {
    let name = "sim-checkerboard-3x12";
    let touches =
        b2b_dataset::read_touch_points(&bundled(name).join("touch_points_robot1_robot3.csv"))
            .unwrap();
    let check = |dir: &std::path::Path| {
        let result = run(dir).unwrap().result;
        let (report, m) =
            b2b_pipeline::verify_pair(&result, Some(("robot1", "robot3")), &touches, 0.3e-3)
                .unwrap();
        let verdict = causes::verify_verdict(&report, &m, DEFAULT_TOLERANCE_MM);
        (report, verdict)
    };
    let (_tmp, good) = copy(name);
    let (report, verdict) = check(&good);
    assert!(report.findings.is_empty(), "{:#?}", report.findings);
    assert!(verdict.pass, "{verdict:?}");

    let (_tmp2, dir) = copy(name);
    let tmp = dir.join("swap");
    std::fs::rename(dir.join("robot1"), &tmp).unwrap();
    std::fs::rename(dir.join("robot3"), dir.join("robot1")).unwrap();
    std::fs::rename(&tmp, dir.join("robot3")).unwrap();
    let (report, verdict) = check(&dir);
    eprintln!("{:#?}", report.findings);
    let named = report
        .findings
        .iter()
        .find(|f| f.kind == kind::SWAPPED_ROBOTS && f.fails)
        .unwrap_or_else(|| panic!("not named: {report:#?}"));
    assert!(
        named
            .message
            .contains("robot1 and robot3 are the other way round"),
        "{}",
        named.message
    );
    assert!(!verdict.pass);
    assert!(verdict.reasons.iter().any(|r| r == &named.message));
}
