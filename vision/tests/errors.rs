//! Bad input gives a clear error, never a panic.

use std::path::PathBuf;

use b2b_calib::camera::CameraModel;
use b2b_vision::{
    BoardDetection, CheckerboardSpec, CornerMethod, GrayImage, VisionError, board_pose,
    detect_checkerboard, load_gray,
};
use nalgebra::{Point2, Point3};
use opencv::core::{Mat, Scalar, Size, Vector};
use opencv::{core, imgcodecs, imgproc};

const SPEC: CheckerboardSpec = CheckerboardSpec {
    cols: 9,
    rows: 6,
    square_m: 0.0236,
};

fn visp_image(n: u32) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!(
        "../../shared/datasets/visp-franka-eye-in-hand/robot1/images/{n:03}.png"
    ))
}

#[test]
fn missing_file_names_the_file() {
    let err = load_gray(&PathBuf::from("/nonexistent/dir/board.png")).unwrap_err();
    assert!(matches!(err, VisionError::Io { .. }), "{err}");
    assert!(
        err.to_string().contains("/nonexistent/dir/board.png"),
        "{err}"
    );
}

#[test]
fn empty_random_and_truncated_files_are_corrupt() {
    let dir = tempfile::tempdir().unwrap();
    let real = std::fs::read(visp_image(1)).unwrap();
    let mut noise = Vec::new();
    let mut x = 0x1234_5678_9abc_def0u64;
    for _ in 0..4096 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        noise.push(x as u8);
    }
    for (name, bytes) in [
        ("empty.png", Vec::new()),
        ("random.png", noise),
        ("truncated.png", real[..200].to_vec()),
    ] {
        let path = dir.path().join(name);
        std::fs::write(&path, &bytes).unwrap();
        let err = load_gray(&path).unwrap_err();
        assert!(
            matches!(err, VisionError::CorruptImage { .. }),
            "{name}: {err}"
        );
        assert!(err.to_string().contains(name), "{err}");
    }
}

#[test]
fn sixteen_bit_png_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("depth.png");
    let depth =
        Mat::new_rows_cols_with_default(48, 64, core::CV_16UC1, Scalar::all(1234.0)).unwrap();
    assert!(imgcodecs::imwrite(path.to_str().unwrap(), &depth, &Vector::new()).unwrap());
    let err = load_gray(&path).unwrap_err();
    assert!(matches!(err, VisionError::SixteenBit { .. }), "{err}");
    assert!(
        err.to_string().contains("16-bit image, expected 8-bit"),
        "{err}"
    );
    assert!(err.to_string().contains("depth.png"), "{err}");
}

#[test]
fn colour_images_are_converted_to_grey() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("colour.png");
    let grey = load_gray(&visp_image(1)).unwrap();
    let mut bgr = Mat::default();
    imgproc::cvt_color(grey.mat(), &mut bgr, imgproc::COLOR_GRAY2BGR, 0).unwrap();
    assert!(imgcodecs::imwrite(path.to_str().unwrap(), &bgr, &Vector::new()).unwrap());
    let back = load_gray(&path).unwrap();
    assert_eq!((back.width(), back.height()), (640, 480));
    assert_eq!(back.pixels(), grey.pixels());
    assert!(detect_checkerboard(&back, &SPEC).is_ok());
}

#[test]
fn images_without_a_board_are_not_found_or_blurred() {
    let mut noise = vec![0u8; 640 * 480];
    let mut x = 0x9E37_79B9_7F4A_7C15u64;
    for p in &mut noise {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        *p = x as u8;
    }
    let img = GrayImage::from_raw(640, 480, &noise).unwrap();
    let err = detect_checkerboard(&img, &SPEC).unwrap_err();
    assert!(matches!(err, VisionError::BoardNotFound { .. }), "{err}");
    assert!(err.to_string().contains("9x6"), "{err}");

    let flat = GrayImage::from_raw(640, 480, &vec![128; 640 * 480]).unwrap();
    let err = detect_checkerboard(&flat, &SPEC).unwrap_err();
    assert!(matches!(err, VisionError::Blurred { .. }), "{err}");

    for (w, h) in [(1, 1), (3, 200), (17, 9)] {
        let tiny = GrayImage::from_raw(w, h, &vec![0; (w * h) as usize]).unwrap();
        assert!(detect_checkerboard(&tiny, &SPEC).is_err());
    }
}

