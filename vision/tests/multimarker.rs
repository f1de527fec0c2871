//! Multimarker sets: the ARToolKit-style file, and poses from rendered images of the
//! 4x3 sheet and the three-face corner with known `camera_from_target`.

use b2b_calib::camera::CameraModel;
use b2b_vision::multimarker::{MultimarkerConfig, detect_multimarker, multimarker_pose};
use b2b_vision::synth::{PlaneScene, TexturedPlane, render_planes};
use b2b_vision::{GrayImage, MarkerDictionary, VisionError};
use nalgebra::{
    Isometry3, Matrix3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};

const W: u32 = 1280;
const H: u32 = 720;

fn camera() -> CameraModel {
    CameraModel::new(W, H, [900.0, 900.0, 639.5, 359.5], &[]).unwrap()
}

/// ARToolKit5's `multi-barcode-4x3.dat`, as shipped (comments and all).
const GRID_4X3_DAT: &str =
    "# multimarker definition file for ARToolKit (format defined by ARToolKit)
# the number of markers
12

# marker 0
00
40.0
1.0000 0.0000 0.0000 -105.0000
0.0000 1.0000 0.0000 70.0000
0.0000 0.0000 1.0000 0.0000

01
40.0
1.0000 0.0000 0.0000 -35.0000
0.0000 1.0000 0.0000 70.0000
0.0000 0.0000 1.0000 0.0000

02
40.0
1.0000 0.0000 0.0000 35.0000
0.0000 1.0000 0.0000 70.0000
0.0000 0.0000 1.0000 0.0000

03
40.0
1.0000 0.0000 0.0000 105.0000
0.0000 1.0000 0.0000 70.0000
0.0000 0.0000 1.0000 0.0000

04
40.0
1.0000 0.0000 0.0000 -105.0000
0.0000 1.0000 0.0000 0.0000
0.0000 0.0000 1.0000 0.0000

05
40.0
1.0000 0.0000 0.0000 -35.0000
0.0000 1.0000 0.0000 0.0000
0.0000 0.0000 1.0000 0.0000

06
40.0
1.0000 0.0000 0.0000 35.0000
0.0000 1.0000 0.0000 0.0000
0.0000 0.0000 1.0000 0.0000

07
40.0
1.0000 0.0000 0.0000 105.0000
0.0000 1.0000 0.0000 0.0000
0.0000 0.0000 1.0000 0.0000

08
40.0
1.0000 0.0000 0.0000 -105.0000
0.0000 1.0000 0.0000 -70.0000
0.0000 0.0000 1.0000 0.0000

09
40.0
1.0000 0.0000 0.0000 -35.0000
0.0000 1.0000 0.0000 -70.0000
0.0000 0.0000 1.0000 0.0000

10
40.0
1.0000 0.0000 0.0000 35.0000
0.0000 1.0000 0.0000 -70.0000
0.0000 0.0000 1.0000 0.0000

11
40.0
1.0000 0.0000 0.0000 105.0000
0.0000 1.0000 0.0000 -70.0000
0.0000 0.0000 1.0000 0.0000
";

fn same_config(a: &MultimarkerConfig, b: &MultimarkerConfig) {
    assert_eq!(a.markers.len(), b.markers.len());
    for (m, n) in a.markers.iter().zip(&b.markers) {
        assert_eq!(m.id, n.id);
        assert!((m.width_m - n.width_m).abs() < 1e-12);
        for (p, q) in m.corners().iter().zip(n.corners().iter()) {
            assert!((p - q).norm() < 1e-9, "marker {}: {p} vs {q}", m.id);
        }
    }
}

