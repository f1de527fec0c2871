//! Corner accuracy on rendered boards with exactly known corners (see `synth`).
//! `cargo test -p b2b-vision --test accuracy -- --nocapture` prints the table.

use b2b_calib::camera::CameraModel;
use b2b_vision::synth::{BoardScene, render_checkerboard};
use b2b_vision::{
    CheckerboardSpec, CornerMethod, VisionError, detect_checkerboard, detect_checkerboard_with,
};
use nalgebra::{Isometry3, Point2, Translation3, UnitQuaternion, Vector3};
use opencv::calib3d::{
    CALIB_CB_ACCURACY, CALIB_CB_ADAPTIVE_THRESH, CALIB_CB_EXHAUSTIVE, CALIB_CB_NORMALIZE_IMAGE,
};

const SPEC: CheckerboardSpec = CheckerboardSpec {
    cols: 9,
    rows: 6,
    square_m: 0.03,
};

fn camera(width: u32, height: u32, f: f64) -> CameraModel {
    CameraModel::new(
        width,
        height,
        [f, f, width as f64 / 2.0 - 0.3, height as f64 / 2.0 + 0.2],
        &[],
    )
    .unwrap()
}

/// The board centred `distance` in front of the camera, turned by roll/pitch/yaw
/// (degrees) about the camera axes.
fn pose(spec: &CheckerboardSpec, distance: f64, [roll, pitch, yaw]: [f64; 3]) -> Isometry3<f64> {
    let r =
        UnitQuaternion::from_euler_angles(roll.to_radians(), pitch.to_radians(), yaw.to_radians());
    let centre = Vector3::new(
        (spec.cols - 1) as f64 * spec.square_m / 2.0,
        (spec.rows - 1) as f64 * spec.square_m / 2.0,
        0.0,
    );
    let t = Vector3::new(0.01, -0.005, distance) - r * centre;
    Isometry3::from_parts(Translation3::from(t), r)
}

struct Case {
    name: &'static str,
    scene: BoardScene,
}

fn cases() -> Vec<Case> {
    let cam = camera(1280, 720, 900.0);
    let mk = |name, cam: &CameraModel, d, angles, noise| {
        let mut scene = BoardScene::new(SPEC, cam.clone(), pose(&SPEC, d, angles));
        scene.noise_sigma = noise;
        Case { name, scene }
    };
    vec![
        mk("frontal 45px", &cam, 0.6, [4.0, -6.0, 7.0], 0.0),
        mk("frontal 180deg", &cam, 0.6, [4.0, -6.0, 187.0], 0.0),
        mk("tilt 35deg", &cam, 0.6, [35.0, 10.0, -12.0], 0.0),
        mk("tilt 35deg 180deg", &cam, 0.6, [-35.0, 10.0, 168.0], 0.0),
        mk("far 22px", &cam, 1.2, [10.0, 15.0, 20.0], 0.0),
        mk("frontal noise2", &cam, 0.6, [4.0, -6.0, 7.0], 2.0),
        mk("tilt noise2", &cam, 0.6, [35.0, 10.0, -12.0], 2.0),
    ]
}

#[derive(Debug, Default)]
struct Stats {
    bias: Vector3<f64>,
    rms: f64,
    max: f64,
}

/// Errors of a detection against the truth, by corner id.
fn stats(pixels: &[Point2<f64>], truth: &[Point2<f64>]) -> Stats {
    let n = truth.len() as f64;
    let mut s = Stats::default();
    for (p, t) in pixels.iter().zip(truth) {
        let e = p - t;
        s.bias += Vector3::new(e.x, e.y, 0.0) / n;
        s.rms += e.norm_squared() / n;
        s.max = s.max.max(e.norm());
    }
    s.rms = s.rms.sqrt();
    s
}

fn methods() -> Vec<(&'static str, CornerMethod)> {
    let classic = CALIB_CB_ADAPTIVE_THRESH | CALIB_CB_NORMALIZE_IMAGE;
    vec![
        ("SB", CornerMethod::SectorBased { flags: 0 }),
        (
            "SB NORMALIZE",
            CornerMethod::SectorBased {
                flags: CALIB_CB_NORMALIZE_IMAGE,
            },
        ),
        (
            "SB ACCURACY",
            CornerMethod::SectorBased {
                flags: CALIB_CB_ACCURACY,
            },
        ),
        (
            "SB ACCURACY|NORMALIZE",
            CornerMethod::SectorBased {
                flags: CALIB_CB_ACCURACY | CALIB_CB_NORMALIZE_IMAGE,
            },
        ),
        (
            "SB NORMALIZE|EXHAUSTIVE",
            CornerMethod::SectorBased {
                flags: CALIB_CB_NORMALIZE_IMAGE | CALIB_CB_EXHAUSTIVE,
            },
        ),
        (
            "classic+subpix 11x11",
            CornerMethod::Classic {
                flags: classic,
                half_window: Some(5),
            },
        ),
        (
            "classic+subpix 7x7",
            CornerMethod::Classic {
                flags: classic,
                half_window: Some(3),
            },
        ),
        (
            "classic+subpix adaptive",
            CornerMethod::Classic {
                flags: classic,
                half_window: None,
            },
        ),
    ]
}

