//! Fiducial targets: ChArUco boards, ArUco grid boards and single ArUco/AprilTag markers.
//!
//! All of it is OpenCV 4.6's contrib `aruco` module (`detectMarkers`,
//! `interpolateCornersCharuco`, `CharucoBoard`, `GridBoard`), not the ≥ 4.7 objdetect
//! `ArucoDetector`, which the installed OpenCV does not have. The results are
//! [`BoardDetection`]s, so [`crate::board_pose`] works on every target alike.
//!
//! # Choices
//!
//! - **Dictionaries** are named as OpenCV names them (`DICT_5X5_100`, `DICT_APRILTAG_36h11`,
//!   …; [`MarkerDictionary`]). Unknown names are refused with
//!   [`VisionError::UnknownDictionary`]; ids that the dictionary does not hold with
//!   [`VisionError::InvalidTarget`], before OpenCV could assert on them.
//! - **Target frames** are OpenCV's, as `shared/dataset-format.md` requires:
//!   - ChArUco: origin at the outer corner of square (0, 0), x along the `squares[0]`
//!     columns, y along the rows, z into the board; corner id `k` is inner corner
//!     `(k % (cols-1), k / (cols-1))` at `((k % (cols-1) + 1)·square, (k / (cols-1) + 1)·square, 0)`
//!     ([`CharucoSpec::target_point`]; a test checks it against OpenCV's
//!     `chessboardCorners`, and [`detect_charuco`] refuses to run if they ever differ).
//!   - ArUco grid: OpenCV 4.6's `GridBoard` layout, marker `(i, j)` (id
//!     `first_id + j·cols + i`) with its top-left corner at `(i·(m+sep), j·(m+sep), 0)`
//!     and its corners clockwise in the image (top-left, top-right, bottom-right,
//!     bottom-left); corner id `4·(id - first_id) + c` ([`ArucoGridSpec::target_point`],
//!     checked against `GridBoard::objPoints` the same way).
//!   - Single marker: the frame of OpenCV's `estimatePoseSingleMarkers` (default
//!     `ARUCO_CCW_CENTER`): origin at the marker centre, x right, y **up**, z out of the
//!     printed side, corners top-left `(-m/2, m/2)`, top-right `(m/2, m/2)`, bottom-right
//!     `(m/2, -m/2)`, bottom-left `(-m/2, -m/2)`.
//! - **ChArUco corners** come from `interpolateCornersCharuco` *with* the camera
//!   matrix and distortion: the board pose from the markers predicts every chessboard
//!   corner (through the lens model, so distortion is handled), then `cornerSubPix`
//!   and [`refine_corners`] refine each one (see the measurements below). Without the
//!   camera, OpenCV interpolates with local homographies, which is worse under
//!   distortion. A corner is kept only when both of the markers that
//!   touch it were seen (`minMarkers = 2`), so corners next to a hidden or missed marker
//!   are left out rather than guessed: on a partly covered board `corner_ids` lists
//!   exactly the corners that were seen, and [`crate::board_pose`] works on them.
//!   Fewer than [`MIN_CHARUCO_CORNERS`] corners, or corners all on one line, are refused.
//! - **Marker corners** (grid and single marker) are refined with OpenCV's
//!   `CORNER_REFINE_SUBPIX`, then moved to the intersections of the marker's four
//!   fitted edges (`refine_marker_quad`, see the measurements below). A marker id that appears twice in a grid is dropped (a
//!   reflection or a second board would otherwise give wrong correspondences);
//!   [`detect_marker`] reports it as [`VisionError::DuplicateMarker`].
//!
//! # What was measured (`tests/markers.rs`)
//!
//! Targets drawn by OpenCV itself, warped by an exact homography into 1280x720 frames
//! (f = 900 px, 4x supersampled), so every true corner is known:
//!
//! | corners                                         | RMS px | max px | pose error |
//! |-------------------------------------------------|--------|--------|------------|
//! | ChArUco, OpenCV `interpolateCornersCharuco` alone | 0.72 | 0.86 | — |
//! | ChArUco + [`refine_corners`] (7x5 / 8x6, tilted ≤ 25°) | 0.035–0.05 | 0.097 | 0.04 mm, 0.01° |
//! | ChArUco, 30 % of the board covered (16 of 24 corners) | — | 0.051 | 0.04 mm, 0.02° |
//! | ChArUco + refinement, noise σ = 2 grey levels     | 0.004–0.054 | 0.097 | — |
//! | markers, OpenCV `CORNER_REFINE_SUBPIX` (grid, 36h11, 6x6, original) | 0.09–0.25 | 0.39 | 0.1–0.8 mm |
//! | markers, OpenCV `CORNER_REFINE_CONTOUR` / `_APRILTAG` | 0.60 | 0.80 | — |
//! | markers, `SUBPIX` + edge-line refinement        | 0.002–0.010 | 0.025 | 0.01–0.04 mm |
//! | the same, noise σ = 2 (grid)                    | 0.012  | 0.028  | — |
//!
//! OpenCV 4.6's ChArUco corners sit about 0.5 px off along both axes on these frames
//! (even frontally, on a perfectly sharp board), so the corners are refined again with
//! the crate's grid-orthogonality refinement ([`refine_corners`]), in a window kept
//! inside the clean checker pattern around each corner (see `charuco_refine_window`);
//! that brings them to the checkerboard's accuracy. Marker corners are L-corners, which
//! `cornerSubPix` pulls inwards by up to 0.4 px, and OpenCV's other two methods are
//! worse; fitting the four straight edges and intersecting them
//! (`refine_marker_quad`) removes that bias. The edges are fitted as straight lines in
//! the distorted image (only their middle 70 % is used); with strong lens distortion
//! on large markers a curved-edge fit would be better (not done).
//!
//! Speed (`cargo bench -p b2b-vision`, release, 7x5 board in a 1280x720 frame):
//! [`detect_charuco`] 3.9 ms, the same as OpenCV's `detectMarkers` +
//! `interpolateCornersCharuco` alone (3.7–4.2 ms); the refinement costs well under the
//! run-to-run spread.
//!
//! # The OpenCV 4.6 ChArUco trap
//!
//! OpenCV(-contrib) 4.6.0 changed the layout of ChArUco boards with an **even number of
//! rows** (opencv_contrib #3291): boards printed from OpenCV ≤ 4.5.5 or bought ready-made
//! may not match what 4.6 detects, and 4.6 has no legacy switch. Boards with an odd
//! number of rows are the same in every version. [`render_charuco`] draws boards with
//! the same OpenCV that detects them, so printed targets and tests always agree.

