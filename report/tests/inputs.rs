//! Loading the report's inputs (errors name the file and what is wrong) and what
//! the page contains for richer or poorer inputs.

use std::path::{Path, PathBuf};

use b2b_protocol::messages::{BoardObservation, Capture, Intrinsics};
use b2b_protocol::{
    CalibrationResult, CaptureResidual, CaptureSummary, HANDEYE_FORMAT, HandEyeResult, Pose,
    Timings,
};
use b2b_report::{CaptureDetail, ReportError, ReportInputs, TouchDetail, write_report};
use nalgebra::{Isometry3, Vector3};

use b2b_errors::chain;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

#[test]
fn missing_and_malformed_files_are_named_in_the_error() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.json");
    let err = ReportInputs::from_files(&missing, None).unwrap_err();
    assert!(matches!(err, ReportError::Read { .. }));
    assert!(err.to_string().contains("nope.json"), "{err}");

    let broken = dir.path().join("RESULT.json");
    std::fs::write(
        &broken,
        "{\n  \"format\": \"b2b-result/1\",\n  \"method\": 3\n}",
    )
    .unwrap();
    let err = ReportInputs::from_files(&broken, None).unwrap_err();
    let msg = chain(&err);
    assert!(
        msg.contains("RESULT.json") && msg.contains("line 3"),
        "{msg}"
    );

    // A quaternion that is not a rotation: the file and the field are named.
    let text = std::fs::read_to_string(fixture("RESULT.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["T_base1_base2"]["q"] = serde_json::json!([0.0, 0.0, 0.0, 2.0]);
    std::fs::write(&broken, v.to_string()).unwrap();
    let msg = chain(&ReportInputs::from_files(&broken, None).unwrap_err());
    assert!(
        msg.contains("RESULT.json") && msg.contains("T_base1_base2.q"),
        "{msg}"
    );

    // A verify report with a share outside [0, 1].
    let verify = dir.path().join("VERIFY.json");
    let text = std::fs::read_to_string(fixture("VERIFY.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["within_predicted_p95"] = serde_json::json!(96.0);
    std::fs::write(&verify, v.to_string()).unwrap();
    let msg = chain(&ReportInputs::from_files(&fixture("RESULT.json"), Some(&verify)).unwrap_err());
    assert!(
        msg.contains("VERIFY.json") && msg.contains("within_predicted_p95"),
        "{msg}"
    );
}

#[test]
fn a_result_alone_gives_the_numbers_and_says_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let inputs = ReportInputs::from_files(&fixture("RESULT.json"), None).unwrap();
    let files = write_report(&inputs, dir.path()).unwrap();
    let names: Vec<String> = files
        .plots
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    // The fixture has two rejected captures: only their plot can be drawn.
    assert_eq!(names, ["rejections.svg"]);
    let html = std::fs::read_to_string(&files.index).unwrap();
    // The translation of the fixture, in mm, and both rejection reasons.
    assert!(html.contains("1039.835"), "translation x missing");
    assert!(html.contains("board not found") && html.contains("board pose ambiguous"));
    assert!(html.contains("No per-capture details"));
    assert!(html.contains("No verify report"));
    for name in &names {
        assert!(html.contains(&format!("src=\"{name}\"")));
    }
}

#[test]
fn richer_inputs_add_plots_and_the_output_is_deterministic() {
    let mut inputs =
        ReportInputs::from_files(&fixture("RESULT.json"), Some(&fixture("VERIFY.json"))).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let files = write_report(&inputs, dir.path()).unwrap();
    // The verify summary alone draws the touch summary plot.
    assert_eq!(files.plots.len(), 2);
    let html = std::fs::read_to_string(&files.index).unwrap();
    assert!(html.contains("96%"), "within-bound share missing");
    // The fixture is of an older version, without the touch check: nothing
    // about it is drawn.
    assert!(!html.contains("against its covariance"));

    let he = HandEyeResult {
        format: HANDEYE_FORMAT.into(),
        robot: "robot1".into(),
        method: "park+refine".into(),
        flange_from_camera: Pose::IDENTITY,
        covariance: [[0.0; 6]; 6],
        base_from_target: None,
        reprojection_rms_px: 0.2,
        per_capture: (0..5)
            .map(|i| CaptureResidual {
                image: format!("images/{i:03}.png"),
                rms_px: Some(0.1 + 0.01 * i as f64),
                outlier_corners: i,
            })
            .collect(),
        captures: CaptureSummary::default(),
        timings_ms: Timings::default(),
    };
    let he_path = dir.path().join("HANDEYE.json");
    std::fs::write(&he_path, serde_json::to_string(&he).unwrap()).unwrap();
    inputs.add_hand_eye_file(&he_path).unwrap();
    assert_eq!(inputs.captures.len(), 5);
    // Adding it twice merges by image, it does not duplicate.
    inputs.add_hand_eye_file(&he_path).unwrap();
    assert_eq!(inputs.captures.len(), 5);

    let camera_from_target = Isometry3::new(Vector3::new(0.0, 0.0, 0.5), Vector3::zeros());
    let capture = Capture {
        index: 7,
        controller_time_s: None,
        image: Some("images/007.png".into()),
        base_from_flange: Pose::IDENTITY,
        camera: Intrinsics {
            width: 640,
            height: 480,
            fx: 600.0,
            fy: 600.0,
            cx: 320.0,
            cy: 240.0,
            dist: vec![],
            estimated: false,
        },
        observation: Some(BoardObservation {
            target_points: vec![[0.0; 3]; 4],
            pixels: vec![[0.0; 2]; 4],
            camera_from_target: Pose::from_isometry(&camera_from_target),
            residuals_px: vec![0.1; 4],
            rms_px: 0.1,
            target_centre: None,
            target: None,
        }),
        rejected: None,
        base_from_target: None,
        features: None,
    };
    let detail = CaptureDetail::from_capture("robot2", &capture).unwrap();
    // The camera is 0.5 m in front of the board: seen from the board, it is at -z.
    let d = detail.view_direction.unwrap();
    assert!((d[2] + 1.0).abs() < 1e-12, "{d:?}");
    inputs.captures.push(detail);
    inputs.touches = (1..=6)
        .map(|row| TouchDetail {
            row,
            error_m: 2e-4 * row as f64,
            bound95_m: 1.1e-3,
        })
        .collect();
    let files = write_report(&inputs, dir.path()).unwrap();
    assert_eq!(files.plots.len(), 6, "{:?}", files.plots);
    let touch_svg = std::fs::read_to_string(dir.path().join("touch_errors.svg")).unwrap();
    // Only row 6 (1.2 mm) is over its 1.1 mm bound.
    assert_eq!(touch_svg.matches("(over)").count(), 1);
    assert!(touch_svg.contains("inside (5/6)"));
    let first = std::fs::read_to_string(&files.index).unwrap();
    let again = tempfile::tempdir().unwrap();
    let files2 = write_report(&inputs, again.path()).unwrap();
    assert_eq!(first, std::fs::read_to_string(&files2.index).unwrap());
    for p in &files.plots {
        let name = p.file_name().unwrap();
        assert_eq!(
            std::fs::read(p).unwrap(),
            std::fs::read(again.path().join(name)).unwrap()
        );
    }
}

#[test]
fn bad_details_are_refused_and_names_are_escaped() {
    let mut inputs = ReportInputs::from_files(&fixture("RESULT.json"), None).unwrap();
    inputs.touches.push(TouchDetail {
        row: 4,
        error_m: f64::NAN,
        bound95_m: 1e-3,
    });
    let dir = tempfile::tempdir().unwrap();
    let err = write_report(&inputs, dir.path()).unwrap_err().to_string();
    assert!(err.contains("touch row 4"), "{err}");
    inputs.touches.clear();
    inputs.captures.push(CaptureDetail {
        robot: "robot1".into(),
        index: 0,
        label: None,
        rms_px: Some(0.1),
        outlier_corners: None,
        view_direction: Some([0.0, 0.0, 2.0]),
        rejected: None,
    });
    assert!(write_report(&inputs, dir.path()).is_err());
    inputs.captures.clear();
    inputs.title = "<script>alert(1)</script>".into();
    let files = write_report(&inputs, dir.path()).unwrap();
    let html = std::fs::read_to_string(files.index).unwrap();
    assert!(!html.contains("<script>") && html.contains("&lt;script&gt;"));
}

#[test]
fn a_result_with_its_per_capture_fits_draws_every_capture_panel() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(fixture("RESULT.json")).unwrap();
    let mut result: CalibrationResult = serde_json::from_str(&text).unwrap();
    for robot in ["robot1", "robot2"] {
        for row in 1..=6usize {
            let a = row as f64;
            let d = nalgebra::Vector3::new(0.3 * a.cos(), 0.3 * a.sin(), -1.0).normalize();
            result.captures.per_capture.push(b2b_protocol::CaptureFit {
                robot: robot.into(),
                row,
                image: Some(format!("images/{row:03}.png")),
                rms_px: Some(0.1 + 0.01 * a),
                outlier_corners: row % 2,
                view_direction: [d.x, d.y, d.z],
            });
        }
    }
    let inputs = ReportInputs::new(result);
    inputs.validate().unwrap();
    // Twelve fitted captures, and the fixture's two rejected before the fit.
    assert_eq!(inputs.captures.len(), 14);
    let files = write_report(&inputs, dir.path()).unwrap();
    let html = std::fs::read_to_string(&files.index).unwrap();
    assert!(!html.contains("No per-capture details"), "{html}");
    let names: Vec<String> = files
        .plots
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert!(names.iter().any(|n| n == "residuals.svg"), "{names:?}");
}

/// The touch check of `verify --json` (`bound_check`) is drawn, flagged where
/// beyond chance with what to do; a p-value that is not a probability is
/// refused by name.
#[test]
fn the_touch_check_is_shown_and_checked() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(fixture("VERIFY.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["bound_check"] = serde_json::json!({
        "offset_chi2": 31.5, "offset_dof": 6, "offset_p": 2.0e-5,
        "scatter_chi2": 70.0, "scatter_dof": 69, "scatter_p": 0.44,
        "offset_beyond_chance": true, "scatter_beyond_chance": false,
        "offset_sigma_mm": 0.41, "scatter_sigma_mm": 0.0
    });
    let verify = dir.path().join("VERIFY.json");
    std::fs::write(&verify, v.to_string()).unwrap();
    let inputs = ReportInputs::from_files(&fixture("RESULT.json"), Some(&verify)).unwrap();
    let files = write_report(&inputs, dir.path()).unwrap();
    let html = std::fs::read_to_string(&files.index).unwrap();
    assert!(
        html.contains("the result's offset against its covariance</td><td class=\"warn\">&chi;&sup2; 31.5 on 6 dof")
            && html.contains("against the tip noise</td><td class=\"ok\">")
            && html.contains("these touches suggest about 0.41 mm")
            && !html.contains("beyond the tips' noise"),
        "{html}"
    );
    v["bound_check"]["scatter_p"] = serde_json::json!(1.5);
    std::fs::write(&verify, v.to_string()).unwrap();
    let msg = chain(&ReportInputs::from_files(&fixture("RESULT.json"), Some(&verify)).unwrap_err());
    assert!(
        msg.contains("VERIFY.json") && msg.contains("bound_check.scatter_p"),
        "{msg}"
    );
}

