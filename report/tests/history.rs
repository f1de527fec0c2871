//! What the report makes of the coordinator's history and of a result's warnings:
//! each cart's hand-eye over time (offsets from its first), and the warnings in a
//! red box at the top of the page.

use std::path::{Path, PathBuf};

use b2b_protocol::Pose;
use b2b_report::{HandEyeHistoryEntry, ReportInputs, write_report};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn entry(robot: &str, minute: i64, pose: &Isometry3<f64>) -> HandEyeHistoryEntry {
    HandEyeHistoryEntry {
        robot: robot.into(),
        recorded_at_unix_ms: 1_700_000_000_000 + minute * 60_000,
        recorded_at: format!("day one, minute {minute}"),
        flange_from_camera: Pose::from_isometry(pose),
    }
}

/// The numbers after `from its first hand-eye` tooltips' robot and time, in
/// document order: "ROBOT day one, minute M: V UNIT".
fn tooltip_values(svg: &str, robot: &str) -> Vec<f64> {
    svg.split(&format!("<title>{robot} day one, minute "))
        .skip(1)
        .map(|rest| {
            let v = rest.split(": ").nth(1).unwrap();
            let number: String = v
                .chars()
                .take_while(|c| c.is_ascii_digit() || *c == '.')
                .collect();
            number.parse().unwrap()
        })
        .collect()
}

#[test]
fn the_history_plots_each_carts_hand_eye_as_offsets_from_its_first() {
    let mut inputs = ReportInputs::from_files(&fixture("RESULT.json"), None).unwrap();
    let x = Isometry3::new(Vector3::new(0.05, -0.02, 0.1), Vector3::new(0.1, 0.2, -0.3));
    // The mount moved by 3 mm along the flange's x and turned 1 degree about the
    // camera's own origin: the camera's origin moves by exactly 3 mm.
    let turn = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 1f64.to_radians());
    let moved = Isometry3::from_parts(
        Translation3::from(x.translation.vector + Vector3::new(0.003, 0.0, 0.0)),
        turn * x.rotation,
    );
    // Recorded out of order: the report sorts by time.
    inputs.hand_eye_history = vec![
        entry("robot1", 90, &moved),
        entry("robot1", 0, &x),
        entry("robot1", 30, &x),
        entry("robot2", 10, &x),
    ];
    inputs.history_source = Some("state/history.sqlite".into());
    let dir = tempfile::tempdir().unwrap();
    let files = write_report(&inputs, dir.path()).unwrap();
    let names: Vec<String> = files
        .plots
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert!(
        names.contains(&"hand_eye_history_mm.svg".to_owned())
            && names.contains(&"hand_eye_history_deg.svg".to_owned()),
        "{names:?}"
    );
    let mm = std::fs::read_to_string(dir.path().join("hand_eye_history_mm.svg")).unwrap();
    let deg = std::fs::read_to_string(dir.path().join("hand_eye_history_deg.svg")).unwrap();
    // In time order, from the first (minute 0) of that robot.
    let t = tooltip_values(&mm, "robot1");
    assert_eq!(t.len(), 3, "{mm}");
    assert_eq!(&t[..2], &[0.0, 0.0]);
    assert!((t[2] - 3.0).abs() < 1e-3, "{t:?}");
    let r = tooltip_values(&deg, "robot1");
    assert!(r[0] == 0.0 && (r[2] - 1.0).abs() < 1e-3, "{r:?}");
    // robot2's single hand-eye is its own first.
    assert_eq!(tooltip_values(&mm, "robot2"), [0.0]);
    // 90 minutes of history read in minutes, from the earliest record.
    assert!(mm.contains("minutes since day one, minute 0"), "{mm}");
    assert!(
        mm.contains("robot1 (3)") && mm.contains("robot2 (1)"),
        "{mm}"
    );
    let html = std::fs::read_to_string(&files.index).unwrap();
    assert!(html.contains("src=\"hand_eye_history_mm.svg\""));
    assert!(
        html.contains("History: 4 recorded hand-eyes of robot1, robot2 from state/history.sqlite")
    );
    assert!(!html.contains("No hand-eye history given"));

    // Without a history: no history plots, and the page says what would draw them.
    inputs.hand_eye_history.clear();
    let again = tempfile::tempdir().unwrap();
    let files = write_report(&inputs, again.path()).unwrap();
    assert!(
        files
            .plots
            .iter()
            .all(|p| !p.to_string_lossy().contains("hand_eye_history")),
        "{:?}",
        files.plots
    );
    let html = std::fs::read_to_string(&files.index).unwrap();
    assert!(html.contains("No hand-eye history given"), "{html}");
}

#[test]
fn a_bad_pose_in_the_history_is_refused_by_robot_and_time() {
    let mut inputs = ReportInputs::from_files(&fixture("RESULT.json"), None).unwrap();
    let mut e = entry("robot2", 5, &Isometry3::identity());
    e.flange_from_camera.q = [0.0, 0.0, 0.0, 2.0];
    inputs.hand_eye_history.push(e);
    let dir = tempfile::tempdir().unwrap();
    let err = write_report(&inputs, dir.path()).unwrap_err().to_string();
    assert!(
        err.contains("hand-eye history of robot2 at day one, minute 5"),
        "{err}"
    );
}

#[test]
fn warnings_head_the_page_escaped() {
    let mut inputs = ReportInputs::from_files(&fixture("RESULT.json"), None).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let html = std::fs::read_to_string(write_report(&inputs, dir.path()).unwrap().index).unwrap();
    assert!(!html.contains("class=\"alert\""), "no warnings, no box");

    inputs.result.warnings = vec![
        "camera mount moved? re-check before surgery: robot2 <moved>".into(),
        "second warning".into(),
    ];
    let html = std::fs::read_to_string(write_report(&inputs, dir.path()).unwrap().index).unwrap();
    let alert = html.find("class=\"alert\"").expect("a warnings box");
    // Above everything else: before the cards and the numbers.
    assert!(alert < html.find("class=\"cards\"").unwrap());
    assert!(
        html.contains("<li>camera mount moved? re-check before surgery: robot2 &lt;moved&gt;</li>")
    );
    assert!(html.contains("<li>second warning</li>"));
}
