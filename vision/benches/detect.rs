//! Detection time per 1280x720 frame: our `detect_checkerboard` (classic detector,
//! grid-orthogonality refinement, colour-based orientation) against OpenCV's plain
//! `findChessboardCorners` + `cornerSubPix` on the same rendered frame.
//! ChArUco: our `detect_charuco` (markers, `interpolateCornersCharuco` with the camera,
//! grid-orthogonality refinement) against OpenCV's `detectMarkers` +
//! `interpolateCornersCharuco` alone, on a 7x5-square board drawn by OpenCV and warped
//! into a 1280x720 frame.
//! Markers: an ArUco grid, a single AprilTag 36h11, the 4x3 multimarker sheet and the
//! three-face multimarker corner, each printed by `printable`/`render_face` and
//! rendered by `synth::render_planes` into a 1280x720 frame, with pose where the
//! detector gives one (multimarker).
//! `cargo bench -p b2b-vision`; `cargo test --benches -p b2b-vision` runs each once.

use std::hint::black_box;

use b2b_calib::camera::CameraModel;
use b2b_vision::multimarker::{MultimarkerConfig, detect_multimarker};
use b2b_vision::printable::{Page, marker_page, pages};
use b2b_vision::synth::{
    BoardScene, PlaneScene, TexturedPlane, render_checkerboard, render_planes,
};
use b2b_vision::{
    ArucoGridSpec, CharucoSpec, CheckerboardSpec, MarkerDictionary, Target, detect_aruco_grid,
    detect_charuco, detect_checkerboard, detect_marker, render_charuco,
};
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, Point2f, Scalar, Size, TermCriteria, Vector};
use opencv::{aruco, calib3d, core, imgproc};

fn frame() -> b2b_vision::GrayImage {
    let spec = CheckerboardSpec {
        cols: 9,
        rows: 6,
        square_m: 0.03,
    };
    let cam = CameraModel::new(1280, 720, [900.0, 900.0, 639.7, 360.2], &[]).unwrap();
    let r = UnitQuaternion::from_euler_angles(0.3, -0.2, 0.15);
    let centre = Vector3::new(0.12, 0.075, 0.0);
    let pose = Isometry3::from_parts(
        Translation3::from(Vector3::new(0.02, 0.0, 0.7) - r * centre),
        r,
    );
    let mut scene = BoardScene::new(spec, cam, pose);
    scene.noise_sigma = 2.0;
    render_checkerboard(&scene).unwrap().0
}

fn bench(c: &mut Criterion) {
    let img = frame();
    let spec = CheckerboardSpec {
        cols: 9,
        rows: 6,
        square_m: 0.03,
    };
    let mut group = c.benchmark_group("detect_1280x720_9x6");
    group.sample_size(20);
    group.bench_function("b2b_vision::detect_checkerboard", |b| {
        b.iter(|| detect_checkerboard(black_box(&img), &spec).unwrap())
    });
    group.bench_function("opencv findChessboardCorners+cornerSubPix 11x11", |b| {
        let criteria = TermCriteria::new(
            opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
            30,
            0.01,
        )
        .unwrap();
        b.iter(|| {
            let mut corners = Vector::<Point2f>::new();
            let flags = calib3d::CALIB_CB_ADAPTIVE_THRESH | calib3d::CALIB_CB_NORMALIZE_IMAGE;
            assert!(
                calib3d::find_chessboard_corners(img.mat(), Size::new(9, 6), &mut corners, flags)
                    .unwrap()
            );
            imgproc::corner_sub_pix(
                img.mat(),
                &mut corners,
                Size::new(5, 5),
                Size::new(-1, -1),
                criteria,
            )
            .unwrap();
            corners
        })
    });
    group.finish();
}

fn charuco_spec() -> CharucoSpec {
    CharucoSpec {
        squares: [7, 5],
        square_m: 0.04,
        marker_m: 0.028,
        dictionary: "DICT_5X5_100".into(),
    }
}

fn camera() -> CameraModel {
    CameraModel::new(1280, 720, [900.0, 900.0, 639.7, 360.2], &[]).unwrap()
}

/// The board drawn by OpenCV at 200 px per square, warped by `K·[r1 r2 t]·A⁻¹` into a
/// 1280x720 frame.
fn charuco_frame() -> b2b_vision::GrayImage {
    let spec = charuco_spec();
    let src = render_charuco(&spec, 200).unwrap();
    let cam = camera();
    let r = UnitQuaternion::from_euler_angles(0.3, -0.2, 0.15);
    let t = Vector3::new(0.02, 0.0, 0.6) - r * Vector3::new(0.14, 0.1, 0.0);
    let k = nalgebra::Matrix3::new(cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0);
    let rm = r.to_rotation_matrix();
    let rt = nalgebra::Matrix3::from_columns(&[
        rm.matrix().column(0).into_owned(),
        rm.matrix().column(1).into_owned(),
        t,
    ]);
    let s = 200.0 / spec.square_m;
    let a = nalgebra::Matrix3::new(s, 0.0, 199.5, 0.0, s, 199.5, 0.0, 0.0, 1.0);
    let h = k * rt * a.try_inverse().unwrap();
    let hm = Mat::from_slice_2d(&[
        [h[(0, 0)], h[(0, 1)], h[(0, 2)]],
        [h[(1, 0)], h[(1, 1)], h[(1, 2)]],
        [h[(2, 0)], h[(2, 1)], h[(2, 2)]],
    ])
    .unwrap();
    let mut out = Mat::default();
    imgproc::warp_perspective(
        src.mat(),
        &mut out,
        &hm,
        Size::new(1280, 720),
        imgproc::INTER_LINEAR,
        core::BORDER_CONSTANT,
        Scalar::all(128.0),
    )
    .unwrap();
    b2b_vision::GrayImage::from_mat(out).unwrap()
}

