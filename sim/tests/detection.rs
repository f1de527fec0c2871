//! The renderer is right: targets rendered by the simulator and detected by OpenCV (the
//! vision crate) give corners where the camera model projects the true target points.
//!
//! Each target is rendered at 1280x720 through a distorting lens from a tilted view,
//! once exactly (uniform light, pinhole focus, no blur, only 8-bit rounding) and once
//! with the full camera (defocus, PSF, vignetting, shot and read noise at 352 lx).
//! The numbers are printed (`--nocapture`); the measured values are in the asserts'
//! comments.

use b2b_calib::camera::CameraModel;
use b2b_sim::Iso3;
use b2b_sim::render::{Lighting, Optics, RenderSettings, Renderer, SceneGeometry};
use b2b_sim::scene::{BoardSpec, SceneTarget};
use b2b_sim::sensor::{SensorNoise, expose};
use b2b_sim::target::TargetModel;
use b2b_vision::{
    ArucoGridSpec, BoardDetection, CharucoSpec, CheckerboardSpec, GrayImage, detect_aruco_grid,
    detect_charuco, detect_checkerboard, detect_marker,
};
use nalgebra::{Matrix3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;

static DUMPED: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

fn camera() -> CameraModel {
    CameraModel::new(
        1280,
        720,
        [910.0, 908.0, 641.3, 358.2],
        &[0.06, -0.12, 0.0004, -0.0003, 0.03],
    )
    .unwrap()
}

thread_local! {
    /// The camera of this test thread (tests run in parallel threads).
    static CAMERA: std::cell::RefCell<CameraModel> = std::cell::RefCell::new(camera());
}

fn current_camera() -> CameraModel {
    CAMERA.with(|c| c.borrow().clone())
}

fn use_camera(cam: CameraModel) {
    CAMERA.with(|c| *c.borrow_mut() = cam);
}

/// A camera `dist` from `centre`, looking at it from `axis` turned by `tilt` about an
/// axis across it, rolled by `roll`.
fn view(target: &TargetModel, dist: f64, tilt: f64, roll: f64) -> Iso3 {
    let axis = target.view_axis;
    let helper = if axis.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let across = (helper - axis * axis.dot(&helper)).normalize();
    let dir = UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(across), tilt) * axis;
    let eye = target.centre + dir * dist;
    let z = -dir;
    let up = axis.cross(&across);
    let y = (up - z * z.dot(&up)).normalize();
    let x = y.cross(&z);
    // Exact (Shepperd) conversion: `UnitQuaternion::from_matrix` iterates from the
    // identity and need not converge for turns near 180°.
    let r = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
        Matrix3::from_columns(&[x, y, z]),
    )) * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll);
    let target_from_camera = Iso3::from_parts(Translation3::from(eye.coords), r);
    target_from_camera.inverse()
}

/// The target alone on a grey background, rendered exactly or with the full camera.
fn render(target: &TargetModel, camera_from_target: &Iso3, realistic: bool) -> GrayImage {
    let cam = current_camera();
    let mut geo = SceneGeometry::default();
    for q in &target.quads {
        geo.add_quad(q.target_from_quad, q.min, q.max, q.texture.clone());
    }
    let mut settings = RenderSettings::ideal();
    settings.background_dn = 60.0;
    let noise = if realistic {
        settings.lighting = Lighting {
            ambient: 0.5,
            ..Lighting::uniform(352.0)
        };
        settings.optics = Optics::realsense();
        SensorNoise::default()
    } else {
        SensorNoise::none()
    };
    let irr = Renderer::new(&cam)
        .unwrap()
        .render(camera_from_target, &geo, &settings);
    let img = expose(&irr, &noise, &mut b2b_sim::Rng::seed_from_u64(3));
    if let Ok(dir) = std::env::var("B2B_SIM_DUMP") {
        let n = DUMPED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        b2b_sim::image_io::write_grey(&std::path::Path::new(&dir).join(format!("{n}.png")), &img)
            .unwrap();
    }
    GrayImage::from_raw(img.width as u32, img.height as u32, &img.data).unwrap()
}