/// Prints bias / RMS / max for every detector on every case (slow: the ACCURACY
/// variants take ~0.5 s a frame). Run with `--ignored --nocapture`.
#[test]
#[ignore = "measurement table, run by hand"]
fn measure_detectors_on_rendered_boards() {
    let cases = cases();
    let rendered: Vec<_> = cases
        .iter()
        .map(|c| render_checkerboard(&c.scene).unwrap())
        .collect();
    println!(
        "{:<32} {:<20} {:>16} {:>8} {:>8} {:>8}",
        "detector", "case", "bias px", "rms px", "max px", "ms"
    );
    for (mname, method) in methods() {
        for refine in [false, true] {
            let mname = if refine {
                format!("{mname} +refine")
            } else {
                mname.to_string()
            };
            for (case, (img, truth)) in cases.iter().zip(&rendered) {
                let t0 = std::time::Instant::now();
                let det = detect_checkerboard_with(img, &SPEC, &[method], refine);
                let ms = t0.elapsed().as_secs_f64() * 1e3;
                match det {
                    Ok(det) => {
                        let s = stats(&det.pixels, truth);
                        println!(
                            "{mname:<32} {:<20} ({:+.3},{:+.3}) {:>8.4} {:>8.4} {ms:>8.1}",
                            case.name, s.bias.x, s.bias.y, s.rms, s.max
                        );
                    }
                    Err(e) => println!("{mname:<32} {:<20} failed: {e}", case.name),
                }
            }
        }
    }
}

/// The default detector must find every rendered board, in the right orientation,
/// to better than 0.05 px RMS without noise (0.15 px with σ = 2 grey levels).
#[test]
fn default_detector_is_accurate_and_oriented_on_rendered_boards() {
    for case in cases() {
        let (img, truth) = render_checkerboard(&case.scene).unwrap();
        let det = detect_checkerboard(&img, &SPEC).unwrap_or_else(|e| panic!("{}: {e}", case.name));
        assert_eq!(det.corner_ids, (0..SPEC.corner_count()).collect::<Vec<_>>());
        let s = stats(&det.pixels, &truth);
        let limit = if case.scene.noise_sigma > 0.0 {
            0.15
        } else {
            0.05
        };
        assert!(
            s.rms < limit,
            "{}: rms {:.4} px (bias {:?}) with {:?}",
            case.name,
            s.rms,
            s.bias,
            det.method
        );
        assert!(s.max < 3.0 * limit, "{}: max {:.4} px", case.name, s.max);
    }
}

/// Boards whose square colours look the same after a 180° turn are refused, not
/// guessed: 8x6 (9x7 squares, all four outer squares black) and 7x5 (black outer
/// squares on a diagonal).
#[test]
fn symmetric_boards_are_refused_as_ambiguous() {
    for spec in [
        CheckerboardSpec {
            cols: 8,
            rows: 6,
            square_m: 0.03,
        },
        CheckerboardSpec {
            cols: 7,
            rows: 5,
            square_m: 0.03,
        },
    ] {
        let scene = BoardScene::new(
            spec,
            camera(1280, 720, 900.0),
            pose(&spec, 0.6, [4.0, -6.0, 7.0]),
        );
        let (img, _) = render_checkerboard(&scene).unwrap();
        let err = detect_checkerboard(&img, &spec).unwrap_err();
        assert!(
            matches!(err, VisionError::AmbiguousOrientation(_)),
            "{spec:?}: {err}"
        );
    }
}

/// 8x7 inner corners (9x8 squares: black outer squares along the top side) is
/// unambiguous too, with the even side along y this time.
#[test]
fn odd_by_even_board_is_oriented_both_ways() {
    let spec = CheckerboardSpec {
        cols: 8,
        rows: 7,
        square_m: 0.03,
    };
    for yaw in [3.0, 183.0, 93.0, -87.0] {
        let scene = BoardScene::new(
            spec,
            camera(1280, 720, 900.0),
            pose(&spec, 0.65, [8.0, -5.0, yaw]),
        );
        let (img, truth) = render_checkerboard(&scene).unwrap();
        let det = detect_checkerboard(&img, &spec).unwrap();
        let s = stats(&det.pixels, &truth);
        assert!(s.rms < 0.05, "yaw {yaw}: rms {:.4}", s.rms);
    }
}

/// With 10x7 squares, inverting the colours gives the same board turned by 180°, so
/// the origin must follow the colours to the opposite corner.
#[test]
fn inverted_colours_move_the_origin_to_the_opposite_corner() {
    let mut scene = BoardScene::new(
        SPEC,
        camera(1280, 720, 900.0),
        pose(&SPEC, 0.6, [4.0, -6.0, 7.0]),
    );
    (scene.black, scene.white) = (220.0, 30.0);
    scene.background = 30.0;
    let (img, truth) = render_checkerboard(&scene).unwrap();
    let det = detect_checkerboard(&img, &SPEC).unwrap();
    let n = truth.len();
    let reversed: Vec<_> = (0..n).map(|k| truth[n - 1 - k]).collect();
    let s = stats(&det.pixels, &reversed);
    assert!(
        s.rms < 0.05,
        "rms {:.4} against the 180°-turned truth",
        s.rms
    );
}