#[test]
fn the_artoolkit_4x3_file_parses_to_the_built_in_grid_and_files_round_trip() {
    let parsed = MultimarkerConfig::parse(GRID_4X3_DAT, "multi-barcode-4x3.dat").unwrap();
    same_config(&parsed, &MultimarkerConfig::grid_4x3());
    assert_eq!(parsed.markers[0].line, 6);
    // Marker 0 is at the top left: its top-left corner is (-125, 90) mm.
    let tl = parsed.corner(0, 0).unwrap();
    assert!((tl - Point3::new(-0.125, 0.09, 0.0)).norm() < 1e-12);
    assert!(parsed.is_planar());
    assert_eq!(parsed.faces().len(), 1);
    for cfg in [
        MultimarkerConfig::grid_4x3(),
        MultimarkerConfig::three_face_corner(),
    ] {
        let back = MultimarkerConfig::parse(&cfg.to_dat(), "round trip").unwrap();
        same_config(&back, &cfg);
    }
    let corner = MultimarkerConfig::three_face_corner();
    assert!(!corner.is_planar());
    assert_eq!(corner.faces().len(), 3);
    // Every marker of the corner faces the open space: its normal has a positive
    // component towards (1, 1, 1), and its corners stay in the positive octant.
    for m in &corner.markers {
        let z = m.set_from_marker.rotation * Vector3::z();
        assert!(z.dot(&Vector3::new(1.0, 1.0, 1.0)) > 0.5);
        for p in m.corners() {
            assert!(p.coords.iter().all(|&v| v >= -1e-12), "{p}");
        }
    }
    // An ARToolKit 2.x centre line before the matrix is skipped.
    let old = "1\n7\n50\n0 0\n1 0 0 10\n0 1 0 20\n0 0 1 30\n";
    let c = MultimarkerConfig::parse(old, "old.dat").unwrap();
    assert_eq!(c.markers[0].id, 7);
    assert!(
        (c.markers[0].set_from_marker.translation.vector - Vector3::new(0.01, 0.02, 0.03)).norm()
            < 1e-12
    );
}

fn file_error(text: &str) -> (usize, String) {
    match MultimarkerConfig::parse(text, "bad.dat") {
        Err(VisionError::MultimarkerFile {
            source_name,
            line,
            reason,
        }) => {
            assert_eq!(source_name, "bad.dat");
            (line, reason)
        }
        other => panic!("expected a file error for {text:?}, got {other:?}"),
    }
}

/// A file that is not a multimarker file at all (a dataset pointing at a
/// system file): the error says so and quotes at most a short excerpt of it.
#[test]
fn a_file_that_is_no_multimarker_file_is_quoted_only_in_excerpt() {
    let text = "root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1:daemon:/usr/sbin:/usr/sbin/nologin\n";
    let (line, reason) = file_error(text);
    assert_eq!(line, 1);
    assert!(reason.contains("number of markers"), "{reason}");
    assert!(
        reason.contains("found \"root:x:0:0:root:/root:/b…\""),
        "{reason}"
    );
    assert!(!reason.contains("/bin/bash"), "{reason}");
    let long = format!(
        "1\n3\n40\n1 0 0 0\n0 1 0 0\n0 0 1 0\n{}\n",
        "secret ".repeat(40)
    );
    let (_, reason) = file_error(&long);
    assert!(reason.len() < 120, "{reason}");
}