/// RMS and largest distance of detected corners from the projected truth.
fn errors(pixels: &[Point2<f64>], truth: &[Point3<f64>], camera_from_target: &Iso3) -> (f64, f64) {
    let cam = current_camera();
    let e: Vec<f64> = pixels
        .iter()
        .zip(truth)
        .map(|(uv, p)| (cam.project(&(camera_from_target * p)).unwrap() - uv).norm())
        .collect();
    let rms = (e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64).sqrt();
    (rms, e.iter().cloned().fold(0.0, f64::max))
}

fn det_errors(det: &BoardDetection, camera_from_target: &Iso3) -> (f64, f64) {
    errors(&det.pixels, &det.target_points, camera_from_target)
}

fn scene_target(json: &str) -> TargetModel {
    let spec: SceneTarget = serde_json::from_str(json).unwrap();
    TargetModel::build(&spec).unwrap()
}

const POSE: &str = r#""base1_from_target": {"t": [0, 0, 0]}"#;

fn report(name: &str, exact: (f64, f64), noisy: (f64, f64), n: usize) {
    println!(
        "{name}: {n} corners; exact RMS {:.4} px max {:.4} px; with noise RMS {:.4} px max {:.4} px",
        exact.0, exact.1, noisy.0, noisy.1
    );
}

#[test]
fn checkerboard_corners_land_where_the_camera_model_puts_them() {
    let board: BoardSpec = serde_json::from_str(&format!(
        r#"{{"inner_corners": [9, 6], "square_m": 0.025, {POSE}}}"#
    ))
    .unwrap();
    let target = TargetModel::checkerboard(&board);
    let spec = CheckerboardSpec {
        cols: 9,
        rows: 6,
        square_m: 0.025,
    };
    let pose = view(&target, 0.42, 0.35, 0.3);
    let exact = det_errors(
        &detect_checkerboard(&render(&target, &pose, false), &spec).unwrap(),
        &pose,
    );
    let det = detect_checkerboard(&render(&target, &pose, true), &spec).unwrap();
    let noisy = det_errors(&det, &pose);
    report("checkerboard", exact, noisy, det.pixels.len());
    assert!(exact.0 < 0.05 && exact.1 < 0.1, "{exact:?}");
    assert!(noisy.0 < 0.1, "{noisy:?}");
}

#[test]
fn charuco_corners_land_where_the_camera_model_puts_them() {
    let target = scene_target(&format!(
        r#"{{"kind": "charuco", "squares": [7, 5], "square_m": 0.04, "marker_m": 0.028,
            "dictionary": "DICT_5X5_100", {POSE}}}"#
    ));
    let spec = CharucoSpec {
        squares: [7, 5],
        square_m: 0.04,
        marker_m: 0.028,
        dictionary: "DICT_5X5_100".into(),
    };
    let pose = view(&target, 0.5, 0.4, -0.5);
    let cam = camera();
    let det = detect_charuco(&render(&target, &pose, false), &spec, &cam).unwrap();
    assert_eq!(det.pixels.len(), 24);
    let exact = det_errors(&det, &pose);
    let det = detect_charuco(&render(&target, &pose, true), &spec, &cam).unwrap();
    let noisy = det_errors(&det, &pose);
    report("charuco", exact, noisy, det.pixels.len());
    assert!(exact.0 < 0.05 && exact.1 < 0.1, "{exact:?}");
    assert!(noisy.0 < 0.1, "{noisy:?}");
}

#[test]
fn aruco_grid_corners_land_where_the_camera_model_puts_them() {
    let target = scene_target(&format!(
        r#"{{"kind": "aruco_grid", "markers": [4, 3], "marker_m": 0.05, "separation_m": 0.01,
            "dictionary": "DICT_6X6_250", "first_id": 3, {POSE}}}"#
    ));
    let spec = ArucoGridSpec {
        markers: [4, 3],
        marker_m: 0.05,
        separation_m: 0.01,
        dictionary: "DICT_6X6_250".into(),
        first_id: 3,
    };
    let pose = view(&target, 0.5, 0.3, 0.2);
    let det = detect_aruco_grid(&render(&target, &pose, false), &spec).unwrap();
    assert_eq!(det.pixels.len(), 48);
    let exact = det_errors(&det, &pose);
    let det = detect_aruco_grid(&render(&target, &pose, true), &spec).unwrap();
    let noisy = det_errors(&det, &pose);
    report("aruco grid", exact, noisy, det.pixels.len());
    assert!(exact.0 < 0.05 && exact.1 < 0.1, "{exact:?}");
    assert!(noisy.0 < 0.1, "{noisy:?}");
}