use std::fmt;
use std::str::FromStr;

use b2b_calib::camera::CameraModel;
use nalgebra::{Point2, Point3, Vector2};
use opencv::aruco::{self, PREDEFINED_DICTIONARY_NAME as Dict};
use opencv::core::{Mat, Point2f, Ptr, Size, Vector};
use opencv::prelude::*;

use crate::checkerboard::{BoardDetection, CornerMethod, refine_corners};
use crate::error::{CvContext, VisionError};
use crate::image::GrayImage;
use crate::pose::camera_matrices;

/// The fewest ChArUco corners [`detect_charuco`] returns: fewer are too few for a
/// trustworthy pose (the planar PnP needs 4, and a handful more make it robust).
pub const MIN_CHARUCO_CORNERS: usize = 6;

/// Largest number of squares or markers per side accepted in a spec.
const MAX_SIDE: usize = 200;

/// Largest side, in pixels, of an image [`render_charuco`] draws.
const MAX_RENDER_SIDE: usize = 20_000;

/// OpenCV's predefined dictionaries: name, id, number of markers.
const DICTIONARIES: [(&str, Dict, usize); 21] = [
    ("DICT_4X4_50", Dict::DICT_4X4_50, 50),
    ("DICT_4X4_100", Dict::DICT_4X4_100, 100),
    ("DICT_4X4_250", Dict::DICT_4X4_250, 250),
    ("DICT_4X4_1000", Dict::DICT_4X4_1000, 1000),
    ("DICT_5X5_50", Dict::DICT_5X5_50, 50),
    ("DICT_5X5_100", Dict::DICT_5X5_100, 100),
    ("DICT_5X5_250", Dict::DICT_5X5_250, 250),
    ("DICT_5X5_1000", Dict::DICT_5X5_1000, 1000),
    ("DICT_6X6_50", Dict::DICT_6X6_50, 50),
    ("DICT_6X6_100", Dict::DICT_6X6_100, 100),
    ("DICT_6X6_250", Dict::DICT_6X6_250, 250),
    ("DICT_6X6_1000", Dict::DICT_6X6_1000, 1000),
    ("DICT_7X7_50", Dict::DICT_7X7_50, 50),
    ("DICT_7X7_100", Dict::DICT_7X7_100, 100),
    ("DICT_7X7_250", Dict::DICT_7X7_250, 250),
    ("DICT_7X7_1000", Dict::DICT_7X7_1000, 1000),
    ("DICT_ARUCO_ORIGINAL", Dict::DICT_ARUCO_ORIGINAL, 1024),
    ("DICT_APRILTAG_16h5", Dict::DICT_APRILTAG_16h5, 30),
    ("DICT_APRILTAG_25h9", Dict::DICT_APRILTAG_25h9, 35),
    ("DICT_APRILTAG_36h10", Dict::DICT_APRILTAG_36h10, 2320),
    ("DICT_APRILTAG_36h11", Dict::DICT_APRILTAG_36h11, 587),
];