/// The verdict comes first on the page (before the numbers and the
/// warnings), with every reason, and the findings beside it; a result of an
/// older version says it has none.
#[test]
fn the_verdict_and_the_findings_come_first() {
    let dir = tempfile::tempdir().unwrap();
    let mut inputs = ReportInputs::from_files(&fixture("RESULT.json"), None).unwrap();
    let html = std::fs::read_to_string(write_report(&inputs, dir.path()).unwrap().index).unwrap();
    assert!(html.contains("VERDICT: none"), "{html}");
    inputs.result.warnings = vec!["a warning".into()];
    inputs.result.findings = vec![b2b_protocol::Finding {
        kind: "change_point".into(),
        robot: Some("robot1".into()),
        row: Some(7),
        fails: true,
        message: "robot1's captures change at row 7 <of its list>".into(),
    }];
    inputs.result.verdict = Some(b2b_protocol::Verdict {
        pass: false,
        tolerance_mm: 2.0,
        reasons: vec!["robot1's captures change at row 7 <of its list>".into()],
    });
    let html = std::fs::read_to_string(write_report(&inputs, dir.path()).unwrap().index).unwrap();
    let at = |needle: &str| {
        html.find(needle)
            .unwrap_or_else(|| panic!("{needle} missing: {html}"))
    };
    assert!(at("VERDICT: FAIL") < at("a warning"));
    assert!(at("VERDICT: FAIL") < at("<h2>base1_from_base2</h2>"));
    assert!(at("VERDICT: FAIL") < at("Findings"));
    assert!(html.contains("row 7 &lt;of its list&gt;"), "escaped");
    assert!(html.contains("against the tolerance of 2.00 mm"));
}