fn bench_charuco(c: &mut Criterion) {
    let img = charuco_frame();
    let spec = charuco_spec();
    let cam = camera();
    assert_eq!(detect_charuco(&img, &spec, &cam).unwrap().pixels.len(), 24);
    let mut group = c.benchmark_group("detect_1280x720_charuco_7x5");
    group.sample_size(20);
    group.bench_function("b2b_vision::detect_charuco", |b| {
        b.iter(|| detect_charuco(black_box(&img), &spec, &cam).unwrap())
    });
    group.bench_function("opencv detectMarkers+interpolateCornersCharuco", |b| {
        let dict = aruco::get_predefined_dictionary_i32(5).unwrap();
        let board = aruco::CharucoBoard::create(7, 5, 0.04, 0.028, &dict).unwrap();
        let params = aruco::DetectorParameters::create().unwrap();
        let k = Mat::from_slice_2d(&[
            [cam.fx, 0.0, cam.cx],
            [0.0, cam.fy, cam.cy],
            [0.0, 0.0, 1.0],
        ])
        .unwrap();
        let dist = Vector::<f64>::from_slice(&[0.0; 5]);
        b.iter(|| {
            let mut corners = Vector::<Vector<Point2f>>::new();
            let mut ids = Vector::<i32>::new();
            let mut rejected = Vector::<Vector<Point2f>>::new();
            aruco::detect_markers(
                img.mat(),
                &dict,
                &mut corners,
                &mut ids,
                &params,
                &mut rejected,
            )
            .unwrap();
            let mut ch = Vector::<Point2f>::new();
            let mut ch_ids = Vector::<i32>::new();
            let n = aruco::interpolate_corners_charuco(
                &corners,
                &ids,
                img.mat(),
                &board,
                &mut ch,
                &mut ch_ids,
                &k,
                &dist,
                2,
            )
            .unwrap();
            assert_eq!(n, 24);
            ch
        })
    });
    group.finish();
}

/// A page of `printable`, laid out with `margin`, as a textured plane in a board
/// frame (x right, y down, z into the page), its top-left corner at
/// `(-margin, -margin)`.
fn page_plane(page: &Page, margin: f64) -> TexturedPlane {
    let dpi = 600.0;
    TexturedPlane {
        texture: page.png(dpi).unwrap(),
        target_from_plane: Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
        ),
        top_left_m: nalgebra::Point2::new(-margin, margin),
        texel_m: 0.0254 / dpi,
    }
}

fn planes_frame(planes: Vec<TexturedPlane>, pose: Isometry3<f64>) -> b2b_vision::GrayImage {
    render_planes(&PlaneScene {
        camera: camera(),
        camera_from_target: pose,
        planes,
        background: 120.0,
        noise_sigma: 2.0,
        seed: 1,
        supersample: 4,
    })
    .unwrap()
}

fn look_at(eye: Vector3<f64>, at: Vector3<f64>, up: Vector3<f64>) -> Isometry3<f64> {
    let z = (at - eye).normalize();
    let y = -(up - z * up.dot(&z)).normalize();
    let x = y.cross(&z);
    let r = nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[x, y, z]));
    Isometry3::from_parts(
        Translation3::from(eye),
        UnitQuaternion::from_rotation_matrix(&r),
    )
    .inverse()
}