/// One of OpenCV's predefined marker dictionaries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct MarkerDictionary {
    index: usize,
}

impl MarkerDictionary {
    /// Parses an OpenCV dictionary name (`DICT_4X4_50` … `DICT_7X7_1000`,
    /// `DICT_ARUCO_ORIGINAL`, `DICT_APRILTAG_16h5/25h9/36h10/36h11`); letter case and
    /// surrounding spaces are ignored.
    pub fn parse(name: &str) -> Result<Self, VisionError> {
        let trimmed = name.trim();
        DICTIONARIES
            .iter()
            .position(|(n, ..)| n.eq_ignore_ascii_case(trimmed))
            .map(|index| MarkerDictionary { index })
            .ok_or_else(|| VisionError::UnknownDictionary(name.to_string()))
    }

    /// Every predefined dictionary.
    pub fn all() -> impl Iterator<Item = MarkerDictionary> {
        (0..DICTIONARIES.len()).map(|index| MarkerDictionary { index })
    }

    /// OpenCV's name, e.g. `DICT_APRILTAG_36h11`.
    pub fn name(&self) -> &'static str {
        DICTIONARIES[self.index].0
    }

    /// Number of markers: valid ids are `0..marker_count()`.
    pub fn marker_count(&self) -> usize {
        DICTIONARIES[self.index].2
    }

    pub(crate) fn opencv(&self) -> Result<Ptr<aruco::Dictionary>, VisionError> {
        aruco::get_predefined_dictionary(DICTIONARIES[self.index].1).cv("getPredefinedDictionary")
    }

    fn check_ids(&self, first: usize, count: usize, what: &str) -> Result<(), VisionError> {
        if first.saturating_add(count) > self.marker_count() {
            return Err(VisionError::InvalidTarget(format!(
                "{what} needs marker ids {first}..{}, but {} has only ids 0..{}",
                first.saturating_add(count),
                self.name(),
                self.marker_count()
            )));
        }
        Ok(())
    }
}

impl FromStr for MarkerDictionary {
    type Err = VisionError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        MarkerDictionary::parse(s)
    }
}

impl fmt::Display for MarkerDictionary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

fn positive(what: &str, v: f64) -> Result<f32, VisionError> {
    // OpenCV stores board lengths as f32.
    if v.is_finite() && v > 0.0 && v < 1e6 {
        Ok(v as f32)
    } else {
        Err(VisionError::InvalidTarget(format!(
            "{what} {v} m must be positive and finite"
        )))
    }
}

fn side(what: &str, [c, r]: [usize; 2], min: usize) -> Result<(i32, i32), VisionError> {
    if c < min || r < min || c > MAX_SIDE || r > MAX_SIDE {
        return Err(VisionError::InvalidTarget(format!(
            "{c}x{r} {what}: need {min} to {MAX_SIDE} along each side"
        )));
    }
    Ok((c as i32, r as i32))
}

/// A ChArUco board, as `shared/dataset-format.md` describes it.
#[derive(Debug, Clone, PartialEq)]
pub struct CharucoSpec {
    /// Squares `[columns, rows]` (not inner corners).
    pub squares: [usize; 2],
    pub square_m: f64,
    pub marker_m: f64,
    /// OpenCV dictionary name, e.g. `DICT_5X5_100`.
    pub dictionary: String,
}

