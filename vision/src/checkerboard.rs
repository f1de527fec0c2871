//! Checkerboard corner detection and the board's origin convention.
//!
//! See the crate docs for the measurements behind the choice of detector. This module
//! owns three steps:
//!
//! 1. **Corners** from one of OpenCV's two detectors ([`CornerMethod`]), tried in
//!    order until one finds the board, then [`refine_corners`].
//! 2. **Handedness.** OpenCV returns the grid in row-major order with rows along the
//!    `cols` direction, but may start at any of the four extreme corners, so the grid
//!    can come back mirrored. The target frame has z = x × y pointing into the board,
//!    i.e. away from a camera that sees the printed side; in pixel coordinates
//!    (u right, v down, camera z forward) that means the image of the x axis turned
//!    towards the image of the y axis must be a clockwise-on-screen turn: the signed
//!    area of the quadrilateral (0,0) → (cols-1,0) → (cols-1,rows-1) → (0,rows-1) is
//!    positive. A negative area is fixed by reversing every row.
//! 3. **Origin.** With handedness fixed, the grid can still be turned by 180°. The
//!    convention puts corner (0,0) at the inner corner that touches a black
//!    outer-corner square. That outer square is the diagonal neighbour across corner
//!    (0,0) of inner square (0,0) (the one spanned by corners (0,0) and (1,1)), and
//!    diagonal neighbours on a checkerboard share a colour; so the rule becomes:
//!    *inner squares with even `a + b` must be the dark ones*. The 180° turn maps inner
//!    square (a, b) to (cols-2-a, rows-2-b), changing the parity of `a + b` by
//!    `cols + rows`. Hence:
//!    - `cols + rows` odd (9x6 inner corners = 10x7 squares: the two black
//!      outer-corner squares sit on the same short side, the other two are white):
//!      exactly one of the two orderings satisfies the rule, and the orientation is
//!      unambiguous. The second black outer corner's inner corner is not a candidate
//!      origin because from it, x along the columns and y along the rows gives a
//!      left-handed frame (z out of the board).
//!    - `cols + rows` even (both odd: black outer squares on a diagonal; both even:
//!      all four outer squares the same colour): the board looks the same turned by
//!      180°, so no image can decide between the two labellings. Square boards
//!      (`cols == rows`) may also look the same turned by 90°: with an even number of
//!      inner corners per side (odd squares) a quarter turn keeps the parity of every
//!      square, so all four turns look the same; with an odd number it flips the parity,
//!      so the colours still tell the quarter turns apart and only the half-turn is left.
//!      [`detect_checkerboard_up_to_symmetry`] returns such a board's corners in one of
//!      the labellings the colours allow, together with the board's symmetry
//!      ([`CheckerboardSpec::symmetry`]); the pipeline chooses each view's labelling from
//!      the robot motion (`b2b_calib::symmetry`). [`detect_checkerboard`] still refuses
//!      these specs with [`VisionError::AmbiguousOrientation`]: its callers take the
//!      labelling as the truth and could not resolve it.
//!
//!    Colours are compared pairwise between neighbouring inner squares (each sampled
//!    at nine points inside the square, interpolated from its four corners), so a
//!    lighting gradient across the board does not matter; at least 90 % of the pairs
//!    must agree and the median contrast must be at least [`MIN_SQUARE_CONTRAST`].

use b2b_calib::symmetry::TargetSymmetry;
use nalgebra::{Point2, Point3};
use opencv::core::{Point2f, Size, TermCriteria, Vector};
use opencv::{calib3d, imgproc};

use crate::error::{CvContext, VisionError};
use crate::image::GrayImage;

/// Median grey-level difference between neighbouring squares below which the square
/// colours are not trusted to fix the orientation.
pub const MIN_SQUARE_CONTRAST: f64 = 8.0;

/// Variance of the Laplacian below which a failed detection is reported as
/// [`VisionError::Blurred`] rather than [`VisionError::BoardNotFound`]. The sharp
/// ViSP images measure 2700–4100; ViSP image 1 with a Gaussian blur of σ = 6 px
/// measures 9.8; a flat grey image measures 0.
pub const BLUR_LAPLACIAN_VAR: f64 = 20.0;

/// Largest number of inner corners per side accepted in a spec.
const MAX_SIDE: usize = 200;

