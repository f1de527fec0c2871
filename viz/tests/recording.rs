//! Writes a recording through every `log_*` call to a temporary `.rrd`, decodes
//! it with [`b2b_viz::summarize_rrd`] (the decoder rerun itself uses,
//! `re_log_encoding`, re-exported by the SDK) and checks that each documented entity is there with the archetype and
//! timelines the crate documentation promises.

use b2b_protocol::Pose;
use b2b_protocol::messages::{BoardObservation, Capture, Intrinsics};
use b2b_protocol::{
    CalibrationResult, CaptureSummary, PredictedError, RESULT_FORMAT, RejectedCapture, Timings,
};
use b2b_viz::{
    Base, ImageView, PixelFormat, Recorder, Touch, depth_to_points, paths, summarize_rrd,
};
use nalgebra::{Isometry3, Point3, Vector3};

fn camera() -> Intrinsics {
    Intrinsics {
        width: 64,
        height: 48,
        fx: 60.0,
        fy: 60.0,
        cx: 32.0,
        cy: 24.0,
        dist: vec![0.01, -0.02, 0.0, 0.0, 0.0],
        estimated: false,
    }
}

fn capture(index: u64, rejected: bool) -> Capture {
    let camera_from_target = Isometry3::new(Vector3::new(-0.05, -0.03, 0.5), Vector3::zeros());
    let target_points: Vec<[f64; 3]> = (0..6)
        .map(|i| [0.02 * (i % 3) as f64, 0.02 * (i / 3) as f64, 0.0])
        .collect();
    let observation = BoardObservation {
        pixels: target_points
            .iter()
            .map(|p| {
                [
                    60.0 * (p[0] - 0.05) / 0.5 + 32.3,
                    60.0 * (p[1] - 0.03) / 0.5 + 23.8,
                ]
            })
            .collect(),
        target_points,
        camera_from_target: Pose::from_isometry(&camera_from_target),
        residuals_px: vec![0.3; 6],
        rms_px: 0.3 + index as f64 * 0.01,
        target_centre: None,
        target: None,
    };
    Capture {
        index,
        controller_time_s: Some(1.7e9 + index as f64),
        image: Some(format!("images/{index:03}.png")),
        base_from_flange: Pose::from_isometry(&Isometry3::new(
            Vector3::new(0.5, 0.1 * index as f64, 0.4),
            Vector3::new(3.0, 0.0, 0.1 * index as f64),
        )),
        camera: camera(),
        observation: (!rejected).then_some(observation),
        rejected: rejected.then(|| "board not found".to_owned()),
        base_from_target: None,
        features: None,
    }
}

fn result() -> CalibrationResult {
    let mut cov = [[0.0; 6]; 6];
    for (i, row) in cov.iter_mut().enumerate() {
        row[i] = if i < 3 { 1e-8 } else { 1e-8 * (i as f64) };
    }
    CalibrationResult {
        format: RESULT_FORMAT.into(),
        method: "board".into(),
        base1_from_base2: Pose::from_isometry(&Isometry3::new(
            Vector3::new(1.0, 0.05, 0.0),
            Vector3::new(0.0, 0.0, 3.1),
        )),
        covariance: cov,
        predicted_touch_error_m: PredictedError {
            mean: 1.6e-4,
            p95: 3.3e-4,
        },
        hand_eye: [
            (
                "robot1".to_owned(),
                Pose::from_isometry(&Isometry3::translation(0.0, 0.06, 0.03)),
            ),
            (
                "robot2".to_owned(),
                Pose::from_isometry(&Isometry3::translation(0.0, -0.07, 0.04)),
            ),
        ]
        .into(),
        captures: CaptureSummary {
            used: [("robot1".to_owned(), 2), ("robot2".to_owned(), 2)].into(),
            rejected: vec![RejectedCapture {
                robot: "robot1".into(),
                image: Some("images/002.png".into()),
                row: Some(3),
                reason: "board not found".into(),
            }],
            per_capture: Vec::new(),
        },
        timings_ms: Timings::default(),
        reference: Some("robot1".into()),
        bases: Default::default(),
        pairs: Vec::new(),
        hand_eye_covariance: Default::default(),
        warnings: Vec::new(),
        findings: Vec::new(),
        verdict: None,
        model_selection: None,
    }
}