impl CharucoSpec {
    /// Checks the spec and returns its dictionary: at least 2x2 squares, markers
    /// smaller than squares, and enough ids in the dictionary for the
    /// `cols·rows / 2` markers (ids `0..`).
    pub fn validate(&self) -> Result<MarkerDictionary, VisionError> {
        side("ChArUco squares", self.squares, 2)?;
        let s = positive("square size", self.square_m)?;
        let m = positive("marker size", self.marker_m)?;
        if m >= s {
            return Err(VisionError::InvalidTarget(format!(
                "marker size {} m must be smaller than the square size {} m",
                self.marker_m, self.square_m
            )));
        }
        let dict = MarkerDictionary::parse(&self.dictionary)?;
        dict.check_ids(0, self.marker_count(), "the ChArUco board")?;
        Ok(dict)
    }

    /// Number of ChArUco (inner chessboard) corners, `(cols-1)·(rows-1)`.
    pub fn corner_count(&self) -> usize {
        self.squares[0].saturating_sub(1) * self.squares[1].saturating_sub(1)
    }

    /// Number of markers (in the white squares), `cols·rows / 2`.
    pub fn marker_count(&self) -> usize {
        self.squares[0] * self.squares[1] / 2
    }

    /// ChArUco corner `id` in OpenCV's board frame:
    /// `((id % (cols-1) + 1)·square, (id / (cols-1) + 1)·square, 0)`.
    pub fn target_point(&self, id: usize) -> Point3<f64> {
        let per_row = self.squares[0].saturating_sub(1).max(1);
        let (i, j) = (id % per_row, id / per_row);
        Point3::new(
            (i + 1) as f64 * self.square_m,
            (j + 1) as f64 * self.square_m,
            0.0,
        )
    }

    pub(crate) fn board(
        &self,
        dict: &MarkerDictionary,
    ) -> Result<Ptr<aruco::CharucoBoard>, VisionError> {
        let (c, r) = side("ChArUco squares", self.squares, 2)?;
        let board = aruco::CharucoBoard::create(
            c,
            r,
            positive("square size", self.square_m)?,
            positive("marker size", self.marker_m)?,
            &dict.opencv()?,
        )
        .cv("CharucoBoard::create")?;
        // Our target points must be OpenCV's (f32 rounding aside).
        let corners = board.chessboard_corners();
        let tol = 1e-5 * self.square_m * (c.max(r) as f64);
        let same = corners.len() == self.corner_count()
            && corners.iter().enumerate().all(|(k, p)| {
                let q = self.target_point(k);
                (f64::from(p.x) - q.x).abs() < tol
                    && (f64::from(p.y) - q.y).abs() < tol
                    && p.z == 0.0
            });
        if !same {
            return Err(VisionError::InvalidTarget(
                "OpenCV's ChArUco corner layout differs from the documented target frame".into(),
            ));
        }
        Ok(board)
    }
}

/// Detects a ChArUco board and returns the corners it saw, by corner id, with their
/// target points in OpenCV's board frame (see the module docs). `camera` is used to
/// predict corners from the markers through the lens model.
pub fn detect_charuco(
    img: &GrayImage,
    spec: &CharucoSpec,
    camera: &CameraModel,
) -> Result<BoardDetection, VisionError> {
    let dict = spec.validate()?;
    let board = spec.board(&dict)?;
    let (corners, ids) = raw_markers(img, &dict, false)?;
    // Keep only the board's own markers: other markers of the same dictionary (a second
    // target, a tool tag) must not feed the board pose.
    let n_markers = spec.marker_count() as i32;
    let (corners, ids): (Vector<Vector<Point2f>>, Vector<i32>) = corners
        .iter()
        .zip(ids.iter())
        .filter(|(_, id)| (0..n_markers).contains(id))
        .unzip();
    if ids.is_empty() {
        return Err(not_found(img, &dict, "ChArUco board markers"));
    }
    let (k, dist) = camera_matrices(camera)?;
    let mut ch_corners = Vector::<Point2f>::new();
    let mut ch_ids = Vector::<i32>::new();
    aruco::interpolate_corners_charuco(
        &corners,
        &ids,
        img.mat(),
        &board,
        &mut ch_corners,
        &mut ch_ids,
        &k,
        &dist,
        2,
    )
    .cv("interpolateCornersCharuco")?;
    let mut found: Vec<(usize, Point2<f64>)> = ch_ids
        .iter()
        .zip(ch_corners.iter())
        .filter(|(id, p)| {
            *id >= 0 && (*id as usize) < spec.corner_count() && p.x.is_finite() && p.y.is_finite()
        })
        .map(|(id, p)| (id as usize, Point2::new(f64::from(p.x), f64::from(p.y))))
        .collect();
    found.sort_by_key(|(id, _)| *id);
    found.dedup_by_key(|(id, _)| *id);
    let half_window = charuco_refine_window(spec, &corners);
    if let Some(w) = half_window {
        let mut pts: Vec<Point2<f64>> = found.iter().map(|(_, p)| *p).collect();
        refine_corners(img, &mut pts, w);
        for ((_, p), q) in found.iter_mut().zip(pts) {
            *p = q;
        }
    }
    if found.len() < MIN_CHARUCO_CORNERS {
        return Err(VisionError::TooFewCorners {
            found: found.len(),
            needed: MIN_CHARUCO_CORNERS,
        });
    }
    let kept: Vector<i32> = found.iter().map(|(id, _)| *id as i32).collect();
    if aruco::test_charuco_corners_collinear(&board, &kept).cv("testCharucoCornersCollinear")? {
        return Err(VisionError::Pose(format!(
            "the {} ChArUco corners seen lie on one line",
            found.len()
        )));
    }
    Ok(BoardDetection {
        target_points: found.iter().map(|(id, _)| spec.target_point(*id)).collect(),
        corner_ids: found.iter().map(|(id, _)| *id).collect(),
        pixels: found.into_iter().map(|(_, p)| p).collect(),
        method: CornerMethod::Charuco,
        refined: half_window.is_some(),
    })
}