/// Every marker of a multimarker target, detected one by one, against its corners in
/// the set frame (so the layout, the ARToolKit file's transforms and the marker
/// orientation are all checked).
fn multimarker_errors(
    target: &TargetModel,
    dictionary: &str,
    pose: &Iso3,
    realistic: bool,
) -> ((f64, f64), usize) {
    let img = render(target, pose, realistic);
    let (mut pixels, mut truth) = (vec![], vec![]);
    for m in &target.markers {
        let det = detect_marker(&img, dictionary, m.id, m.width_m)
            .unwrap_or_else(|e| panic!("marker {}: {e}", m.id));
        pixels.extend(det.pixels);
        truth.extend(m.corners_in_set());
    }
    (errors(&pixels, &truth, pose), pixels.len())
}

#[test]
fn single_and_planar_multimarker_corners_land_where_the_camera_model_puts_them() {
    for (name, layout, dict, dist) in [
        (
            "single marker",
            r#"{"shape": "grid", "markers": [1, 1], "marker_m": 0.1, "pitch_m": 0.1, "first_id": 7}"#,
            "DICT_APRILTAG_36h11",
            0.45,
        ),
        (
            "4x3 multimarker",
            r#"{"shape": "grid", "markers": [4, 3], "marker_m": 0.04, "pitch_m": 0.07}"#,
            "DICT_4X4_50",
            0.45,
        ),
    ] {
        let target = scene_target(&format!(
            r#"{{"kind": "multimarker", "dictionary": "{dict}", "layout": {layout},
                "margin_m": 0.03, {POSE}}}"#
        ));
        let pose = view(&target, dist, 0.35, 0.4);
        let (exact, n) = multimarker_errors(&target, dict, &pose, false);
        let (noisy, _) = multimarker_errors(&target, dict, &pose, true);
        report(name, exact, noisy, n);
        // The vision crate fits marker edges as straight lines in the distorted image;
        // a 100 mm marker's edges (~200 px) bend by ~0.1 px under this lens, which
        // shows as a systematic error (measured 0.076 px RMS, noise-free or not).
        let limit = if name == "single marker" { 0.1 } else { 0.05 };
        assert!(exact.0 < limit && exact.1 < 0.1, "{name}: {exact:?}");
        assert!(noisy.0 < 0.1, "{name}: {noisy:?}");
        // Through a distortion-free lens the same marker is found to 0.05 px.
        use_camera(CameraModel::new(1280, 720, [910.0, 908.0, 641.3, 358.2], &[]).unwrap());
        let (pinhole, _) = multimarker_errors(&target, dict, &pose, false);
        use_camera(camera());
        println!(
            "{name}, no lens distortion: RMS {:.4} px max {:.4} px",
            pinhole.0, pinhole.1
        );
        assert!(pinhole.0 < 0.05 && pinhole.1 < 0.1, "{name}: {pinhole:?}");
    }
}

#[test]
fn three_face_corner_markers_land_where_the_camera_model_puts_them() {
    let target = scene_target(&format!(
        r#"{{"kind": "multimarker", "dictionary": "DICT_4X4_50",
            "layout": {{"shape": "corner", "per_side": 2, "marker_m": 0.04, "pitch_m": 0.06,
                        "face_m": 0.13}}, {POSE}}}"#
    ));
    assert_eq!(target.quads.len(), 3);
    let pose = view(&target, 0.33, 0.1, 0.2);
    let (exact, n) = multimarker_errors(&target, "DICT_4X4_50", &pose, false);
    let (noisy, _) = multimarker_errors(&target, "DICT_4X4_50", &pose, true);
    report("three-face corner", exact, noisy, n);
    assert_eq!(n, 48);
    assert!(exact.0 < 0.05 && exact.1 < 0.15, "{exact:?}");
    assert!(noisy.0 < 0.15, "{noisy:?}");
}