#[test]
fn malformed_files_name_the_line_and_the_problem() {
    let m = "1 0 0 0\n0 1 0 0\n0 0 1 0\n";
    let cases: Vec<(String, usize, &str)> = vec![
        (String::new(), 0, "empty"),
        ("# only a comment\n".into(), 1, "empty"),
        ("twelve\n".into(), 1, "number of markers"),
        ("0\n".into(), 1, "need 1"),
        (format!("1\na.patt\n40\n{m}"), 2, "template pattern"),
        (format!("1\n3 4\n40\n{m}"), 2, "not a barcode id"),
        (format!("1\n-3\n40\n{m}"), 2, "not a barcode id"),
        (format!("1\n{}\n40\n{m}", 1u64 << 40), 2, "upper bits"),
        (format!("1\n3\n-40\n{m}"), 3, "positive width"),
        (format!("1\n3\nforty\n{m}"), 3, "positive width"),
        ("1\n3\n40\n1 0 0 0\n0 1 0\n0 0 1 0\n".into(), 5, "row 2"),
        ("1\n3\n40\n1 0 0 0\n0 1 0 nan\n0 0 1 0\n".into(), 5, "row 2"),
        (
            "1\n3\n40\n2 0 0 0\n0 1 0 0\n0 0 1 0\n".into(),
            2,
            "not a rotation",
        ),
        (
            "1\n3\n40\n-1 0 0 0\n0 1 0 0\n0 0 1 0\n".into(),
            2,
            "not a rotation",
        ),
        (format!("2\n3\n40\n{m}\n3\n40\n{m}"), 8, "appears twice"),
        (format!("2\n3\n40\n{m}"), 6, "ends inside marker 2 of 2"),
        ("1\n3\n40\n1 0 0 0\n".into(), 4, "ends inside marker 1"),
        (format!("1\n3\n40\n{m}4\n"), 7, "after the 1 markers"),
    ];
    for (text, line, what) in cases {
        let (l, reason) = file_error(&text);
        assert_eq!(l, line, "{text:?}: {reason}");
        assert!(
            reason.contains(what),
            "{text:?}: {reason:?} should mention {what:?}"
        );
    }
    // A missing file names the file.
    let err = MultimarkerConfig::load(std::path::Path::new("/nonexistent/set.dat")).unwrap_err();
    assert!(err.to_string().contains("/nonexistent/set.dat"), "{err}");
    // Non-UTF-8 bytes are refused with the file name.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("binary.dat");
    std::fs::write(&p, [0xff, 0xfe, 0x00, 0x31]).unwrap();
    let err = MultimarkerConfig::load(&p).unwrap_err();
    assert!(err.to_string().contains("binary.dat"), "{err}");
    // Ids outside the dictionary are refused against the dictionary, naming the line.
    let cfg = MultimarkerConfig::parse(&format!("1\n40\n40\n{m}"), "big.dat").unwrap();
    let dict = MarkerDictionary::parse("DICT_APRILTAG_16h5").unwrap();
    let img = GrayImage::from_raw(64, 64, &[128; 64 * 64]).unwrap();
    match detect_multimarker(&img, &cfg, &dict, &camera()) {
        Err(VisionError::MultimarkerFile {
            line: 2, reason, ..
        }) => {
            assert!(reason.contains("DICT_APRILTAG_16h5"), "{reason}")
        }
        other => panic!("{other:?}"),
    }
}

/// `T_camera_target` of a camera at `eye` (target frame) looking at `at`, with the
/// target's `up` pointing up in the image.
fn look_at(eye: Vector3<f64>, at: Vector3<f64>, up: Vector3<f64>) -> Isometry3<f64> {
    let z = (at - eye).normalize();
    let y = -(up - z * up.dot(&z)).normalize();
    let x = y.cross(&z);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Isometry3::from_parts(
        Translation3::from(eye),
        UnitQuaternion::from_rotation_matrix(&r),
    )
    .inverse()
}

fn render(
    cfg: &MultimarkerConfig,
    dict: &MarkerDictionary,
    pose: &Isometry3<f64>,
    margin_m: f64,
    noise: f64,
) -> GrayImage {
    let planes = TexturedPlane::multimarker_faces(cfg, dict, 6000.0, margin_m).unwrap();
    render_planes(&PlaneScene {
        camera: camera(),
        camera_from_target: *pose,
        planes,
        background: 120.0,
        noise_sigma: noise,
        seed: 3,
        supersample: 8,
    })
    .unwrap()
}

fn pose_error(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let d = a.inverse() * b;
    (d.translation.vector.norm(), d.rotation.angle())
}