/// Half-window for [`refine_corners`] on ChArUco corners: the window must stay in the
/// clean checker pattern around a corner, which reaches `(square - marker) / 2` along
/// both axes before a marker starts. The image scale comes from the smallest side of
/// the markers seen (the most foreshortened); `None` (no refinement) when that zone is
/// under 3 px.
fn charuco_refine_window(spec: &CharucoSpec, markers: &Vector<Vector<Point2f>>) -> Option<i32> {
    let min_side = markers
        .iter()
        .flat_map(|q| {
            let q = q.to_vec();
            (0..q.len())
                .map(|i| {
                    let (a, b) = (q[i], q[(i + 1) % q.len()]);
                    f64::from((a.x - b.x).hypot(a.y - b.y))
                })
                .collect::<Vec<_>>()
        })
        .fold(f64::INFINITY, f64::min);
    let clean_px = min_side / spec.marker_m * 0.5 * (spec.square_m - spec.marker_m);
    (clean_px.is_finite() && clean_px >= 3.0)
        .then(|| (0.8 * clean_px).floor().clamp(2.0, 10.0) as i32)
}

/// Draws the board with OpenCV (`CharucoBoard::draw`, one-bit marker borders) on a
/// white page with a one-square quiet zone: the image is `(cols+2)·px_per_square` by
/// `(rows+2)·px_per_square`, and ChArUco corner `(i, j)` (id `j·(cols-1) + i`) lies at
/// pixel `((i+2)·px_per_square - 0.5, (j+2)·px_per_square - 0.5)` (pixel centres at
/// integers). Square (0, 0), at the top left, is black.
pub fn render_charuco(spec: &CharucoSpec, px_per_square: usize) -> Result<GrayImage, VisionError> {
    let dict = spec.validate()?;
    let [c, r] = spec.squares;
    let min_px = 4;
    if px_per_square < min_px || (c.max(r) + 2).saturating_mul(px_per_square) > MAX_RENDER_SIDE {
        return Err(VisionError::InvalidTarget(format!(
            "{px_per_square} px per square: need at least {min_px} and at most \
             {MAX_RENDER_SIDE} px per image side"
        )));
    }
    let mut board = spec.board(&dict)?;
    let pps = px_per_square as i32;
    let (w, h) = ((c as i32 + 2) * pps, (r as i32 + 2) * pps);
    let mut img = Mat::default();
    board
        .draw(Size::new(w, h), &mut img, pps, 1)
        .cv("CharucoBoard::draw")?;
    GrayImage::from_mat(img)
}

/// A grid of ArUco markers, as `shared/dataset-format.md` describes it.
#[derive(Debug, Clone, PartialEq)]
pub struct ArucoGridSpec {
    /// Markers `[columns, rows]`.
    pub markers: [usize; 2],
    pub marker_m: f64,
    /// Gap between neighbouring markers.
    pub separation_m: f64,
    /// OpenCV dictionary name.
    pub dictionary: String,
    /// Id of marker (0, 0); marker `(i, j)` has id `first_id + j·cols + i`.
    pub first_id: usize,
}