/// Every image of the committed marker datasets is detected by the vision crate (the
/// ChArUco set's occluder hides part of the board in some: fewer corners there).
#[test]
fn committed_marker_datasets_are_detected() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets");
    for name in [
        "sim-charuco-occluded-2x10",
        "sim-aruco-grid-2x5",
        "sim-single-marker-2x5",
        "sim-multimarker-4x3-2x10",
        "sim-multimarker-corner-2x10",
    ] {
        let ds = b2b_dataset::Dataset::load(&root.join(name)).unwrap();
        let target = ds.manifest.target.clone();
        let markers = match &target {
            b2b_dataset::Target::Multimarker { .. } => {
                let scene =
                    b2b_sim::scene::Scene::load(&root.join(name).join("scene.json")).unwrap();
                scene.target_model(&root.join(name)).unwrap().0.markers
            }
            _ => vec![],
        };
        let mut counts = vec![];
        for (r, robot) in ds.robots.iter().enumerate() {
            let m = ds.manifest.robots[r].camera.clone().unwrap();
            let cam =
                CameraModel::new(m.width, m.height, [m.fx, m.fy, m.cx, m.cy], &m.dist).unwrap();
            for cap in &robot.captures {
                let path = ds.image_path(&robot.id, cap).unwrap();
                let img = b2b_vision::load_gray(&path).unwrap();
                let n = match &target {
                    b2b_dataset::Target::Charuco {
                        squares,
                        square_m,
                        marker_m,
                        dictionary,
                    } => {
                        let spec = CharucoSpec {
                            squares: squares.map(|v| v as usize),
                            square_m: *square_m,
                            marker_m: *marker_m,
                            dictionary: dictionary.clone(),
                        };
                        detect_charuco(&img, &spec, &cam).map_or(0, |d| d.pixels.len())
                    }
                    b2b_dataset::Target::ArucoGrid {
                        markers,
                        marker_m,
                        separation_m,
                        dictionary,
                        first_id,
                    } => {
                        let spec = ArucoGridSpec {
                            markers: markers.map(|v| v as usize),
                            marker_m: *marker_m,
                            separation_m: *separation_m,
                            dictionary: dictionary.clone(),
                            first_id: *first_id as usize,
                        };
                        detect_aruco_grid(&img, &spec).map_or(0, |d| d.pixels.len())
                    }
                    b2b_dataset::Target::Multimarker { dictionary, .. } => markers
                        .iter()
                        .filter_map(|m| detect_marker(&img, dictionary, m.id, m.width_m).ok())
                        .map(|d| d.pixels.len())
                        .sum(),
                    b2b_dataset::Target::Checkerboard { .. } => unreachable!(),
                };
                counts.push(n);
            }
        }
        println!("{name}: corners per image {counts:?}");
        let full = counts.iter().copied().max().unwrap();
        assert!(full > 0, "{name}: nothing detected");
        if name.starts_with("sim-charuco") {
            // Occluded captures lose corners but keep enough for a pose.
            assert!(counts.iter().all(|&n| n >= 6), "{name}: {counts:?}");
            assert!(
                counts.iter().any(|&n| n < full),
                "{name}: no capture is occluded"
            );
        } else {
            assert!(counts.iter().all(|&n| n == full), "{name}: {counts:?}");
        }
    }
}

/// The board of the colour RGB-D set is found in every (colour) image.
#[test]
fn committed_rgbd_images_show_the_board() {
    let root =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-rgbd-boxes-2x5");
    let ds = b2b_dataset::Dataset::load(&root).unwrap();
    let spec = CheckerboardSpec {
        cols: 9,
        rows: 6,
        square_m: 0.025,
    };
    for robot in &ds.robots {
        for cap in &robot.captures {
            let img = b2b_vision::load_gray(&ds.image_path(&robot.id, cap).unwrap()).unwrap();
            let det = detect_checkerboard(&img, &spec)
                .unwrap_or_else(|e| panic!("{} {:?}: {e}", robot.id, cap.image));
            assert_eq!(det.pixels.len(), 54);
        }
    }
}
