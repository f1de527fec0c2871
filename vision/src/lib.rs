//! The vision boundary: the only crate in the workspace that links OpenCV.
//!
//! Images come in as 8-bit grey ([`load_gray`], [`GrayImage`]); boards come out as
//! corners in the target frame of `shared/dataset-format.md` ([`detect_checkerboard`],
//! [`BoardDetection`]) and as `camera_from_target` poses ([`board_pose`]). Everything
//! above this crate works with nalgebra types and [`b2b_calib::camera::CameraModel`];
//! no OpenCV type crosses the API except [`GrayImage::mat`], for callers that want to
//! hand frames to other OpenCV code.
//!
//! # Corner detection: what was measured and chosen
//!
//! Rendered 9x6 boards with exactly known corners ([`synth`]: box-filtered by 16x16
//! supersampling, so the image of a corner is exactly its projection), 1280x720,
//! f = 900 px, squares ≈ 45 px (22 px for "far"), tilted up to 35°, both 180°
//! orientations, with and without Gaussian noise of σ = 2 grey levels. RMS corner
//! error in px (bias below 0.01 px unless noted); times are per frame in the dev
//! profile (OpenCV itself is optimised), from `tests/accuracy.rs`
//! (`cargo test -p b2b-vision --test accuracy -- --ignored --nocapture`):
//!
//! | detector                                      | frontal | tilt 35° | far 22 px | noise σ=2 | ms |
//! |-----------------------------------------------|---------|----------|-----------|-----------|----|
//! | `findChessboardCornersSB` (no flags)          | 0.024   | 0.061    | 0.186 (bias 0.14) | 0.026–0.061 | 120 |
//! | SB `NORMALIZE_IMAGE`                          | 0.029–0.034 | 0.069–0.081 | 0.185  | 0.043–0.075 | 190 |
//! | SB `ACCURACY`                                 | 0.013–0.015 | 0.031–0.033 | 0.121 (bias 0.07) | 0.018–0.034 | 600 |
//! | SB `ACCURACY \| NORMALIZE_IMAGE`              | 0.023–0.025 | 0.044–0.061 | 0.113 | 0.040–0.052 | 500 |
//! | classic + `cornerSubPix` 11x11                | 0.049–0.050 | 0.038–0.052 | 0.042 | 0.040–0.052 | 1.5 |
//! | classic + `cornerSubPix` 7x7                  | 0.073   | 0.052–0.068 | 0.041  | 0.053–0.075 | 1.2 |
//! | classic + `cornerSubPix` adaptive window      | 0.044   | 0.040–0.048 | 0.043  | 0.041–0.045 | 1.6 |
//! | **any of the above + [`checkerboard::refine_corners`]** | **0.012** | **0.019–0.027** | **0.025** | **0.015–0.020** | +3 |
//!
//! (`EXHAUSTIVE` changes nothing on these frames.) So neither OpenCV detector
//! reaches 0.05 px everywhere: the sector-based one is biased on small squares even
//! with `ACCURACY`, and `cornerSubPix` levels off at 0.04–0.05 px. The gradient-
//! orthogonality refinement evaluated on the pixel grid (no bilinear resampling of
//! the window) lands on the same corners from every detector's output, at 0.012–0.027
//! px with no bias, so the detector order ([`DEFAULT_METHODS`]) is chosen for speed and
//! robustness alone: classic first (~50x faster), then the sector-based detector for
//! the boards the classic one misses, then `EXHAUSTIVE`. The test
//! `default_detector_is_accurate_and_oriented_on_rendered_boards` holds this at
//! < 0.05 px RMS (< 0.15 px with noise).
//!
//! On the real ViSP Franka images (640x480, 8 views of a 9x6 board) the detector
//! finds 8/8 boards and [`board_pose`] leaves 0.28–0.54 px RMS (mean 0.41) with the
//! shipped zero-distortion intrinsics; every detector gives the same or worse, and
//! adding k1 = 0.05 brings them to 0.20–0.38 px, so what is left is the lens, not the
//! corners. Through ViSP's hand-eye, the 8 `base_from_target` poses agree to 6.5 mm and
//! 1.1°, and their mean is ViSP's published one.
//!
//! Speed (`cargo bench -p b2b-vision`, release, one rendered 1280x720 frame with
//! noise, this 2-core machine): [`detect_checkerboard`] 3.0 ms against 1.44 ms for
//! OpenCV's plain `findChessboardCorners` + `cornerSubPix`; the extra 1.5 ms is
//! the refinement and the orientation check.
//!
//! # Fiducial targets
//!
//! [`markers`] detects ChArUco boards ([`detect_charuco`]), ArUco grid boards
//! ([`detect_aruco_grid`]) and single ArUco/AprilTag markers ([`detect_marker`]) with
//! OpenCV 4.6's contrib `aruco` module, by the dictionary names of the dataset format
//! ([`MarkerDictionary`]), and returns the same [`BoardDetection`] as the checkerboard.
//! A ChArUco board may be partly hidden: the corners seen are returned by id.
//!
//! [`multimarker`] reads ARToolKit-style multimarker files ([`MultimarkerConfig`],
//! millimetres, barcode ids = ids of the dataset's dictionary) and fits
//! `camera_from_target` to every visible marker's corners at once
//! ([`detect_multimarker`]: IPPE + LM when the corners seen are coplanar, with an
//! ambiguity check; SQPnP + LM otherwise). On frames rendered by
//! [`synth::render_planes`] (1280x720, f = 900 px, `tests/multimarker.rs`): the 4x3
//! sheet 0.003–0.013 mm / ≤ 0.012° from the true pose (frontal, tilted, noise σ = 2,
//! 10 of 12 markers in the frame), the three-face corner 0.008–0.14 mm / ≤ 0.04°
//! (12 markers), its floor alone 0.26 mm / 0.00°.
//!
//! [`intrinsics`] calibrates a camera from checkerboard or ChArUco images with
//! per-image errors and rejections ([`calibrate_intrinsics`]); on rendered 640x480
//! views with fx = 600, k1 = -0.12 it recovers fx within 0.05 % (`tests/intrinsics.rs`).
//! [`printable`] lays every target kind out as SVG (exact size in mm) and PNG (at a
//! DPI), plus the multimarker file.
//!
//! # One target model
//!
//! [`Target`] is the target every path works with: detection and pose
//! ([`Target::detect`]), the points, centre, view axis and symmetry the planner and
//! the symmetric-board rule need, intrinsics ([`calibrate_intrinsics`]: checkerboard
//! or ChArUco) and printing ([`printable::pages`]). The pipeline makes it from
//! `dataset.json`'s `target` block (the file schema, which names a multimarker set
//! by its file).
//!
//! # Orientation
//!
//! OpenCV's detectors return the grid starting at any of its four corners. The
//! target frame is fixed by handedness (z into the board) and by the square colours;
//! [`checkerboard`] explains the rule. Boards with `cols + rows` even look the same
//! turned by 180° (square ones possibly by 90°): [`detect_checkerboard`] refuses them
//! as [`VisionError::AmbiguousOrientation`], and
//! [`detect_checkerboard_up_to_symmetry`] returns their corners in one labelling plus
//! the board's symmetry, for a caller that decides the labelling from robot motion.
//!
//! # Errors
//!
//! One [`VisionError`]; nothing panics on bad input (missing, empty, corrupt or
//! 16-bit files, boards of the wrong size, images without a board, tiny images).

mod error;

pub mod checkerboard;
pub mod features;
pub mod image;
pub mod intrinsics;
pub mod markers;
pub mod multimarker;
pub mod pose;
pub mod printable;
pub mod synth;
pub mod target;

pub use checkerboard::{
    BoardDetection, CheckerboardSpec, CornerMethod, DEFAULT_METHODS, detect_checkerboard,
    detect_checkerboard_up_to_symmetry, detect_checkerboard_with,
};
pub use error::VisionError;
pub use image::{
    GrayImage, MAX_IMAGE_PIXELS, check_image_file, decode_gray, header_size, image_file_size,
    load_gray, load_gray_sized,
};
pub use intrinsics::{
    DistortionTerms, IntrinsicsOptions, IntrinsicsResult, calibrate_from_detections,
    calibrate_intrinsics, calibrate_intrinsics_from_dir,
};
pub use markers::{
    ArucoGridSpec, CharucoSpec, MarkerDictionary, detect_aruco_grid, detect_charuco, detect_marker,
    render_charuco,
};
pub use multimarker::{
    MultimarkerConfig, MultimarkerDetection, detect_multimarker, multimarker_pose,
};
pub use pose::{PoseEstimate, board_pose};
pub use target::Target;
