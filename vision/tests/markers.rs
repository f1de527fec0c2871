//! ChArUco boards, ArUco grids and single markers drawn by OpenCV, seen through a known
//! camera pose, detected with exactly known corners.
//!
//! Scenes: OpenCV draws the target at 4x the final resolution; a homography
//! `K·[r1 r2 t]·A⁻¹` (A: target metres → source pixels) warps it with bilinear
//! interpolation into a 4x-sized frame, which `INTER_AREA` shrinks to 1280x720. The
//! drawn edges lie on pixel boundaries, so the true image of target point P is
//! exactly `camera.project(pose * P)`.

use b2b_calib::camera::CameraModel;
use b2b_vision::markers::{MIN_CHARUCO_CORNERS, marker_target_points};
use b2b_vision::{
    ArucoGridSpec, CharucoSpec, CornerMethod, GrayImage, MarkerDictionary, VisionError, board_pose,
    detect_aruco_grid, detect_charuco, detect_marker, render_charuco,
};
use nalgebra::{Isometry3, Matrix3, Point2, Point3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, Point, Scalar, Size, Vector};
use opencv::prelude::*;
use opencv::{aruco, core, imgproc};

const W: u32 = 1280;
const H: u32 = 720;

fn camera() -> CameraModel {
    CameraModel::new(W, H, [900.0, 900.0, 639.5, 359.5], &[]).unwrap()
}

/// A pose that shows the target's point `centre` at the image centre from `dist` m,
/// turned by the given Euler angles.
fn pose(centre: Vector3<f64>, dist: f64, angles: (f64, f64, f64)) -> Isometry3<f64> {
    let r = UnitQuaternion::from_euler_angles(angles.0, angles.1, angles.2);
    Isometry3::from_parts(
        Translation3::from(Vector3::new(0.0, 0.0, dist) - r * centre),
        r,
    )
}

/// Warps `src` (drawn so that target point (X, Y) is at source pixel `a·(X, Y, 1)`)
/// into the camera's image.
fn scene(src: &Mat, a: Matrix3<f64>, pose: &Isometry3<f64>, cam: &CameraModel) -> GrayImage {
    let k_big = Matrix3::new(
        4.0 * cam.fx,
        0.0,
        4.0 * cam.cx + 1.5,
        0.0,
        4.0 * cam.fy,
        4.0 * cam.cy + 1.5,
        0.0,
        0.0,
        1.0,
    );
    let r = pose.rotation.to_rotation_matrix();
    let rt = Matrix3::from_columns(&[
        r.matrix().column(0).into_owned(),
        r.matrix().column(1).into_owned(),
        pose.translation.vector,
    ]);
    let h = k_big * rt * a.try_inverse().unwrap();
    let hm = Mat::from_slice_2d(&[
        [h[(0, 0)], h[(0, 1)], h[(0, 2)]],
        [h[(1, 0)], h[(1, 1)], h[(1, 2)]],
        [h[(2, 0)], h[(2, 1)], h[(2, 2)]],
    ])
    .unwrap();
    let mut big = Mat::default();
    imgproc::warp_perspective(
        src,
        &mut big,
        &hm,
        Size::new(4 * W as i32, 4 * H as i32),
        imgproc::INTER_LINEAR,
        core::BORDER_CONSTANT,
        Scalar::all(128.0),
    )
    .unwrap();
    let mut small = Mat::default();
    imgproc::resize(
        &big,
        &mut small,
        Size::new(W as i32, H as i32),
        0.0,
        0.0,
        imgproc::INTER_AREA,
    )
    .unwrap();
    GrayImage::from_mat(small).unwrap()
}

/// Source pixel of target point (X, Y): `offset + scale·(±X, ±Y) - 0.5`.
fn affine(scale: f64, offset: (f64, f64), y_up: bool) -> Matrix3<f64> {
    let sy = if y_up { -scale } else { scale };
    Matrix3::new(
        scale,
        0.0,
        offset.0 - 0.5,
        0.0,
        sy,
        offset.1 - 0.5,
        0.0,
        0.0,
        1.0,
    )
}