/// A checkerboard by its inner corners: `cols` along x, `rows` along y.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CheckerboardSpec {
    pub cols: usize,
    pub rows: usize,
    pub square_m: f64,
}

impl CheckerboardSpec {
    /// Checks the spec is one OpenCV can look for (both sides at least 3 corners).
    pub fn validate(&self) -> Result<(), VisionError> {
        if self.cols < 3 || self.rows < 3 {
            return Err(VisionError::InvalidSpec(format!(
                "{}x{} inner corners: OpenCV needs at least 3 along each side",
                self.cols, self.rows
            )));
        }
        if self.cols > MAX_SIDE || self.rows > MAX_SIDE {
            return Err(VisionError::InvalidSpec(format!(
                "{}x{} inner corners: more than {MAX_SIDE} along a side",
                self.cols, self.rows
            )));
        }
        if !(self.square_m.is_finite() && self.square_m > 0.0) {
            return Err(VisionError::InvalidSpec(format!(
                "square size {} m must be positive and finite",
                self.square_m
            )));
        }
        Ok(())
    }

    /// Number of inner corners.
    pub fn corner_count(&self) -> usize {
        self.cols * self.rows
    }

    /// Whether the square colours decide the origin (see the module docs): true
    /// exactly when `cols + rows` is odd.
    pub fn orientation_is_unambiguous(&self) -> bool {
        (self.cols + self.rows) % 2 == 1
    }

    /// The labellings of this board that no image can tell apart (see the module docs):
    /// only the identity when `cols + rows` is odd; the identity and the half-turn about
    /// the board centre otherwise; all four quarter turns for square boards with an even
    /// number of inner corners per side.
    pub fn symmetry(&self) -> TargetSymmetry {
        if self.orientation_is_unambiguous() {
            return TargetSymmetry::trivial(self.corner_count());
        }
        let quarter = self.cols == self.rows && self.cols.is_multiple_of(2);
        TargetSymmetry::grid_turns(self.cols, self.rows, self.square_m, quarter)
    }

    /// Corner `id = j * cols + i` in the target frame: `(i * square, j * square, 0)`.
    pub fn target_point(&self, id: usize) -> Point3<f64> {
        let (i, j) = (id % self.cols, id / self.cols);
        Point3::new(i as f64 * self.square_m, j as f64 * self.square_m, 0.0)
    }
}

/// The corners of one board in one image, in the dataset-format target frame.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardDetection {
    /// Corner positions in the target frame (metres, z = 0).
    pub target_points: Vec<Point3<f64>>,
    /// `j * cols + i` for corner (i, j).
    pub corner_ids: Vec<usize>,
    /// Sub-pixel image positions (OpenCV convention: top-left pixel centre at (0, 0)).
    pub pixels: Vec<Point2<f64>>,
    /// The detector that produced the corners.
    pub method: CornerMethod,
    /// Whether [`refine_corners`] ran after it (for marker corners: whether every
    /// marker's edge-line refinement succeeded, see [`crate::markers`]).
    pub refined: bool,
}

/// One of OpenCV's chessboard detectors with its settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CornerMethod {
    /// `findChessboardCornersSB` (Duda & Frese's sector-based detector) with these
    /// `CALIB_CB_*` flags. It localises corners itself; no `cornerSubPix`.
    SectorBased { flags: i32 },
    /// `findChessboardCorners` with these flags, then `cornerSubPix` with a
    /// `(2w+1)²` window; `half_window: None` picks `w` from the corner spacing.
    Classic {
        flags: i32,
        half_window: Option<i32>,
    },
    /// Not a checkerboard detector: ChArUco corners interpolated from the board's
    /// ArUco markers and refined by `cornerSubPix` ([`crate::markers::detect_charuco`]).
    Charuco,
    /// Not a checkerboard detector: the four corners of each ArUco/AprilTag marker,
    /// refined by `cornerSubPix` ([`crate::markers::detect_aruco_grid`],
    /// [`crate::markers::detect_marker`]).
    ArucoMarkers,
    /// Not a detector here: corners another process detected and published (a
    /// live agent's observation, refitted at the coordinator).
    Published,
}

