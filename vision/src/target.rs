//! The one target model: what every path that looks at, prints, plans about or
//! calibrates from a target works with (the offline pipeline and the live agent's
//! detection, the intrinsics calibration, the printable sheet).
//!
//! `dataset.json`'s `target` block (`b2b_dataset::Target`) is the file schema; it
//! names a multimarker set by its file. The pipeline reads that file and checks the
//! sizes (`b2b_pipeline::target_from_manifest`), giving a [`Target`] whose parts are
//! validated specs and a parsed multimarker set. What stays private to the detectors
//! (OpenCV's boards and dictionaries, the corner search) never leaves this crate.

use b2b_calib::camera::CameraModel;
use b2b_calib::symmetry::TargetSymmetry;
use nalgebra::{Point3, Vector3};

use crate::checkerboard::{BoardDetection, CheckerboardSpec};
use crate::error::VisionError;
use crate::image::GrayImage;
use crate::markers::{ArucoGridSpec, CharucoSpec, MarkerDictionary};
use crate::multimarker::MultimarkerConfig;
use crate::pose::PoseEstimate;

/// A calibration target, ready for detection, printing and planning.
#[derive(Debug, Clone, PartialEq)]
pub enum Target {
    Checkerboard(CheckerboardSpec),
    Charuco(CharucoSpec),
    ArucoGrid(ArucoGridSpec),
    /// An ARToolKit-style multimarker set (its file already read) and the dictionary
    /// its barcode ids belong to.
    Multimarker {
        config: MultimarkerConfig,
        dictionary: MarkerDictionary,
    },
}

