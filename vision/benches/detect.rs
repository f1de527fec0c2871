//! Detection time per 1280x720 frame: our `detect_checkerboard` (classic detector,
//! grid-orthogonality refinement, colour-based orientation) against OpenCV's plain
//! `findChessboardCorners` + `cornerSubPix` on the same rendered frame.
//! `cargo bench -p b2b-vision`; `cargo test --benches -p b2b-vision` runs each once.

use std::hint::black_box;

use b2b_calib::camera::CameraModel;
use b2b_vision::synth::{BoardScene, render_checkerboard};
use b2b_vision::{CheckerboardSpec, detect_checkerboard};
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{Point2f, Size, TermCriteria, Vector};
use opencv::{calib3d, imgproc};

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

criterion_group!(benches, bench);
criterion_main!(benches);