/// The detectors [`detect_checkerboard`] tries, in order (see the crate docs for the
/// measurements). After [`refine_corners`] every detector lands on the same corners,
/// so the order is about speed and robustness: the classic detector is ~50x faster
/// and finds boards under strong perspective; the sector-based one finds boards the
/// classic one misses in uneven light; `EXHAUSTIVE` is the slow last resort.
pub const DEFAULT_METHODS: [CornerMethod; 3] = [
    // FAST_CHECK: without it, findChessboardCorners on an image with no board
    // (an occluded or missed view) tries every dilation and threshold: 30 s on
    // one 1280x720 frame here, against 27 ms with it. A board it wrongly rejects
    // still gets the sector-based detectors below.
    CornerMethod::Classic {
        flags: calib3d::CALIB_CB_ADAPTIVE_THRESH
            | calib3d::CALIB_CB_NORMALIZE_IMAGE
            | calib3d::CALIB_CB_FAST_CHECK,
        half_window: None,
    },
    CornerMethod::SectorBased {
        flags: calib3d::CALIB_CB_NORMALIZE_IMAGE,
    },
    CornerMethod::SectorBased {
        flags: calib3d::CALIB_CB_NORMALIZE_IMAGE | calib3d::CALIB_CB_EXHAUSTIVE,
    },
];

/// Finds all inner corners of the board with sub-pixel accuracy, ordered and
/// oriented by the dataset-format convention (see the module docs): the
/// [`DEFAULT_METHODS`], then [`refine_corners`].
pub fn detect_checkerboard(
    img: &GrayImage,
    spec: &CheckerboardSpec,
) -> Result<BoardDetection, VisionError> {
    detect_checkerboard_with(img, spec, &DEFAULT_METHODS, true)
}

/// [`detect_checkerboard`] with an explicit list of detectors, tried in order, and
/// with or without the final [`refine_corners`] step.
pub fn detect_checkerboard_with(
    img: &GrayImage,
    spec: &CheckerboardSpec,
    methods: &[CornerMethod],
    refine: bool,
) -> Result<BoardDetection, VisionError> {
    spec.validate()?;
    check_orientable(spec)?;
    detect_any(img, spec, methods, refine)
}

/// [`detect_checkerboard`] for every spec, symmetric ones included: the corners in one
/// of the labellings the square colours allow, and the labellings no image can tell
/// apart ([`CheckerboardSpec::symmetry`]; only the identity when `cols + rows` is odd,
/// and then the detection is exactly [`detect_checkerboard`]'s). The caller must choose
/// each view's labelling (`b2b_calib::symmetry::resolve_labelling`) before using
/// `target_points`, `corner_ids` or a pose fitted to them.
pub fn detect_checkerboard_up_to_symmetry(
    img: &GrayImage,
    spec: &CheckerboardSpec,
) -> Result<(BoardDetection, TargetSymmetry), VisionError> {
    spec.validate()?;
    let det = detect_any(img, spec, &DEFAULT_METHODS, true)?;
    Ok((det, spec.symmetry()))
}

fn detect_any(
    img: &GrayImage,
    spec: &CheckerboardSpec,
    methods: &[CornerMethod],
    refine: bool,
) -> Result<BoardDetection, VisionError> {
    for &method in methods {
        let Some(mut raw) = find_corners(img, spec, method)? else {
            continue;
        };
        if raw.len() != spec.corner_count() {
            return Err(VisionError::TooFewCorners {
                found: raw.len(),
                needed: spec.corner_count(),
            });
        }
        if refine {
            let w = adaptive_half_window(&raw, spec);
            refine_corners(img, &mut raw, w);
        }
        let pixels = orient_any(img, spec, raw)?;
        let n = spec.corner_count();
        return Ok(BoardDetection {
            target_points: (0..n).map(|k| spec.target_point(k)).collect(),
            corner_ids: (0..n).collect(),
            pixels,
            method,
            refined: refine,
        });
    }
    let laplacian_var = img.laplacian_variance()?;
    if laplacian_var < BLUR_LAPLACIAN_VAR {
        return Err(VisionError::Blurred {
            laplacian_var,
            threshold: BLUR_LAPLACIAN_VAR,
        });
    }
    Err(VisionError::BoardNotFound {
        cols: spec.cols,
        rows: spec.rows,
        width: img.width(),
        height: img.height(),
        laplacian_var,
    })
}