impl Target {
    /// The kind as `dataset.json`'s `target.kind` names it (`checkerboard`,
    /// `charuco`, `aruco_grid`, `multimarker`).
    pub fn kind(&self) -> &'static str {
        match self {
            Target::Checkerboard(_) => "checkerboard",
            Target::Charuco(_) => "charuco",
            Target::ArucoGrid(_) => "aruco_grid",
            Target::Multimarker { .. } => "multimarker",
        }
    }

    /// Every point of the target (corners by id), in the target frame.
    pub fn all_points(&self) -> Vec<Point3<f64>> {
        match self {
            Target::Checkerboard(s) => (0..s.corner_count()).map(|k| s.target_point(k)).collect(),
            Target::Charuco(s) => (0..s.corner_count()).map(|k| s.target_point(k)).collect(),
            Target::ArucoGrid(s) => (0..4 * s.marker_count())
                .map(|k| s.target_point(k))
                .collect(),
            Target::Multimarker { config, .. } => {
                config.markers.iter().flat_map(|m| m.corners()).collect()
            }
        }
    }

    /// The direction (target frame, unit) from the target towards where it is seen
    /// from: a board's printed side faces -z of its frame (z points into it); a
    /// multimarker set is seen along the mean of its markers' outward normals (+z
    /// of each marker, ARToolKit's convention): +z of a planar sheet, the middle of
    /// a three-face corner's view.
    pub fn view_axis(&self) -> Vector3<f64> {
        let minus_z = -Vector3::z();
        match self {
            Target::Multimarker { config, .. } => {
                let sum: Vector3<f64> = config
                    .markers
                    .iter()
                    .map(|m| m.set_from_marker.rotation * Vector3::z())
                    .sum();
                sum.try_normalize(1e-9).unwrap_or(Vector3::z())
            }
            _ => minus_z,
        }
    }

    /// The centroid of [`Target::all_points`].
    pub fn centre(&self) -> Point3<f64> {
        let pts = self.all_points();
        Point3::from(pts.iter().map(|p| p.coords).sum::<Vector3<f64>>() / pts.len().max(1) as f64)
    }

    /// The labellings of the target that no image can tell apart (only the identity
    /// unless it is a checkerboard with `cols + rows` even).
    pub fn symmetry(&self) -> TargetSymmetry {
        match self {
            Target::Checkerboard(s) => s.symmetry(),
            _ => TargetSymmetry::trivial(self.all_points().len()),
        }
    }

    /// The target for messages ("8x6 checkerboard (inner corners; 9x7 squares)").
    pub fn describe(&self) -> String {
        match self {
            Target::Checkerboard(s) => format!(
                "{}x{} checkerboard (inner corners; {}x{} squares)",
                s.cols,
                s.rows,
                s.cols + 1,
                s.rows + 1
            ),
            Target::Charuco(s) => format!("{}x{} ChArUco board", s.squares[0], s.squares[1]),
            Target::ArucoGrid(s) => {
                format!("{}x{} ArUco grid", s.markers[0], s.markers[1])
            }
            Target::Multimarker { config, .. } => {
                format!("multimarker set of {} markers", config.markers.len())
            }
        }
    }

    /// Whether this is a board (checkerboard, ChArUco, ArUco grid) rather than a
    /// multimarker set.
    pub fn is_board(&self) -> bool {
        !matches!(self, Target::Multimarker { .. })
    }

    /// Finds the target in an image and fits `camera_from_target`: the corners seen
    /// (target points and pixels) and the pose with its residuals.
    /// A symmetric checkerboard is refused ([`VisionError::AmbiguousOrientation`]);
    /// [`Target::detect_up_to_symmetry`] returns it in some labelling.
    pub fn detect(
        &self,
        img: &GrayImage,
        camera: &CameraModel,
    ) -> Result<(BoardDetection, PoseEstimate), VisionError> {
        self.detect_impl(img, camera, false)
    }

    /// [`Target::detect`], but a symmetric checkerboard comes back in one of the
    /// labellings of [`Target::symmetry`], which the caller must resolve.
    pub fn detect_up_to_symmetry(
        &self,
        img: &GrayImage,
        camera: &CameraModel,
    ) -> Result<(BoardDetection, PoseEstimate), VisionError> {
        self.detect_impl(img, camera, true)
    }

    fn detect_impl(
        &self,
        img: &GrayImage,
        camera: &CameraModel,
        up_to_symmetry: bool,
    ) -> Result<(BoardDetection, PoseEstimate), VisionError> {
        // A multimarker set's detector fits its own pose (over every marker seen);
        // boards go through the one corner detection and PnP.
        if let Target::Multimarker { config, dictionary } = self {
            let m = crate::detect_multimarker(img, config, dictionary, camera)?;
            let pose = PoseEstimate {
                camera_from_target: m.camera_from_target,
                residuals_px: m.residuals_px,
                rms_px: m.rms_px,
            };
            return Ok((m.detection, pose));
        }
        let det = self.detect_corners_impl(img, camera, up_to_symmetry)?;
        let pose = crate::board_pose(&det, camera)?;
        Ok((det, pose))
    }

    /// Finds the target's corners in an image. `camera` may be a rough guess: the
    /// checkerboard and ArUco grid detectors do not use it, ChArUco uses it to
    /// predict corners from the markers (then snaps them to the image), and a
    /// multimarker set's corners are the markers' own.
    pub fn detect_corners(
        &self,
        img: &GrayImage,
        camera: &CameraModel,
    ) -> Result<BoardDetection, VisionError> {
        self.detect_corners_impl(img, camera, false)
    }

    /// [`Target::detect_corners`], but a symmetric checkerboard comes back in one of
    /// the labellings of [`Target::symmetry`], which the caller must resolve.
    pub fn detect_corners_up_to_symmetry(
        &self,
        img: &GrayImage,
        camera: &CameraModel,
    ) -> Result<BoardDetection, VisionError> {
        self.detect_corners_impl(img, camera, true)
    }

    fn detect_corners_impl(
        &self,
        img: &GrayImage,
        camera: &CameraModel,
        up_to_symmetry: bool,
    ) -> Result<BoardDetection, VisionError> {
        match self {
            Target::Checkerboard(s) if up_to_symmetry => {
                crate::detect_checkerboard_up_to_symmetry(img, s).map(|(det, _)| det)
            }
            Target::Checkerboard(s) => crate::detect_checkerboard(img, s),
            Target::Charuco(s) => crate::detect_charuco(img, s, camera),
            Target::ArucoGrid(s) => crate::detect_aruco_grid(img, s),
            Target::Multimarker { config, dictionary } => {
                crate::detect_multimarker(img, config, dictionary, camera).map(|m| m.detection)
            }
        }
    }

    /// `camera_from_target` of corners found by [`Target::detect_corners`].
    pub fn pose(
        &self,
        det: &BoardDetection,
        camera: &CameraModel,
    ) -> Result<PoseEstimate, VisionError> {
        match self {
            Target::Multimarker { .. } => {
                crate::multimarker_pose(&det.target_points, &det.pixels, camera)
                    .map(|(pose, _)| pose)
            }
            _ => crate::board_pose(det, camera),
        }
    }
}