/// Pixel error of every detected corner against the projection of its true point.
fn corner_errors(det: &b2b_vision::MultimarkerDetection, truth: &Isometry3<f64>) -> (f64, f64) {
    let cam = camera();
    let e: Vec<f64> = det
        .detection
        .target_points
        .iter()
        .zip(&det.detection.pixels)
        .map(|(p, uv)| (cam.project(&(truth * p)).unwrap() - uv).norm())
        .collect();
    let rms = (e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64).sqrt();
    (rms, e.iter().cloned().fold(0.0, f64::max))
}

#[test]
fn the_4x3_grid_gives_its_pose_from_all_markers_and_from_part_of_them() {
    let cfg = MultimarkerConfig::grid_4x3();
    let dict = MarkerDictionary::parse("DICT_4X4_50").unwrap();
    let cases = [
        (
            "frontal 0.6 m",
            Vector3::new(0.0, 0.0, 0.6),
            Vector3::zeros(),
            0.0,
            12,
        ),
        (
            "tilted 0.55 m",
            Vector3::new(0.2, -0.15, 0.5),
            Vector3::zeros(),
            0.0,
            12,
        ),
        (
            "tilted, noise 2",
            Vector3::new(-0.25, 0.1, 0.55),
            Vector3::zeros(),
            2.0,
            12,
        ),
        // Close and looking at the right edge: the left markers are out of the frame.
        (
            "partly outside",
            Vector3::new(0.12, 0.02, 0.3),
            Vector3::new(0.1, 0.0, 0.0),
            0.0,
            0,
        ),
    ];
    for (name, eye, at, noise, expect_all) in cases {
        let truth = look_at(eye, at, Vector3::y());
        let img = render(&cfg, &dict, &truth, 0.02, noise);
        let det = detect_multimarker(&img, &cfg, &dict, &camera()).unwrap();
        let (dt, da) = pose_error(&det.camera_from_target, &truth);
        let (c_rms, c_max) = corner_errors(&det, &truth);
        eprintln!(
            "4x3 {name}: {} markers {:?}, pose error {:.3} mm {:.4} deg, fit RMS {:.3} px, \
             corner error RMS {c_rms:.3} max {c_max:.3} px",
            det.markers.len(),
            det.markers,
            dt * 1e3,
            da.to_degrees(),
            det.rms_px
        );
        assert!(det.planar);
        if expect_all > 0 {
            assert_eq!(det.markers.len(), expect_all, "{name}");
        } else {
            assert!(
                (3..12).contains(&det.markers.len()),
                "{name}: {:?}",
                det.markers
            );
        }
        assert_eq!(det.detection.pixels.len(), 4 * det.markers.len());
        assert_eq!(det.residuals_px.len(), det.detection.pixels.len());
        let tol = if noise > 0.0 { 2.0 } else { 1.0 };
        assert!(
            dt < 0.5e-3 * tol && da.to_degrees() < 0.1 * tol,
            "{name}: {dt} m {da} rad"
        );
        assert!(
            c_rms < 0.1 * tol && c_max < 0.5 * tol,
            "{name}: corner error {c_rms} / {c_max} px"
        );
        assert!(det.rms_px < 0.1 * tol, "{name}: fit RMS {}", det.rms_px);
    }
}