#[test]
fn a_recording_holds_every_documented_entity() {
    let dir = tempfile::tempdir().unwrap();
    let rrd = dir.path().join("run.rrd");
    let rec = Recorder::save("b2b_test", &rrd).unwrap();
    assert!(rec.is_enabled());

    rec.log_base(Base::One, &Isometry3::identity()).unwrap();
    let board: Vec<[f64; 3]> = (0..6).map(|i| [0.02 * i as f64, 0.0, 0.0]).collect();
    rec.log_target(&Isometry3::translation(0.6, 0.0, 0.0), &board)
        .unwrap();
    let gray = vec![128u8; 64 * 48];
    let bgr = vec![30u8; 64 * 48 * 3];
    for (base, robot) in [(Base::One, "robot1"), (Base::Two, "robot2")] {
        rec.log_hand_eye(base, &Isometry3::translation(0.0, 0.05, 0.03), &camera())
            .unwrap();
        for i in 0..3 {
            let c = capture(i, robot == "robot1" && i == 2);
            rec.log_capture(base, &c).unwrap();
            let image = match base {
                Base::One => ImageView {
                    pixels: &gray,
                    width: 64,
                    height: 48,
                    format: PixelFormat::Gray,
                },
                Base::Two => ImageView {
                    pixels: &bgr,
                    width: 64,
                    height: 48,
                    format: PixelFormat::Bgr,
                },
            };
            rec.log_image(base, image).unwrap();
            let depth = vec![700u16; 64 * 48];
            let cloud = depth_to_points(&depth, 64, 48, &camera(), 1e-3, 8).unwrap();
            rec.log_depth_points(base, &cloud).unwrap();
        }
    }
    let result = result();
    rec.log_result(&result, ["robot1", "robot2"], 100.0)
        .unwrap();
    let base1_from_base2 = result.base1_from_base2.to_isometry("T").unwrap();
    let touches: Vec<Touch> = (1..=4)
        .map(|row| {
            let tip1 = Point3::new(0.5, 0.1 * row as f64, 0.2);
            let tip2 =
                base1_from_base2.inverse() * (tip1 + Vector3::new(0.0002 * row as f64, 0.0, 0.0));
            Touch {
                row,
                tip1_in_base1: tip1,
                tip2_in_base2: tip2,
                bound95_m: 4e-4,
            }
        })
        .collect();
    rec.log_touches(&base1_from_base2, &touches).unwrap();
    rec.finish().unwrap();

    let entities = summarize_rrd(&rrd).unwrap();
    if std::env::var_os("B2B_PRINT_ENTITIES").is_some() {
        for (path, e) in &entities {
            eprintln!(
                "{path}: {} rows, {:?}, {:?}",
                e.rows, e.timelines, e.components
            );
        }
        eprintln!("size {} bytes", std::fs::metadata(&rrd).unwrap().len());
    }
    let expect = |path: &str, component: &str| {
        let e = entities
            .get(path)
            .unwrap_or_else(|| panic!("{path} missing; have {:?}", entities.keys()));
        assert!(
            e.components.iter().any(|c| c.starts_with(component)),
            "{path}: no {component} among {:?}",
            e.components
        );
        e
    };
    expect(paths::WORLD, "ViewCoordinates:");
    expect(&paths::base(Base::One), "Transform3D:");
    expect(&paths::base(Base::Two), "Transform3D:");
    expect(&paths::base(Base::Two), "TransformAxes3D:");
    expect(paths::TARGET, "Transform3D:");
    expect(paths::TARGET_POINTS, "Points3D:positions");
    expect(paths::UNCERTAINTY, "Ellipsoids3D:half_sizes");
    // What does not change over a run is static (visible on every timeline).
    for path in [
        paths::TARGET,
        paths::UNCERTAINTY,
        paths::TOUCHES,
        paths::SUMMARY,
    ] {
        assert_eq!(entities[path].rows, 0, "{path} should be static");
    }
    assert_eq!(entities[&paths::base(Base::Two)].rows, 0);
    expect(paths::TOUCHES, "Points3D:colors");
    expect(paths::TOUCH_ERRORS, "LineStrips3D:strips");
    expect(paths::SUMMARY, "TextDocument:text");
    let errors = expect(paths::TOUCH_ERROR_MM, "Scalars:scalars");
    assert!(errors.timelines.contains("touch"), "{errors:?}");
    assert_eq!(errors.rows, 4);
    expect(paths::TOUCH_BOUND_MM, "Scalars:scalars");
    for base in [Base::One, Base::Two] {
        let flange = expect(&paths::flange(base), "Transform3D:");
        assert!(
            flange.timelines.contains("capture") && flange.timelines.contains("time"),
            "{flange:?}"
        );
        assert_eq!(flange.rows, 3, "one flange pose per capture");
        expect(&paths::flange_trail(base), "LineStrips3D:strips");
        expect(&paths::camera(base), "Transform3D:");
        expect(&paths::image(base), "Pinhole:image_from_camera");
        let image = expect(&paths::image(base), "Image:buffer");
        assert!(image.timelines.contains("capture"));
        expect(&paths::depth(base), "Points3D:positions");
        expect(&paths::log(base), "TextLog:text");
        let rms = expect(&paths::rms(base), "Scalars:scalars");
        let detected = expect(&paths::detected(base), "Points2D:positions");
        expect(&paths::reprojected(base), "Points2D:positions");
        expect(&paths::residuals(base), "LineStrips2D:strips");
        // Robot 1 had one rejected capture of three: two observations, one count.
        let good = if base == Base::One { 2 } else { 3 };
        assert_eq!(rms.rows, good, "{base:?} rms rows");
        assert_eq!(detected.rows, good, "{base:?} detected rows");
    }
    expect(&paths::rejected(Base::One), "Scalars:scalars");
    assert!(
        !entities.contains_key(&paths::rejected(Base::Two)),
        "robot 2 rejected nothing"
    );
}