impl ArucoGridSpec {
    /// Checks the spec and returns its dictionary.
    pub fn validate(&self) -> Result<MarkerDictionary, VisionError> {
        side("ArUco grid markers", self.markers, 1)?;
        positive("marker size", self.marker_m)?;
        if !(self.separation_m.is_finite() && self.separation_m >= 0.0) {
            return Err(VisionError::InvalidTarget(format!(
                "marker separation {} m must be finite and not negative",
                self.separation_m
            )));
        }
        let dict = MarkerDictionary::parse(&self.dictionary)?;
        dict.check_ids(self.first_id, self.marker_count(), "the ArUco grid")?;
        Ok(dict)
    }

    /// Number of markers.
    pub fn marker_count(&self) -> usize {
        self.markers[0] * self.markers[1]
    }

    /// Corner `c` (0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left) of marker
    /// index `id / 4 = j·cols + i` (marker id minus `first_id`), `c = id % 4`, in
    /// OpenCV 4.6's `GridBoard` frame.
    pub fn target_point(&self, id: usize) -> Point3<f64> {
        let (marker, c) = (id / 4, id % 4);
        let cols = self.markers[0].max(1);
        let (i, j) = (marker % cols, marker / cols);
        let step = self.marker_m + self.separation_m;
        let (dx, dy) = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)][c];
        Point3::new(
            i as f64 * step + dx * self.marker_m,
            j as f64 * step + dy * self.marker_m,
            0.0,
        )
    }

    fn board(&self, dict: &MarkerDictionary) -> Result<Ptr<aruco::GridBoard>, VisionError> {
        let (c, r) = side("ArUco grid markers", self.markers, 1)?;
        let first = i32::try_from(self.first_id)
            .map_err(|_| VisionError::InvalidTarget(format!("first id {}", self.first_id)))?;
        let sep = self.separation_m as f32;
        let board = aruco::GridBoard::create(
            c,
            r,
            positive("marker size", self.marker_m)?,
            sep,
            &dict.opencv()?,
            first,
        )
        .cv("GridBoard::create")?;
        let obj = board.obj_points();
        let tol = 1e-5 * (self.marker_m + self.separation_m) * (c.max(r) as f64);
        let same = obj.len() == self.marker_count()
            && obj.iter().enumerate().all(|(m, quad)| {
                quad.len() == 4
                    && quad.iter().enumerate().all(|(k, p)| {
                        let q = self.target_point(4 * m + k);
                        (f64::from(p.x) - q.x).abs() < tol
                            && (f64::from(p.y) - q.y).abs() < tol
                            && p.z == 0.0
                    })
            });
        if !same {
            return Err(VisionError::InvalidTarget(
                "OpenCV's GridBoard layout differs from the documented target frame".into(),
            ));
        }
        Ok(board)
    }
}

/// Detects the markers of an ArUco grid: the four corners of every marker seen, with
/// corner id `4·(marker id - first_id) + c` (see [`ArucoGridSpec::target_point`]).
pub fn detect_aruco_grid(
    img: &GrayImage,
    spec: &ArucoGridSpec,
) -> Result<BoardDetection, VisionError> {
    let dict = spec.validate()?;
    spec.board(&dict)?;
    let (corners, ids) = raw_markers(img, &dict, true)?;
    let ids: Vec<i32> = ids.to_vec();
    let quads = refined_quads(img, &dict, &corners)?;
    let range = spec.first_id..spec.first_id + spec.marker_count();
    let mut det = BoardDetection {
        target_points: Vec::new(),
        corner_ids: Vec::new(),
        pixels: Vec::new(),
        method: CornerMethod::ArucoMarkers,
        refined: false,
    };
    let mut seen: Vec<(usize, Vec<Point2<f64>>)> = Vec::new();
    let mut all_refined = true;
    for (k, (quad, ok)) in quads.into_iter().enumerate() {
        let id = ids[k];
        if id < 0 || !range.contains(&(id as usize)) || quad.len() != 4 {
            continue;
        }
        if ids.iter().filter(|&&other| other == id).count() > 1 {
            continue;
        }
        all_refined &= ok;
        seen.push((id as usize - spec.first_id, quad));
    }
    if seen.is_empty() {
        return Err(not_found(img, &dict, "markers of the ArUco grid"));
    }
    seen.sort_by_key(|(m, _)| *m);
    det.refined = all_refined;
    for (m, pts) in seen {
        for (c, p) in pts.into_iter().enumerate() {
            det.corner_ids.push(4 * m + c);
            det.target_points.push(spec.target_point(4 * m + c));
            det.pixels.push(p);
        }
    }
    Ok(det)
}