#[test]
fn the_three_face_corner_gives_a_non_planar_pose() {
    let cfg = MultimarkerConfig::three_face_corner();
    let dict = MarkerDictionary::parse("DICT_APRILTAG_36h11").unwrap();
    let at = Vector3::new(0.06, 0.06, 0.06);
    let cases = [
        ("diagonal", Vector3::new(0.4, 0.4, 0.4), 0.0, 12),
        ("from the side", Vector3::new(0.45, 0.25, 0.35), 0.0, 9),
        ("noise 2", Vector3::new(0.3, 0.45, 0.4), 2.0, 9),
    ];
    for (name, eye, noise, min_markers) in cases {
        let truth = look_at(eye, at, Vector3::z());
        let img = render(&cfg, &dict, &truth, 0.01, noise);
        let det = detect_multimarker(&img, &cfg, &dict, &camera()).unwrap();
        let (dt, da) = pose_error(&det.camera_from_target, &truth);
        let (c_rms, c_max) = corner_errors(&det, &truth);
        eprintln!(
            "corner {name}: {} markers {:?}, pose error {:.3} mm {:.4} deg, fit RMS {:.3} px, \
             corner error RMS {c_rms:.3} max {c_max:.3} px",
            det.markers.len(),
            det.markers,
            dt * 1e3,
            da.to_degrees(),
            det.rms_px
        );
        assert!(!det.planar, "{name}");
        assert!(
            det.markers.len() >= min_markers,
            "{name}: {:?}",
            det.markers
        );
        let tol = if noise > 0.0 { 2.0 } else { 1.0 };
        assert!(
            dt < 0.5e-3 * tol && da.to_degrees() < 0.1 * tol,
            "{name}: {dt} m {da} rad"
        );
        // A marker seen almost edge-on keeps OpenCV's corners (its edge refinement
        // gives up), up to ~1 px off; the joint fit over all corners absorbs it.
        assert!(
            c_rms < 0.25 * tol && c_max < 1.5 * tol,
            "{name}: corner error {c_rms} / {c_max} px"
        );
    }
    // Only the floor in view (looking straight down at it): coplanar corners, IPPE.
    let truth = look_at(
        Vector3::new(0.06, 0.06, 0.35),
        Vector3::new(0.06, 0.06, 0.0),
        Vector3::y(),
    );
    let planes = TexturedPlane::multimarker_faces(&cfg, &dict, 6000.0, 0.01).unwrap();
    let img = render_planes(&PlaneScene {
        camera: camera(),
        camera_from_target: truth,
        planes: planes.into_iter().take(1).collect(),
        background: 120.0,
        noise_sigma: 0.0,
        seed: 1,
        supersample: 8,
    })
    .unwrap();
    let det = detect_multimarker(&img, &cfg, &dict, &camera()).unwrap();
    let (dt, da) = pose_error(&det.camera_from_target, &truth);
    eprintln!(
        "corner, floor only: {:?}, {:.3} mm {:.4} deg",
        det.markers,
        dt * 1e3,
        da.to_degrees()
    );
    assert!(det.planar);
    assert_eq!(det.markers, vec![0, 1, 2, 3]);
    assert!(dt < 0.5e-3 && da.to_degrees() < 0.1);
}

#[test]
fn wrong_dictionary_or_no_markers_is_not_found() {
    let cfg = MultimarkerConfig::grid_4x3();
    let dict = MarkerDictionary::parse("DICT_4X4_50").unwrap();
    let truth = look_at(Vector3::new(0.1, 0.0, 0.6), Vector3::zeros(), Vector3::y());
    let img = render(&cfg, &dict, &truth, 0.02, 0.0);
    for other in ["DICT_5X5_100", "DICT_APRILTAG_36h11", "DICT_6X6_50"] {
        let d = MarkerDictionary::parse(other).unwrap();
        match detect_multimarker(&img, &cfg, &d, &camera()) {
            Err(VisionError::MarkersNotFound { dictionary, .. }) => assert_eq!(dictionary, other),
            r => panic!("{other}: expected not found, got {r:?}"),
        }
    }
    // A set whose ids are not on the sheet.
    let mut shifted = cfg.clone();
    for m in &mut shifted.markers {
        m.id += 20;
    }
    assert!(matches!(
        detect_multimarker(&img, &shifted, &dict, &camera()),
        Err(VisionError::MarkersNotFound { .. })
    ));
    // Empty and tiny images.
    let grey = GrayImage::from_raw(W, H, &vec![120; (W * H) as usize]).unwrap();
    assert!(matches!(
        detect_multimarker(&grey, &cfg, &dict, &camera()),
        Err(VisionError::MarkersNotFound { .. })
    ));
    let tiny = GrayImage::from_raw(3, 3, &[0; 9]).unwrap();
    assert!(matches!(
        detect_multimarker(&tiny, &cfg, &dict, &camera()),
        Err(VisionError::MarkersNotFound { .. })
    ));
}