/// Runs one OpenCV detector; `None` when it does not find the board. The corners
/// are in OpenCV's order (row-major, `cols` per row, any start corner).
pub fn find_corners(
    img: &GrayImage,
    spec: &CheckerboardSpec,
    method: CornerMethod,
) -> Result<Option<Vec<Point2<f64>>>, VisionError> {
    spec.validate()?;
    // Both detectors need a few pixels per square; tiny images cannot hold a board
    // and make OpenCV's internals assert.
    let min_side = 2 * (spec.cols.min(spec.rows) as u32 + 1);
    let max_side = 2 * (spec.cols.max(spec.rows) as u32 + 1);
    if img.width().min(img.height()) < min_side || img.width().max(img.height()) < max_side {
        return Ok(None);
    }
    let size = Size::new(spec.cols as i32, spec.rows as i32);
    let mut corners = Vector::<Point2f>::new();
    match method {
        CornerMethod::Charuco | CornerMethod::ArucoMarkers | CornerMethod::Published => {
            return Err(VisionError::InvalidSpec(format!(
                "{method:?} is not a checkerboard detector"
            )));
        }
        CornerMethod::SectorBased { flags } => {
            let found = calib3d::find_chessboard_corners_sb(img.mat(), size, &mut corners, flags)
                .cv("findChessboardCornersSB")?;
            if !found {
                return Ok(None);
            }
        }
        CornerMethod::Classic { flags, half_window } => {
            let found = calib3d::find_chessboard_corners(img.mat(), size, &mut corners, flags)
                .cv("findChessboardCorners")?;
            if !found {
                return Ok(None);
            }
            let w = half_window.unwrap_or_else(|| adaptive_half_window(&to_points(&corners), spec));
            let criteria = TermCriteria::new(
                opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
                100,
                1e-4,
            )
            .cv("TermCriteria")?;
            imgproc::corner_sub_pix(
                img.mat(),
                &mut corners,
                Size::new(w, w),
                Size::new(-1, -1),
                criteria,
            )
            .cv("cornerSubPix")?;
        }
    }
    Ok(Some(to_points(&corners)))
}

fn to_points(corners: &Vector<Point2f>) -> Vec<Point2<f64>> {
    corners
        .iter()
        .map(|p| Point2::new(f64::from(p.x), f64::from(p.y)))
        .collect()
}

/// Half-window for `cornerSubPix` and [`refine_corners`]: 40 % of the shortest distance between neighbouring
/// corners (so the window never reaches the next corner), between 2 and 10 px.
pub fn adaptive_half_window(corners: &[Point2<f64>], spec: &CheckerboardSpec) -> i32 {
    let (c, r) = (spec.cols, spec.rows);
    let mut d_min = f64::INFINITY;
    for j in 0..r {
        for i in 0..c {
            let p = corners[j * c + i];
            if i + 1 < c {
                d_min = d_min.min((corners[j * c + i + 1] - p).norm());
            }
            if j + 1 < r {
                d_min = d_min.min((corners[(j + 1) * c + i] - p).norm());
            }
        }
    }
    (0.4 * d_min).round().clamp(2.0, 10.0) as i32
}

/// Reorders corners found in OpenCV's order so that corner (0,0) is the origin of
/// the dataset-format target frame (see the module docs). `corners` must hold
/// `cols * rows` points, row-major with `cols` per row.
pub fn orient_corners(
    img: &GrayImage,
    spec: &CheckerboardSpec,
    corners: Vec<Point2<f64>>,
) -> Result<Vec<Point2<f64>>, VisionError> {
    spec.validate()?;
    check_orientable(spec)?;
    orient_any(img, spec, corners)
}