/// The four corners of one marker in a single marker's frame (OpenCV's
/// `estimatePoseSingleMarkers` convention, see the module docs): corner ids 0..4 =
/// top-left, top-right, bottom-right, bottom-left.
pub fn marker_target_points(marker_m: f64) -> [Point3<f64>; 4] {
    let h = 0.5 * marker_m;
    [
        Point3::new(-h, h, 0.0),
        Point3::new(h, h, 0.0),
        Point3::new(h, -h, 0.0),
        Point3::new(-h, -h, 0.0),
    ]
}

/// Detects marker `id` of `dictionary` (an OpenCV name) with side `marker_m`.
pub fn detect_marker(
    img: &GrayImage,
    dictionary: &str,
    id: usize,
    marker_m: f64,
) -> Result<BoardDetection, VisionError> {
    let dict = MarkerDictionary::parse(dictionary)?;
    dict.check_ids(id, 1, "the marker")?;
    positive("marker size", marker_m)?;
    let (corners, ids) = raw_markers(img, &dict, true)?;
    let hits: Vec<Vector<Point2f>> = corners
        .iter()
        .zip(ids.iter())
        .filter(|(q, i)| *i >= 0 && *i as usize == id && q.len() == 4)
        .map(|(q, _)| q)
        .collect();
    if hits.len() > 1 {
        return Err(VisionError::DuplicateMarker {
            id,
            dictionary: dict.name(),
            count: hits.len(),
        });
    }
    let hits: Vector<Vector<Point2f>> = hits.into_iter().collect();
    let Some((pixels, refined)) = refined_quads(img, &dict, &hits)?.pop() else {
        return Err(not_found(img, &dict, &format!("marker {id}")));
    };
    Ok(BoardDetection {
        target_points: marker_target_points(marker_m).to_vec(),
        corner_ids: (0..4).collect(),
        pixels,
        method: CornerMethod::ArucoMarkers,
        refined,
    })
}

/// A marker's four corners and whether [`refine_marker_quad`] refined them.
pub(crate) type RefinedQuad = (Vec<Point2<f64>>, bool);

/// Converts OpenCV's marker quads to points and refines each with
/// [`refine_marker_quad`]; the flag says whether that refinement succeeded.
pub(crate) fn refined_quads(
    img: &GrayImage,
    dict: &MarkerDictionary,
    corners: &Vector<Vector<Point2f>>,
) -> Result<Vec<RefinedQuad>, VisionError> {
    let cells = dict.opencv()?.marker_size() + 2;
    Ok(corners
        .iter()
        .map(|q| {
            let mut pts: Vec<Point2<f64>> = q
                .iter()
                .map(|p| Point2::new(f64::from(p.x), f64::from(p.y)))
                .collect();
            let ok = refine_marker_quad(img, &mut pts, cells);
            (pts, ok)
        })
        .collect())
}