/// A deterministic N(0, 1) sequence.
fn gaussians(seed: u64) -> impl FnMut() -> f64 {
    let mut s = seed | 1;
    let mut u = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    move || (-2.0 * u().ln()).sqrt() * (std::f64::consts::TAU * u()).cos()
}

#[test]
fn pose_from_correspondences_planar_and_not_with_noise_and_bad_input() {
    let cam = camera();
    let corner = MultimarkerConfig::three_face_corner();
    let pts: Vec<Point3<f64>> = corner.markers.iter().flat_map(|m| m.corners()).collect();
    let mut g = gaussians(7);
    for k in 0..20 {
        let eye = Vector3::new(0.3 + 0.01 * k as f64, 0.5 - 0.01 * k as f64, 0.35);
        let truth = look_at(eye, Vector3::new(0.06, 0.06, 0.05), Vector3::z());
        let px: Vec<Point2<f64>> = pts
            .iter()
            .map(|p| {
                cam.project(&(truth * p)).unwrap() + nalgebra::Vector2::new(0.3 * g(), 0.3 * g())
            })
            .collect();
        let (est, planar) = multimarker_pose(&pts, &px, &cam).unwrap();
        assert!(!planar);
        let (dt, da) = pose_error(&est.camera_from_target, &truth);
        assert!(
            dt < 2e-3 && da.to_degrees() < 0.3,
            "case {k}: {dt} m, {da} rad"
        );
        assert!(
            (0.3..0.55).contains(&est.rms_px),
            "case {k}: RMS {}",
            est.rms_px
        );
    }
    // Too few, mismatched and non-finite input.
    assert!(matches!(
        multimarker_pose(&pts[..3], &[Point2::origin(); 3], &cam),
        Err(VisionError::TooFewCorners {
            found: 3,
            needed: 4
        })
    ));
    assert!(matches!(
        multimarker_pose(&pts[..5], &[Point2::origin(); 4], &cam),
        Err(VisionError::Pose(_))
    ));
    let mut px = vec![Point2::new(600.0, 300.0); 8];
    px[2].x = f64::NAN;
    assert!(matches!(
        multimarker_pose(&pts[..8], &px, &cam),
        Err(VisionError::Pose(_))
    ));
}

#[test]
fn a_small_noisy_single_marker_is_ambiguous_not_silently_wrong() {
    // One 40 mm marker 1.5 m away, turned by 20 degrees: the two planar solutions
    // fit its four corners within the noise.
    let cam = camera();
    let grid = MultimarkerConfig::grid_4x3();
    let pts = grid.markers[5].corners().to_vec();
    let truth = Isometry3::from_parts(
        Translation3::new(0.0, 0.0, 1.5),
        UnitQuaternion::from_euler_angles(0.35, 0.0, 0.0),
    ) * Isometry3::translation(0.035, 0.0, 0.0);
    let mut g = gaussians(11);
    let mut ambiguous = 0;
    for _ in 0..10 {
        let px: Vec<Point2<f64>> = pts
            .iter()
            .map(|p| {
                cam.project(&(truth * p)).unwrap() + nalgebra::Vector2::new(0.2 * g(), 0.2 * g())
            })
            .collect();
        match multimarker_pose(&pts, &px, &cam) {
            Err(VisionError::AmbiguousPose(why)) => {
                ambiguous += 1;
                assert!(why.contains("planar solutions"), "{why}");
            }
            Ok((est, _)) => {
                // Accepted only when it is the right one.
                let (_, da) = pose_error(&est.camera_from_target, &truth);
                assert!(da.to_degrees() < 10.0, "accepted a flipped pose: {da} rad");
            }
            Err(e) => panic!("{e}"),
        }
    }
    assert!(ambiguous >= 5, "only {ambiguous} of 10 flagged");
}