#[test]
fn a_heavily_blurred_board_is_reported_as_blurred() {
    let sharp = load_gray(&visp_image(1)).unwrap();
    let mut blurred = Mat::default();
    imgproc::gaussian_blur(
        sharp.mat(),
        &mut blurred,
        Size::new(0, 0),
        6.0,
        6.0,
        core::BORDER_DEFAULT,
    )
    .unwrap();
    let img = GrayImage::from_mat(blurred).unwrap();
    let var = img.laplacian_variance().unwrap();
    println!(
        "laplacian variance: sharp {:.0}, blurred {var:.1}",
        sharp.laplacian_variance().unwrap()
    );
    match detect_checkerboard(&img, &SPEC) {
        // OpenCV may still find a board this blurred; then the corners must still be usable.
        Ok(det) => assert_eq!(det.pixels.len(), 54, "laplacian var {var}"),
        Err(err) => assert!(
            matches!(err, VisionError::Blurred { .. }),
            "laplacian var {var}: {err}"
        ),
    }
}

#[test]
fn wrong_board_sizes_are_not_found_or_refused() {
    let img = load_gray(&visp_image(1)).unwrap();
    // Bigger than the printed board: not there.
    for (cols, rows) in [(10, 7), (11, 6), (9, 8)] {
        let spec = CheckerboardSpec {
            cols,
            rows,
            square_m: 0.0236,
        };
        let err = detect_checkerboard(&img, &spec).unwrap_err();
        assert!(
            matches!(err, VisionError::BoardNotFound { .. }),
            "{cols}x{rows}: {err}"
        );
    }
    // Symmetric specs are refused before looking; impossible ones are invalid.
    let err = detect_checkerboard(
        &img,
        &CheckerboardSpec {
            cols: 7,
            rows: 5,
            square_m: 0.0236,
        },
    )
    .unwrap_err();
    assert!(matches!(err, VisionError::AmbiguousOrientation(_)), "{err}");
    for spec in [
        CheckerboardSpec {
            cols: 2,
            rows: 5,
            square_m: 0.02,
        },
        CheckerboardSpec {
            cols: 0,
            rows: 0,
            square_m: 0.02,
        },
        CheckerboardSpec {
            cols: 9,
            rows: 6,
            square_m: -1.0,
        },
        CheckerboardSpec {
            cols: 9,
            rows: 6,
            square_m: f64::NAN,
        },
        CheckerboardSpec {
            cols: 100_000,
            rows: 3,
            square_m: 0.02,
        },
    ] {
        let err = detect_checkerboard(&img, &spec).unwrap_err();
        assert!(
            matches!(err, VisionError::InvalidSpec(_)),
            "{spec:?}: {err}"
        );
    }
}

#[test]
fn raw_buffers_of_the_wrong_length_are_refused() {
    assert!(matches!(
        GrayImage::from_raw(10, 10, &[0; 99]),
        Err(VisionError::InvalidImage(_))
    ));
    assert!(matches!(
        GrayImage::from_raw(0, 10, &[]),
        Err(VisionError::InvalidImage(_))
    ));
    assert!(matches!(
        GrayImage::from_mat(Mat::default()),
        Err(VisionError::InvalidImage(_))
    ));
}

#[test]
fn pose_rejects_too_few_or_inconsistent_points() {
    let cam = CameraModel::new(640, 480, [600.0, 600.0, 320.0, 240.0], &[]).unwrap();
    let method = CornerMethod::SectorBased { flags: 0 };
    let three = BoardDetection {
        target_points: vec![Point3::origin(); 3],
        corner_ids: vec![0, 1, 2],
        pixels: vec![Point2::origin(); 3],
        method,
        refined: false,
    };
    assert!(matches!(
        board_pose(&three, &cam),
        Err(VisionError::TooFewCorners {
            found: 3,
            needed: 4
        })
    ));
    let mismatched = BoardDetection {
        pixels: vec![Point2::origin(); 5],
        ..three.clone()
    };
    assert!(matches!(
        board_pose(&mismatched, &cam),
        Err(VisionError::Pose(_))
    ));
    let off_plane = BoardDetection {
        target_points: (0..4).map(|k| Point3::new(k as f64, 0.0, 1.0)).collect(),
        corner_ids: vec![0, 1, 2, 3],
        pixels: vec![Point2::new(1.0, 2.0); 4],
        method,
        refined: false,
    };
    assert!(matches!(
        board_pose(&off_plane, &cam),
        Err(VisionError::Pose(_))
    ));
}