/// [`orient_corners`] for every spec: for a symmetric one, the corners in one of the
/// labellings of [`CheckerboardSpec::symmetry`] that satisfy the colour rule.
fn orient_any(
    img: &GrayImage,
    spec: &CheckerboardSpec,
    mut corners: Vec<Point2<f64>>,
) -> Result<Vec<Point2<f64>>, VisionError> {
    let (c, r) = (spec.cols, spec.rows);
    if corners.len() != c * r {
        return Err(VisionError::TooFewCorners {
            found: corners.len(),
            needed: c * r,
        });
    }
    // Handedness: signed area of the outer quadrilateral, positive for x right/y down.
    let quad = [
        corners[0],
        corners[c - 1],
        corners[c * r - 1],
        corners[(r - 1) * c],
    ];
    let area: f64 = (0..4)
        .map(|k| {
            let (p, q) = (quad[k], quad[(k + 1) % 4]);
            p.x * q.y - q.x * p.y
        })
        .sum();
    if !area.is_finite() || area.abs() < 1.0 {
        return Err(VisionError::AmbiguousOrientation(format!(
            "the corner grid is degenerate (signed area {area:.3} px²)"
        )));
    }
    if area < 0.0 {
        for row in corners.chunks_mut(c) {
            row.reverse();
        }
    }
    // Origin: inner squares with even a + b must be the dark ones.
    let mut means = vec![f64::NAN; (c - 1) * (r - 1)];
    for b in 0..r - 1 {
        for a in 0..c - 1 {
            means[b * (c - 1) + a] = square_mean(img, &corners, c, a, b).unwrap_or(f64::NAN);
        }
    }
    let (mut even_dark, mut pairs) = (0usize, 0usize);
    let mut contrasts = Vec::new();
    for b in 0..r - 1 {
        for a in 0..c - 1 {
            let m = means[b * (c - 1) + a];
            let neighbours = [
                (a + 1 < c - 1).then(|| means[b * (c - 1) + a + 1]),
                (b + 1 < r - 1).then(|| means[(b + 1) * (c - 1) + a]),
            ];
            for n in neighbours.into_iter().flatten() {
                if !(m.is_finite() && n.is_finite()) {
                    continue;
                }
                // (a, b) and its neighbour have opposite parity.
                let (even, odd) = if (a + b) % 2 == 0 { (m, n) } else { (n, m) };
                pairs += 1;
                if even < odd {
                    even_dark += 1;
                }
                contrasts.push((m - n).abs());
            }
        }
    }
    if pairs == 0 {
        return Err(VisionError::AmbiguousOrientation(
            "no pair of neighbouring squares lies inside the image".into(),
        ));
    }
    contrasts.sort_by(f64::total_cmp);
    let contrast = contrasts[contrasts.len() / 2];
    if contrast < MIN_SQUARE_CONTRAST {
        return Err(VisionError::AmbiguousOrientation(format!(
            "square contrast {contrast:.1} grey levels is below {MIN_SQUARE_CONTRAST}"
        )));
    }
    let agree = even_dark as f64 / pairs as f64;
    if agree >= 0.9 {
        Ok(corners)
    } else if agree <= 0.1 && spec.orientation_is_unambiguous() {
        // cols + rows is odd: turning by 180° makes the even squares the dark ones.
        corners.reverse();
        Ok(corners)
    } else if agree <= 0.1 && c == r && c % 2 == 1 {
        // A square board with an even number of squares per side: a quarter turn flips
        // the parity of every square. Corner (i, j) becomes (c-1-j, i).
        let mut turned = corners.clone();
        for (m, p) in corners.into_iter().enumerate() {
            let (i, j) = (m % c, m / c);
            turned[i * c + (c - 1 - j)] = p;
        }
        Ok(turned)
    } else if agree <= 0.1 {
        // cols + rows even: every turn the board allows keeps the parity of the squares.
        Err(VisionError::AmbiguousOrientation(format!(
            "the {c}x{r} board's candidate origins touch white outer-corner squares ({} of \
             {pairs} neighbouring pairs disagree with the convention): its colours are \
             inverted with respect to the dataset-format convention, which no turn fixes",
            pairs - even_dark
        )))
    } else {
        Err(VisionError::AmbiguousOrientation(format!(
            "square colours are inconsistent: {even_dark} of {pairs} neighbouring pairs say \
             corner (0,0) touches a dark square"
        )))
    }
}

/// Refuses specs whose square colours cannot fix the origin (`cols + rows` even).
fn check_orientable(spec: &CheckerboardSpec) -> Result<(), VisionError> {
    if spec.orientation_is_unambiguous() {
        return Ok(());
    }
    Err(VisionError::AmbiguousOrientation(format!(
        "a {}x{} board (inner corners; {}x{} squares) looks the same turned by 180°, so its \
         square colours cannot fix the origin in one image; the offline pipeline decides \
         it from the robot motion over all captures (detect_checkerboard_up_to_symmetry), \
         otherwise use a board with cols + rows odd or a ChArUco board",
        spec.cols,
        spec.rows,
        spec.cols + 1,
        spec.rows + 1
    )))
}