#[test]
fn a_bad_viewer_address_is_refused_and_a_disabled_recorder_still_validates() {
    assert!(Recorder::connect("b2b_test", "not a url").is_err());
    // Reading back something that is not a recording is an error naming the file.
    let dir = tempfile::tempdir().unwrap();
    let junk = dir.path().join("junk.rrd");
    std::fs::write(&junk, b"not a recording").unwrap();
    let err = summarize_rrd(&junk).unwrap_err().to_string();
    assert!(err.contains("junk.rrd"), "{err}");
    let rec = Recorder::disabled();
    rec.log_capture(Base::One, &capture(0, false)).unwrap();
    let mut bad = capture(1, false);
    bad.base_from_flange.q = [0.0, 0.0, 0.0, 3.0];
    assert!(rec.log_capture(Base::One, &bad).is_err());
    rec.finish().unwrap();
}

#[test]
fn streaming_to_a_viewer_that_is_not_there_does_not_hang() {
    // Nothing listens on port 9 (discard) here: logging must not block and
    // finishing must return (with an error or not) well inside its timeout.
    let start = std::time::Instant::now();
    let rec = Recorder::connect("b2b_test", "rerun+http://127.0.0.1:9/proxy").unwrap();
    rec.log_capture(Base::One, &capture(0, false)).unwrap();
    let finished = rec.finish();
    let took = start.elapsed();
    eprintln!("finish without a viewer: {finished:?} after {took:?}");
    assert!(
        took < b2b_viz::FINISH_TIMEOUT + std::time::Duration::from_secs(5),
        "{took:?}"
    );
}