/// Adds Gaussian noise (Box–Muller on a fixed xorshift sequence).
fn noisy(img: &GrayImage, sigma: f64) -> GrayImage {
    let mut state = 0x2545_f491_4f6c_dd1d_u64;
    let mut uniform = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let px: Vec<u8> = img
        .pixels()
        .iter()
        .map(|&v| {
            let g = (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos();
            (f64::from(v) + sigma * g).round().clamp(0.0, 255.0) as u8
        })
        .collect();
    GrayImage::from_raw(img.width(), img.height(), &px).unwrap()
}

fn charuco_spec() -> CharucoSpec {
    CharucoSpec {
        squares: [7, 5],
        square_m: 0.04,
        marker_m: 0.028,
        dictionary: "DICT_5X5_100".into(),
    }
}

/// Renders `spec` with [`render_charuco`] at `pps` px per square and shows it at `pose`.
fn charuco_scene(spec: &CharucoSpec, pose: &Isometry3<f64>, pps: usize) -> GrayImage {
    let src = render_charuco(spec, pps).unwrap();
    let p = pps as f64;
    // render_charuco: one-square margin, board frame y down.
    let a = affine(p / spec.square_m, (p, p), false);
    scene(src.mat(), a, pose, &camera())
}

fn errors_px(pixels: &[Point2<f64>], targets: &[Point3<f64>], pose: &Isometry3<f64>) -> Vec<f64> {
    let cam = camera();
    pixels
        .iter()
        .zip(targets)
        .map(|(uv, p)| (cam.project(&(pose * p)).unwrap() - uv).norm())
        .collect()
}

fn rms(e: &[f64]) -> f64 {
    (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt()
}

fn pose_error(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let d = a.inverse() * b;
    (d.translation.vector.norm(), d.rotation.angle().to_degrees())
}

#[test]
fn every_opencv_dictionary_name_parses_and_unknown_names_are_refused() {
    let names: Vec<&str> = MarkerDictionary::all().map(|d| d.name()).collect();
    assert_eq!(names.len(), 21);
    for name in &names {
        let d: MarkerDictionary = name.parse().unwrap();
        assert_eq!(d.name(), *name);
        assert_eq!(MarkerDictionary::parse(&name.to_lowercase()).unwrap(), d);
    }
    for (name, count) in [
        ("DICT_4X4_50", 50),
        ("DICT_7X7_1000", 1000),
        ("DICT_ARUCO_ORIGINAL", 1024),
        ("DICT_APRILTAG_16h5", 30),
        ("DICT_APRILTAG_36h11", 587),
    ] {
        assert_eq!(MarkerDictionary::parse(name).unwrap().marker_count(), count);
    }
    // Our marker counts are OpenCV's.
    for d in MarkerDictionary::all() {
        let ocv = aruco::get_predefined_dictionary_i32(
            names.iter().position(|n| *n == d.name()).unwrap() as i32,
        )
        .unwrap();
        assert_eq!(ocv.bytes_list().rows() as usize, d.marker_count(), "{d}");
    }
    for bad in ["", "DICT_4X4_49", "DICT_8X8_50", "APRILTAG_36h11", "36h11"] {
        let err = MarkerDictionary::parse(bad).unwrap_err();
        assert!(matches!(err, VisionError::UnknownDictionary(_)), "{err}");
        assert!(err.to_string().contains("DICT_APRILTAG"), "{err}");
    }
}

#[test]
fn charuco_target_points_are_opencvs_chessboard_corners() {
    for (squares, dict) in [
        ([7, 5], "DICT_5X5_100"),
        ([8, 6], "DICT_4X4_50"),
        ([5, 5], "DICT_6X6_250"),
        ([2, 3], "DICT_4X4_50"),
    ] {
        let spec = CharucoSpec {
            squares,
            square_m: 0.035,
            marker_m: 0.02,
            dictionary: dict.into(),
        };
        let board = aruco::CharucoBoard::create(
            squares[0] as i32,
            squares[1] as i32,
            0.035,
            0.02,
            &aruco::get_predefined_dictionary_i32(0).unwrap(),
        )
        .unwrap();
        let corners = board.chessboard_corners();
        assert_eq!(corners.len(), spec.corner_count());
        for (k, p) in corners.iter().enumerate() {
            let q = spec.target_point(k);
            assert!(
                (f64::from(p.x) - q.x).abs() < 1e-6 && (f64::from(p.y) - q.y).abs() < 1e-6,
                "{squares:?} corner {k}: OpenCV {p:?}, ours {q}"
            );
        }
    }
}

#[test]
fn charuco_corners_are_found_to_a_tenth_of_a_pixel() {
    for (name, spec, angles) in [
        ("frontal 7x5", charuco_spec(), (0.0, 0.0, 0.0)),
        ("tilted 7x5", charuco_spec(), (0.35, -0.25, 0.2)),
        (
            "tilted 8x6 (even rows)",
            CharucoSpec {
                squares: [8, 6],
                square_m: 0.035,
                marker_m: 0.026,
                dictionary: "DICT_4X4_50".into(),
            },
            (-0.3, 0.3, -0.1),
        ),
    ] {
        let centre = Vector3::new(
            0.5 * spec.squares[0] as f64 * spec.square_m,
            0.5 * spec.squares[1] as f64 * spec.square_m,
            0.0,
        );
        let truth = pose(centre, 0.6, angles);
        let img = charuco_scene(&spec, &truth, 240);
        let det = detect_charuco(&img, &spec, &camera()).unwrap();
        assert_eq!(det.method, CornerMethod::Charuco);
        assert_eq!(
            det.corner_ids,
            (0..spec.corner_count()).collect::<Vec<_>>(),
            "{name}"
        );
        let e = errors_px(&det.pixels, &det.target_points, &truth);
        let max = e.iter().cloned().fold(0.0, f64::max);
        println!(
            "{name}: {} corners, RMS {:.4} px, max {max:.4} px",
            e.len(),
            rms(&e)
        );
        assert!(max < 0.1, "{name}: max corner error {max} px");
        let noisy_det = detect_charuco(&noisy(&img, 2.0), &spec, &camera()).unwrap();
        let e = errors_px(&noisy_det.pixels, &noisy_det.target_points, &truth);
        let max_noisy = e.iter().cloned().fold(0.0, f64::max);
        println!(
            "{name}, noise σ=2: RMS {:.4} px, max {max_noisy:.4} px",
            rms(&e)
        );
        assert!(
            max_noisy < 0.15,
            "{name}: max error with noise {max_noisy} px"
        );
        let est = board_pose(&det, &camera()).unwrap();
        let (dt, dr) = pose_error(&est.camera_from_target, &truth);
        println!("{name}: pose error {:.3} mm, {dr:.4} deg", dt * 1e3);
        assert!(dt < 1e-3 && dr < 0.1, "{name}: {dt} m, {dr} deg");
    }
}

#[test]
fn charuco_pose_survives_a_board_thirty_percent_covered() {
    let spec = charuco_spec();
    let centre = Vector3::new(0.14, 0.10, 0.0);
    let truth = pose(centre, 0.6, (0.25, 0.2, 0.1));
    let img = charuco_scene(&spec, &truth, 240);
    // Cover x < 30 % of the board width (and the margin beyond it) with a grey card.
    let cam = camera();
    let x_cut = 0.3 * 7.0 * spec.square_m;
    let quad: Vector<Point> = [(-0.05, -0.05), (x_cut, -0.05), (x_cut, 0.25), (-0.05, 0.25)]
        .iter()
        .map(|&(x, y)| {
            let uv = cam.project(&(truth * Point3::new(x, y, 0.0))).unwrap();
            Point::new(uv.x.round() as i32, uv.y.round() as i32)
        })
        .collect();
    let mut mat = img.mat().try_clone().unwrap();
    imgproc::fill_convex_poly(&mut mat, &quad, Scalar::all(90.0), imgproc::LINE_8, 0).unwrap();
    let covered = GrayImage::from_mat(mat).unwrap();

    let det = detect_charuco(&covered, &spec, &cam).unwrap();
    // Corner columns at x = 0.04 and 0.08 m are under the card; the four others are seen.
    let expected: Vec<usize> = (0..spec.corner_count())
        .filter(|&k| spec.target_point(k).x > x_cut)
        .collect();
    assert_eq!(det.corner_ids, expected);
    assert_eq!(expected.len(), 16);
    let e = errors_px(&det.pixels, &det.target_points, &truth);
    let max = e.iter().cloned().fold(0.0, f64::max);
    println!("covered: {} corners, max error {max:.4} px", e.len());
    assert!(max < 0.1, "max corner error {max} px");
    let est = board_pose(&det, &cam).unwrap();
    let (dt, dr) = pose_error(&est.camera_from_target, &truth);
    println!("covered: pose error {:.3} mm, {dr:.4} deg", dt * 1e3);
    assert!(dt < 2e-3 && dr < 0.2, "{dt} m, {dr} deg");
}

#[test]
fn charuco_errors_are_clear() {
    let cam = camera();
    let blank = GrayImage::from_raw(W, H, &vec![128; (W * H) as usize]).unwrap();
    let err = detect_charuco(&blank, &charuco_spec(), &cam).unwrap_err();
    assert!(matches!(err, VisionError::MarkersNotFound { .. }), "{err}");
    let tiny = GrayImage::from_raw(3, 2, &[0, 255, 0, 255, 0, 255]).unwrap();
    let err = detect_charuco(&tiny, &charuco_spec(), &cam).unwrap_err();
    assert!(matches!(err, VisionError::MarkersNotFound { .. }), "{err}");
    for spec in [
        CharucoSpec {
            squares: [1, 5],
            ..charuco_spec()
        },
        CharucoSpec {
            marker_m: 0.05,
            ..charuco_spec()
        },
        CharucoSpec {
            square_m: f64::NAN,
            ..charuco_spec()
        },
        CharucoSpec {
            squares: [12, 10], // 60 markers
            dictionary: "DICT_4X4_50".into(),
            ..charuco_spec()
        },
    ] {
        let err = detect_charuco(&blank, &spec, &cam).unwrap_err();
        assert!(matches!(err, VisionError::InvalidTarget(_)), "{err}");
        assert!(render_charuco(&spec, 40).is_err());
    }
    let err = detect_charuco(
        &blank,
        &CharucoSpec {
            dictionary: "DICT_5X5_1001".into(),
            ..charuco_spec()
        },
        &cam,
    )
    .unwrap_err();
    assert!(matches!(err, VisionError::UnknownDictionary(_)), "{err}");
    assert!(render_charuco(&charuco_spec(), 0).is_err());
    assert!(render_charuco(&charuco_spec(), 100_000).is_err());

    // Only a corner of the board in view: too few corners, not a bad pose.
    let spec = charuco_spec();
    let truth = pose(Vector3::new(0.14, 0.10, 0.0), 0.6, (0.0, 0.0, 0.0));
    let img = charuco_scene(&spec, &truth, 240);
    let mut mat = img.mat().try_clone().unwrap();
    let keep = cam.project(&(truth * Point3::new(0.1, 0.1, 0.0))).unwrap();
    imgproc::rectangle(
        &mut mat,
        core::Rect::new(keep.x as i32, 0, W as i32, H as i32),
        Scalar::all(128.0),
        -1,
        imgproc::LINE_8,
        0,
    )
    .unwrap();
    imgproc::rectangle(
        &mut mat,
        core::Rect::new(0, keep.y as i32, W as i32, H as i32),
        Scalar::all(128.0),
        -1,
        imgproc::LINE_8,
        0,
    )
    .unwrap();
    let err = detect_charuco(&GrayImage::from_mat(mat).unwrap(), &spec, &cam).unwrap_err();
    assert!(
        matches!(err, VisionError::TooFewCorners { needed, .. } if needed == MIN_CHARUCO_CORNERS)
            || matches!(
                err,
                VisionError::Pose(_) | VisionError::MarkersNotFound { .. }
            ),
        "{err}"
    );
}

#[test]
fn aruco_grid_corners_and_pose() {
    let spec = ArucoGridSpec {
        markers: [4, 3],
        marker_m: 0.04,
        separation_m: 0.01,
        dictionary: "DICT_5X5_100".into(),
        first_id: 10,
    };
    // GridBoard::draw at 5000 px/m: markers 200 px, gaps 50 px, 100 px margins.
    let board = aruco::GridBoard::create(
        4,
        3,
        0.04,
        0.01,
        &aruco::get_predefined_dictionary_i32(5).unwrap(),
        10,
    )
    .unwrap();
    let mut board = board;
    let mut src = Mat::default();
    board
        .draw(Size::new(950 + 200, 700 + 200), &mut src, 100, 1)
        .unwrap();
    let truth = pose(Vector3::new(0.095, 0.07, 0.0), 0.5, (0.3, -0.3, 0.4));
    let img = scene(
        &src,
        affine(5000.0, (100.0, 100.0), false),
        &truth,
        &camera(),
    );
    let det = detect_aruco_grid(&img, &spec).unwrap();
    assert_eq!(det.method, CornerMethod::ArucoMarkers);
    assert_eq!(det.corner_ids, (0..48).collect::<Vec<_>>());
    let e = errors_px(&det.pixels, &det.target_points, &truth);
    let max = e.iter().cloned().fold(0.0, f64::max);
    println!(
        "grid: {} corners, RMS {:.4} px, max {max:.4} px",
        e.len(),
        rms(&e)
    );
    // OpenCV's CORNER_REFINE_SUBPIX alone: 0.25 px RMS, 0.39 max.
    assert!(max < 0.1, "max corner error {max} px");
    assert!(det.refined);
    let est = board_pose(&det, &camera()).unwrap();
    let (dt, dr) = pose_error(&est.camera_from_target, &truth);
    println!("grid: pose error {:.3} mm, {dr:.4} deg", dt * 1e3);
    assert!(dt < 1e-3 && dr < 0.1, "{dt} m, {dr} deg");

    // With sensor noise (σ = 2 grey levels) the corners stay within a tenth of a pixel.
    let det = detect_aruco_grid(&noisy(&img, 2.0), &spec).unwrap();
    let e = errors_px(&det.pixels, &det.target_points, &truth);
    let max = e.iter().cloned().fold(0.0, f64::max);
    println!("grid, noise σ=2: RMS {:.4} px, max {max:.4} px", rms(&e));
    assert!(
        det.corner_ids.len() == 48 && max < 0.1,
        "max corner error {max} px"
    );

    // Markers of the same dictionary outside the grid's ids are ignored; a grid
    // whose ids are not in view is "not found".
    let other = ArucoGridSpec {
        first_id: 40,
        ..spec.clone()
    };
    let err = detect_aruco_grid(&img, &other).unwrap_err();
    assert!(matches!(err, VisionError::MarkersNotFound { .. }), "{err}");
    let bad = ArucoGridSpec {
        first_id: 95,
        ..spec.clone()
    };
    assert!(matches!(
        detect_aruco_grid(&img, &bad).unwrap_err(),
        VisionError::InvalidTarget(_)
    ));
}

/// A single marker drawn by `aruco::drawMarker`, 400 px on a white 600x600 page.
fn marker_source(dictionary: i32, id: i32) -> Mat {
    let dict = aruco::get_predefined_dictionary_i32(dictionary).unwrap();
    let mut marker = Mat::default();
    aruco::draw_marker(&dict, id, 400, &mut marker, 1).unwrap();
    let mut page =
        Mat::new_rows_cols_with_default(600, 600, core::CV_8UC1, Scalar::all(255.0)).unwrap();
    let mut roi = Mat::roi_mut(&mut page, core::Rect::new(100, 100, 400, 400)).unwrap();
    marker.copy_to(&mut roi).unwrap();
    page
}

#[test]
fn single_markers_follow_opencvs_corner_order_and_pose_convention() {
    let m = 0.1;
    // Marker frame: centre origin, y up; source pixel of (X, Y) = 300 + 4000·(X, -Y) - 0.5.
    let a = affine(4000.0, (300.0, 300.0), true);
    for (name, dict_index, id, angles) in [
        ("DICT_APRILTAG_36h11", 20, 7, (0.3, 0.2, 0.5)),
        ("DICT_6X6_250", 10, 23, (-0.2, 0.35, -2.5)),
        ("DICT_ARUCO_ORIGINAL", 16, 100, (0.0, 0.0, 0.0)),
    ] {
        // Seen from the printed side: camera on the marker's +z side, so turn by π about x.
        let flip = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
        let base = pose(Vector3::zeros(), 0.6, angles);
        let truth = Isometry3::from_parts(base.translation, base.rotation * flip);
        let img = scene(&marker_source(dict_index, id), a, &truth, &camera());
        let det = detect_marker(&img, name, id as usize, m).unwrap();
        assert_eq!(det.corner_ids, vec![0, 1, 2, 3]);
        let e = errors_px(&det.pixels, &det.target_points, &truth);
        let max = e.iter().cloned().fold(0.0, f64::max);
        println!("{name} id {id}: RMS {:.4} px, max {max:.4} px", rms(&e));
        assert!(max < 0.1, "{name}: max corner error {max} px");
        assert!(det.refined);
        let est = board_pose(&det, &camera()).unwrap();
        let (dt, dr) = pose_error(&est.camera_from_target, &truth);
        println!("{name}: pose error {:.3} mm, {dr:.4} deg", dt * 1e3);
        assert!(dt < 3e-3 && dr < 1.0, "{name}: {dt} m, {dr} deg");

        // OpenCV's estimatePoseSingleMarkers uses the same object points and finds the
        // same pose from the same corners.
        let (k, dist) = (
            Mat::from_slice_2d(&[[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
                .unwrap(),
            Vector::<f64>::new(),
        );
        let quad: Vector<Vector<core::Point2f>> = std::iter::once(
            det.pixels
                .iter()
                .map(|p| core::Point2f::new(p.x as f32, p.y as f32))
                .collect::<Vector<_>>(),
        )
        .collect();
        let (mut rvecs, mut tvecs, mut obj) = (Mat::default(), Mat::default(), Mat::default());
        aruco::estimate_pose_single_markers(
            &quad,
            m as f32,
            &k,
            &dist,
            &mut rvecs,
            &mut tvecs,
            &mut obj,
            aruco::EstimateParameters::create().unwrap(),
        )
        .unwrap();
        let obj: Vec<core::Point3f> = obj.data_typed::<core::Point3f>().unwrap().to_vec();
        for (o, t) in obj.iter().zip(marker_target_points(m)) {
            assert!(
                (f64::from(o.x) - t.x).abs() < 1e-7 && (f64::from(o.y) - t.y).abs() < 1e-7,
                "OpenCV {o:?}, ours {t}"
            );
        }
        let t = tvecs.data_typed::<core::Vec3d>().unwrap()[0];
        let t = Vector3::new(t[0], t[1], t[2]);
        assert!((t - est.camera_from_target.translation.vector).norm() < 1e-3);
    }
}

#[test]
fn single_marker_errors_are_clear() {
    let a = affine(4000.0, (300.0, 300.0), true);
    let flip = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
    let truth = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.6), flip);
    let img = scene(&marker_source(20, 7), a, &truth, &camera());
    let err = detect_marker(&img, "DICT_APRILTAG_36h11", 8, 0.1).unwrap_err();
    assert!(matches!(err, VisionError::MarkersNotFound { .. }), "{err}");
    let err = detect_marker(&img, "DICT_APRILTAG_36h11", 587, 0.1).unwrap_err();
    assert!(matches!(err, VisionError::InvalidTarget(_)), "{err}");
    let err = detect_marker(&img, "DICT_APRILTAG_36h11", 7, -0.1).unwrap_err();
    assert!(matches!(err, VisionError::InvalidTarget(_)), "{err}");
    let err = detect_marker(&img, "APRILTAG", 7, 0.1).unwrap_err();
    assert!(matches!(err, VisionError::UnknownDictionary(_)), "{err}");

    // Two copies of the same marker: ambiguous.
    let mut twice = Mat::default();
    core::hconcat2(img.mat(), img.mat(), &mut twice).unwrap();
    let twice = GrayImage::from_mat(twice).unwrap();
    let err = detect_marker(&twice, "DICT_APRILTAG_36h11", 7, 0.1).unwrap_err();
    assert!(
        matches!(err, VisionError::DuplicateMarker { count: 2, .. }),
        "{err}"
    );
}