/// Moves the four outer corners of a marker to the intersections of its four edges.
///
/// Each side's edge is located at points between 15 % and 85 % of its length, away
/// from the corners, as the centroid of the intensity gradient across the edge within
/// ±40 % of a cell (so the scan stays inside the black border and the white quiet
/// zone); a total-least-squares line through them, intersected with the neighbouring
/// sides' lines, gives the corners. Unlike `cornerSubPix` on an L-corner, this is not
/// pulled inwards by the blur of the corner. The quad is left alone when the marker is
/// too small (cells under 2.5 px), an edge is missing, or a corner would move by more
/// than a pixel.
fn refine_marker_quad(img: &GrayImage, quad: &mut [Point2<f64>], cells: i32) -> bool {
    if quad.len() != 4 || cells < 3 {
        return false;
    }
    let side = |i: usize| quad[(i + 1) % 4] - quad[i];
    let min_side = (0..4).map(|i| side(i).norm()).fold(f64::INFINITY, f64::min);
    let r = (0.4 * min_side / f64::from(cells)).min(3.0);
    if r.is_nan() || r < 1.0 {
        return false;
    }
    const STEP: f64 = 0.25;
    let n_steps = (2.0 * r / STEP).floor() as usize;
    let mut lines = Vec::with_capacity(4);
    for (i, &a) in quad.iter().enumerate() {
        let len = side(i).norm();
        let d = side(i) / len;
        let n = Vector2::new(-d.y, d.x);
        let n_samples = (0.7 * len).ceil().max(1.0) as usize;
        let mut pts = Vec::with_capacity(n_samples + 1);
        for k in 0..=n_samples {
            let p0 = a + side(i) * (0.15 + 0.7 * k as f64 / n_samples as f64);
            let Some(vals) = (0..=n_steps)
                .map(|j| {
                    let q = p0 + n * (-r + STEP * j as f64);
                    img.sample(q.x, q.y)
                })
                .collect::<Option<Vec<f64>>>()
            else {
                continue;
            };
            let grads: Vec<f64> = vals.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
            let g_max = grads.iter().cloned().fold(0.0, f64::max);
            // A gradient under 20 grey levels per pixel is no edge worth the name.
            if g_max < 5.0 {
                continue;
            }
            let floor = 0.1 * g_max;
            let (mut sw, mut sws) = (0.0, 0.0);
            for (j, g) in grads.iter().enumerate() {
                let w = (g - floor).max(0.0);
                sw += w;
                sws += w * (-r + STEP * (j as f64 + 0.5));
            }
            pts.push(p0 + n * (sws / sw));
        }
        if pts.len() < 5 {
            return false;
        }
        let c = pts.iter().fold(Vector2::zeros(), |acc, p| acc + p.coords) / pts.len() as f64;
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        for p in &pts {
            let v = p.coords - c;
            sxx += v.x * v.x;
            sxy += v.x * v.y;
            syy += v.y * v.y;
        }
        // Principal direction of the 2x2 scatter matrix.
        let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        lines.push((c, Vector2::new(theta.cos(), theta.sin())));
    }
    let mut out = [Point2::origin(); 4];
    for (i, o) in out.iter_mut().enumerate() {
        let (c1, d1) = lines[(i + 3) % 4];
        let (c2, d2) = lines[i];
        let cross = d1.x * d2.y - d1.y * d2.x;
        if cross.abs() < 0.1 {
            return false;
        }
        let w = c2 - c1;
        let t = (w.x * d2.y - w.y * d2.x) / cross;
        let p = Point2::from(c1 + d1 * t);
        let moved = (p - quad[i]).norm();
        if moved.is_nan() || moved > 1.0 {
            return false;
        }
        *o = p;
    }
    quad.copy_from_slice(&out);
    true
}

fn not_found(img: &GrayImage, dict: &MarkerDictionary, what: &str) -> VisionError {
    VisionError::MarkersNotFound {
        what: what.to_string(),
        dictionary: dict.name(),
        width: img.width(),
        height: img.height(),
    }
}

/// `detectMarkers` with OpenCV's default parameters, and `CORNER_REFINE_SUBPIX` when
/// `subpix`. Returns the marker corners (clockwise from the top-left) and ids.
pub(crate) fn raw_markers(
    img: &GrayImage,
    dict: &MarkerDictionary,
    subpix: bool,
) -> Result<(Vector<Vector<Point2f>>, Vector<i32>), VisionError> {
    let mut corners = Vector::<Vector<Point2f>>::new();
    let mut ids = Vector::<i32>::new();
    // A marker needs a few pixels per bit; tiny images cannot hold one.
    if img.width().min(img.height()) < 8 {
        return Ok((corners, ids));
    }
    let mut params = aruco::DetectorParameters::create().cv("DetectorParameters::create")?;
    if subpix {
        params.set_corner_refinement_method(aruco::CORNER_REFINE_SUBPIX);
    }
    let mut rejected = Vector::<Vector<Point2f>>::new();
    aruco::detect_markers(
        img.mat(),
        &dict.opencv()?,
        &mut corners,
        &mut ids,
        &params,
        &mut rejected,
    )
    .cv("detectMarkers")?;
    if corners.len() != ids.len() {
        return Err(VisionError::InvalidImage(format!(
            "detectMarkers returned {} quads for {} ids",
            corners.len(),
            ids.len()
        )));
    }
    Ok((corners, ids))
}
