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
//!   refines each one. Without the camera, OpenCV interpolates with local homographies,
//!   which is worse under distortion. A corner is kept only when both of the markers that
//!   touch it were seen (`minMarkers = 2`), so corners next to a hidden or missed marker
//!   are left out rather than guessed: on a partly covered board `corner_ids` lists
//!   exactly the corners that were seen, and [`crate::board_pose`] works on them.
//!   Fewer than [`MIN_CHARUCO_CORNERS`] corners, or corners all on one line, are refused.
//! - **Marker corners** (grid and single marker) are refined with OpenCV's
//!   `CORNER_REFINE_SUBPIX`. A marker id that appears twice in a grid is dropped (a
//!   reflection or a second board would otherwise give wrong correspondences);
//!   [`detect_marker`] reports it as [`VisionError::DuplicateMarker`].
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
use nalgebra::{Point2, Point3};
use opencv::aruco::{self, PREDEFINED_DICTIONARY_NAME as Dict};
use opencv::core::{Mat, Point2f, Ptr, Size, Vector};
use opencv::prelude::*;

use crate::checkerboard::{BoardDetection, CornerMethod};
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

    fn opencv(&self) -> Result<Ptr<aruco::Dictionary>, VisionError> {
        aruco::get_predefined_dictionary(DICTIONARIES[self.index].1)
            .cv("getPredefinedDictionary")
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

    fn board(&self, dict: &MarkerDictionary) -> Result<Ptr<aruco::CharucoBoard>, VisionError> {
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
        refined: false,
    })
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
    let range = spec.first_id..spec.first_id + spec.marker_count();
    let mut det = BoardDetection {
        target_points: Vec::new(),
        corner_ids: Vec::new(),
        pixels: Vec::new(),
        method: CornerMethod::ArucoMarkers,
        refined: false,
    };
    let mut seen: Vec<(usize, Vec<Point2<f64>>)> = Vec::new();
    for (k, quad) in corners.iter().enumerate() {
        let id = ids[k];
        if id < 0 || !range.contains(&(id as usize)) || quad.len() != 4 {
            continue;
        }
        if ids.iter().filter(|&&other| other == id).count() > 1 {
            continue;
        }
        let pts: Vec<Point2<f64>> = quad
            .iter()
            .map(|p| Point2::new(f64::from(p.x), f64::from(p.y)))
            .collect();
        seen.push((id as usize - spec.first_id, pts));
    }
    if seen.is_empty() {
        return Err(not_found(img, &dict, "markers of the ArUco grid"));
    }
    seen.sort_by_key(|(m, _)| *m);
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
        .filter(|(q, i)| *i as usize == id && *i >= 0 && q.len() == 4)
        .map(|(q, _)| q)
        .collect();
    let quad = match hits.as_slice() {
        [q] => q,
        [] => return Err(not_found(img, &dict, &format!("marker {id}"))),
        _ => {
            return Err(VisionError::DuplicateMarker {
                id,
                dictionary: dict.name(),
                count: hits.len(),
            });
        }
    };
    Ok(BoardDetection {
        target_points: marker_target_points(marker_m).to_vec(),
        corner_ids: (0..4).collect(),
        pixels: quad
            .iter()
            .map(|p| Point2::new(f64::from(p.x), f64::from(p.y)))
            .collect(),
        method: CornerMethod::ArucoMarkers,
        refined: false,
    })
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
fn raw_markers(
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