/// Mean grey value inside inner square (a, b), sampled at nine points bilinearly
/// interpolated between its four corners; `None` if any sample is off the image.
fn square_mean(
    img: &GrayImage,
    corners: &[Point2<f64>],
    c: usize,
    a: usize,
    b: usize,
) -> Option<f64> {
    let p00 = corners[b * c + a].coords;
    let p10 = corners[b * c + a + 1].coords;
    let p01 = corners[(b + 1) * c + a].coords;
    let p11 = corners[(b + 1) * c + a + 1].coords;
    let mut sum = 0.0;
    for s in [0.3, 0.5, 0.7] {
        for t in [0.3, 0.5, 0.7] {
            let p = p00 * ((1.0 - s) * (1.0 - t))
                + p10 * (s * (1.0 - t))
                + p01 * ((1.0 - s) * t)
                + p11 * (s * t);
            sum += img.sample(p.x, p.y)?;
        }
    }
    Some(sum / 9.0)
}

/// Refines corners by the gradient-orthogonality principle of `cornerSubPix`
/// (every image gradient near a corner is orthogonal to the vector from the corner),
/// but evaluated on the integer pixel grid with a Gaussian weight centred on the
/// current estimate (Scharr gradients, radius `half_window`, σ = `half_window / 2`),
/// instead of on a window resampled around the estimate by bilinear interpolation as
/// `cornerSubPix` does. Straight edges stay straight under perspective, so the
/// principle itself is unbiased; on rendered boards this halves to quarters the
/// error of `cornerSubPix` and removes the bias of the sector-based detector (see the
/// crate docs). Each corner moves at most `half_window` from its start.
pub fn refine_corners(img: &GrayImage, corners: &mut [Point2<f64>], half_window: i32) {
    let (w, h) = (img.width() as i64, img.height() as i64);
    let p = img.pixels();
    let at = |x: i64, y: i64| f64::from(p[(y * w + x) as usize]);
    let r = f64::from(half_window.max(1));
    let sigma2 = (0.5 * r) * (0.5 * r);
    for c in corners.iter_mut() {
        let mut est = *c;
        for _ in 0..30 {
            let (mut a11, mut a12, mut a22, mut b1, mut b2) = (0.0, 0.0, 0.0, 0.0, 0.0);
            let (x0, y0) = ((est.x - r).ceil() as i64, (est.y - r).ceil() as i64);
            let (x1, y1) = ((est.x + r).floor() as i64, (est.y + r).floor() as i64);
            for y in y0.max(1)..=y1.min(h - 2) {
                for x in x0.max(1)..=x1.min(w - 2) {
                    let (dx, dy) = (x as f64 - est.x, y as f64 - est.y);
                    let d2 = dx * dx + dy * dy;
                    if d2 > r * r {
                        continue;
                    }
                    // Scharr derivative: the most rotation-invariant 3x3 gradient.
                    let gx = 3.0
                        * (at(x + 1, y - 1) - at(x - 1, y - 1) + at(x + 1, y + 1)
                            - at(x - 1, y + 1))
                        + 10.0 * (at(x + 1, y) - at(x - 1, y));
                    let gy = 3.0
                        * (at(x - 1, y + 1) - at(x - 1, y - 1) + at(x + 1, y + 1)
                            - at(x + 1, y - 1))
                        + 10.0 * (at(x, y + 1) - at(x, y - 1));
                    let wq = (-d2 / (2.0 * sigma2)).exp();
                    let (gxx, gxy, gyy) = (wq * gx * gx, wq * gx * gy, wq * gy * gy);
                    a11 += gxx;
                    a12 += gxy;
                    a22 += gyy;
                    b1 += gxx * x as f64 + gxy * y as f64;
                    b2 += gxy * x as f64 + gyy * y as f64;
                }
            }
            let det = a11 * a22 - a12 * a12;
            let well_posed = det.abs() > 1e-12 * (a11 + a22).powi(2);
            if !well_posed || !det.is_finite() {
                break;
            }
            let next = Point2::new((a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det);
            let step = (next - est).norm();
            if !step.is_finite() || (next - *c).norm() > r {
                break;
            }
            est = next;
            if step < 1e-4 {
                break;
            }
        }
        *c = est;
    }
}