fn bench_markers(c: &mut Criterion) {
    let cam = camera();
    let tilted = |centre: Vector3<f64>, d: f64| {
        let r = UnitQuaternion::from_euler_angles(0.3, -0.2, 0.15);
        Isometry3::from_parts(
            Translation3::from(Vector3::new(0.02, 0.0, d) - r * centre),
            r,
        )
    };
    let grid = ArucoGridSpec {
        markers: [4, 3],
        marker_m: 0.05,
        separation_m: 0.01,
        dictionary: "DICT_6X6_250".into(),
        first_id: 0,
    };
    let grid_img = planes_frame(
        vec![page_plane(
            &pages(&Target::ArucoGrid(grid.clone()), 0.01).unwrap()[0],
            0.01,
        )],
        tilted(Vector3::new(0.115, 0.085, 0.0), 0.7),
    );
    assert_eq!(
        detect_aruco_grid(&grid_img, &grid).unwrap().pixels.len(),
        48
    );
    let tag = marker_page("DICT_APRILTAG_36h11", 7, 0.1, 0.03).unwrap();
    let tag_img = planes_frame(
        vec![page_plane(&tag, 0.03)],
        tilted(Vector3::new(0.05, 0.05, 0.0), 0.6),
    );
    detect_marker(&tag_img, "DICT_APRILTAG_36h11", 7, 0.1).unwrap();
    let mm_grid = MultimarkerConfig::grid_4x3();
    let dict4 = MarkerDictionary::parse("DICT_4X4_50").unwrap();
    let mm_grid_img = planes_frame(
        TexturedPlane::multimarker_faces(&mm_grid, &dict4, 6000.0, 0.02).unwrap(),
        look_at(
            Vector3::new(0.2, -0.15, 0.55),
            Vector3::zeros(),
            Vector3::y(),
        ),
    );
    assert_eq!(
        detect_multimarker(&mm_grid_img, &mm_grid, &dict4, &cam)
            .unwrap()
            .markers
            .len(),
        12
    );
    let corner = MultimarkerConfig::three_face_corner();
    let corner_img = planes_frame(
        TexturedPlane::multimarker_faces(&corner, &dict4, 6000.0, 0.01).unwrap(),
        look_at(
            Vector3::new(0.4, 0.4, 0.4),
            Vector3::new(0.06, 0.06, 0.06),
            Vector3::z(),
        ),
    );
    assert_eq!(
        detect_multimarker(&corner_img, &corner, &dict4, &cam)
            .unwrap()
            .markers
            .len(),
        12
    );

    let mut group = c.benchmark_group("detect_1280x720_markers");
    group.sample_size(20);
    group.bench_function("b2b_vision::detect_aruco_grid 4x3 DICT_6X6_250", |b| {
        b.iter(|| detect_aruco_grid(black_box(&grid_img), &grid).unwrap())
    });
    group.bench_function("b2b_vision::detect_marker AprilTag 36h11", |b| {
        b.iter(|| detect_marker(black_box(&tag_img), "DICT_APRILTAG_36h11", 7, 0.1).unwrap())
    });
    group.bench_function("b2b_vision::detect_multimarker 4x3 sheet (+pose)", |b| {
        b.iter(|| detect_multimarker(black_box(&mm_grid_img), &mm_grid, &dict4, &cam).unwrap())
    });
    group.bench_function(
        "b2b_vision::detect_multimarker three-face corner (+pose)",
        |b| b.iter(|| detect_multimarker(black_box(&corner_img), &corner, &dict4, &cam).unwrap()),
    );
    group.finish();
}

/// A missed view: the same frame with a band over most of the board (an occluder,
/// a view that turned away), so no detector can find it. What a failure costs
/// matters as much as a success: without `CALIB_CB_FAST_CHECK`, OpenCV's classic
/// detector tried every dilation and threshold for 30 s on such a 1280x720 frame
/// (a rendered, board-edge-on view), 27 ms with it. The peer is OpenCV's classic
/// detector with the same flags as ours, then the sector-based one.
fn bench_missed(c: &mut Criterion) {
    let board = frame();
    let (w, h) = (board.width() as usize, board.height() as usize);
    let mut pixels = board.pixels().to_vec();
    for (k, p) in pixels.iter_mut().enumerate() {
        let (x, y) = (k % w, k / w);
        // A band across the board's middle (the board spans about x 400-900).
        if (250..520).contains(&y) && x > 300 {
            *p = 70;
        }
    }
    let img = b2b_vision::GrayImage::from_raw(w as u32, h as u32, &pixels).unwrap();
    let spec = CheckerboardSpec {
        cols: 9,
        rows: 6,
        square_m: 0.03,
    };
    let mut group = c.benchmark_group("detect_1280x720_9x6_missed");
    group.sample_size(10);
    group.bench_function("b2b_vision::detect_checkerboard (fails)", |b| {
        b.iter(|| assert!(detect_checkerboard(black_box(&img), &spec).is_err()))
    });
    group.bench_function(
        "opencv findChessboardCorners (fast check) + findChessboardCornersSB (fail)",
        |b| {
            b.iter(|| {
                let mut corners = Vector::<Point2f>::new();
                let flags = calib3d::CALIB_CB_ADAPTIVE_THRESH
                    | calib3d::CALIB_CB_NORMALIZE_IMAGE
                    | calib3d::CALIB_CB_FAST_CHECK;
                let classic = calib3d::find_chessboard_corners(
                    img.mat(),
                    Size::new(9, 6),
                    &mut corners,
                    flags,
                )
                .unwrap();
                let sb = calib3d::find_chessboard_corners_sb(
                    img.mat(),
                    Size::new(9, 6),
                    &mut corners,
                    calib3d::CALIB_CB_NORMALIZE_IMAGE,
                )
                .unwrap();
                assert!(!classic && !sb);
            })
        },
    );
    group.finish();
}

criterion_group!(benches, bench, bench_charuco, bench_markers, bench_missed);
criterion_main!(benches);
