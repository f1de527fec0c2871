//! Multimarker targets: a set of ArUco/AprilTag markers at known poses in one frame,
//! described by an ARToolKit-style multimarker file, and their pose from every visible
//! marker's corners at once.
//!
//! # The file (`shared/facts.md` §3.1, `notes/marker-convention.md`)
//!
//! Lines starting with `#` and blank lines are skipped. The first remaining line is the
//! number of markers N; then each marker has five lines: its barcode id, its width
//! (the outer black border's side) and the three rows of the 3x4 `[R | t]` that maps
//! marker-local points into the set frame, `p_set = T · p_marker`. Widths and
//! translations are **millimetres** (ARToolKit's convention) and are converted to
//! metres here. Only barcode (matrix) ids are supported: the id is the marker's id in
//! the dataset's OpenCV dictionary. A template pattern (`a.patt`) is refused, as are
//! global ids with upper bits set, duplicate ids, rotations that are not rotations and
//! anything after the N-th marker. An ARToolKit 2.x centre line (two numbers) before
//! the matrix is tolerated and skipped, as ARToolKit does. Every error names the file
//! and the line.
//!
//! The marker-local frame is OpenCV's single-marker one: origin at the centre, x right
//! and y up in the printed image, z out of the printed face; the corners are top-left
//! `(-w/2, w/2)`, top-right, bottom-right, bottom-left, in OpenCV's detection order.
//!
//! # The pose
//!
//! [`detect_multimarker`] finds the set's markers ([`crate::markers`]' detector and
//! edge-line refinement), maps each marker's four corners into the set frame and solves
//! one PnP problem over all of them ([`multimarker_pose`]):
//! - the visible corners are **coplanar** (the 4x3 sheet, or only one face of a corner
//!   target in view): OpenCV's IPPE in the plane's own frame gives both planar
//!   solutions, each refined by Levenberg–Marquardt over all corners; when the second
//!   one explains the corners about as well as the first and the two differ by more
//!   than a degree, the pose is refused as [`VisionError::AmbiguousPose`] (a small,
//!   nearly frontal single marker);
//! - **non-coplanar** corners: SQPnP (a globally optimal PnP for general point sets,
//!   OpenCV ≥ 4.5.3), then Levenberg–Marquardt.
//!
//! Residuals are recomputed with [`CameraModel::project`].

use std::collections::BTreeMap;
use std::path::Path;

use b2b_errors::excerpt;

use b2b_calib::camera::CameraModel;
use nalgebra::{
    Isometry3, Matrix3, Point2, Point3, Rotation3, SymmetricEigen, Translation3, UnitQuaternion,
    Vector3,
};
use opencv::calib3d;
use opencv::core::{Mat, Point2d, Point3d, TermCriteria, Vector};
use opencv::prelude::*;

use crate::checkerboard::{BoardDetection, CornerMethod};
use crate::error::{CvContext, VisionError};
use crate::image::GrayImage;
use crate::markers::{MarkerDictionary, marker_target_points, raw_markers, refined_quads};
use crate::pose::{PoseEstimate, camera_matrices};

/// Most markers a file may declare.
pub const MAX_MARKERS: usize = 4096;

/// The second planar solution's RMS must exceed `AMBIGUITY_RATIO · best + AMBIGUITY_MARGIN_PX`
/// for a planar pose to be accepted (when the two poses differ by more than a degree).
pub const AMBIGUITY_RATIO: f64 = 3.0;
/// See [`AMBIGUITY_RATIO`].
pub const AMBIGUITY_MARGIN_PX: f64 = 0.1;

/// One marker of a multimarker set.
#[derive(Debug, Clone, PartialEq)]
pub struct MultimarkerMarker {
    /// Barcode id = the marker's id in the OpenCV dictionary.
    pub id: usize,
    /// Outer black border's side, metres.
    pub width_m: f64,
    /// `T_set_marker` (metres).
    pub set_from_marker: Isometry3<f64>,
    /// Line of the file where the marker's entry starts (0 when built in code).
    pub line: usize,
}

impl MultimarkerMarker {
    /// The marker's four corners in the set frame, in OpenCV's order (top-left,
    /// top-right, bottom-right, bottom-left).
    pub fn corners(&self) -> [Point3<f64>; 4] {
        marker_target_points(self.width_m).map(|p| self.set_from_marker * p)
    }
}

/// A multimarker set: what an ARToolKit-style multimarker file describes.
#[derive(Debug, Clone, PartialEq)]
pub struct MultimarkerConfig {
    /// Where the set came from (the file path, or a name), for messages.
    pub source: String,
    pub markers: Vec<MultimarkerMarker>,
}

/// One flat face of a multimarker set: markers that share a plane and an orientation.
#[derive(Debug, Clone, PartialEq)]
pub struct MultimarkerFace {
    /// `T_set_face`: the face frame has the markers' rotation, its origin on their plane.
    pub set_from_face: Isometry3<f64>,
    /// `(id, centre (x, y) in the face frame, width)`, metres.
    pub markers: Vec<(usize, Point2<f64>, f64)>,
}

fn file_error(source: &str, line: usize, reason: impl Into<String>) -> VisionError {
    VisionError::MultimarkerFile {
        source_name: source.to_string(),
        line,
        reason: reason.into(),
    }
}

fn numbers(text: &str) -> Option<Vec<f64>> {
    text.split_whitespace()
        .map(|t| t.parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect()
}

impl MultimarkerConfig {
    /// Reads and parses a multimarker file.
    pub fn load(path: &Path) -> Result<Self, VisionError> {
        let text = std::fs::read(path).map_err(|source| VisionError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let text = String::from_utf8(text).map_err(|e| {
            file_error(
                &path.display().to_string(),
                0,
                format!("not UTF-8 text ({e})"),
            )
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses the text of a multimarker file; `source_name` names it in errors.
    pub fn parse(text: &str, source_name: &str) -> Result<Self, VisionError> {
        let mut lines = text
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l.trim()))
            .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
        let last_line = text.lines().count();
        let (n_line, n_text) = lines.next().ok_or_else(|| {
            file_error(source_name, last_line, "no marker count: the file is empty")
        })?;
        let n: usize = n_text.parse().map_err(|_| {
            file_error(
                source_name,
                n_line,
                format!(
                    "expected the number of markers, found \"{}\"",
                    excerpt(n_text)
                ),
            )
        })?;
        if n == 0 || n > MAX_MARKERS {
            return Err(file_error(
                source_name,
                n_line,
                format!("number of markers {n}: need 1 to {MAX_MARKERS}"),
            ));
        }
        let mut markers: Vec<MultimarkerMarker> = Vec::with_capacity(n);
        let mut next = |k: usize, what: &str| {
            lines.next().ok_or_else(|| {
                file_error(
                    source_name,
                    last_line,
                    format!(
                        "the file ends inside marker {} of {n}: expected {what}",
                        k + 1
                    ),
                )
            })
        };
        for k in 0..n {
            let (id_line, id_text) = next(k, "a barcode id")?;
            let tokens: Vec<&str> = id_text.split_whitespace().collect();
            let id = match tokens.as_slice() {
                [t] if t.bytes().all(|b| b.is_ascii_digit()) => t.parse::<u64>().map_err(|_| {
                    file_error(
                        source_name,
                        id_line,
                        format!("barcode id {} is too large", excerpt(t)),
                    )
                })?,
                _ => {
                    return Err(file_error(
                        source_name,
                        id_line,
                        format!(
                            "marker {}: \"{}\" is not a barcode id; template pattern \
                             markers are not supported, only barcode (matrix) ids that are \
                             ids of the dataset's dictionary",
                            k + 1,
                            excerpt(id_text)
                        ),
                    ));
                }
            };
            if id > 0x7fff {
                return Err(file_error(
                    source_name,
                    id_line,
                    format!("barcode id {id} has upper bits set (a global id): not supported"),
                ));
            }
            let id = id as usize;
            if let Some(other) = markers.iter().find(|m| m.id == id) {
                return Err(file_error(
                    source_name,
                    id_line,
                    format!(
                        "barcode id {id} appears twice (first at line {})",
                        other.line
                    ),
                ));
            }
            let (w_line, w_text) = next(k, "the marker width")?;
            let width_mm = match numbers(w_text).as_deref() {
                Some([w]) if *w > 0.0 && *w < 1e5 => *w,
                _ => {
                    return Err(file_error(
                        source_name,
                        w_line,
                        format!(
                            "marker {id}: expected one positive width in millimetres, found \"{}\"",
                            excerpt(w_text)
                        ),
                    ));
                }
            };
            let mut rows = Vec::with_capacity(3);
            while rows.len() < 3 {
                let (r_line, r_text) = next(k, "three rows of the 3x4 transform")?;
                match numbers(r_text).as_deref() {
                    // ARToolKit 2.x: a line with the marker centre, skipped.
                    Some([_, _]) if rows.is_empty() => {}
                    Some(&[a, b, c, d]) => rows.push([a, b, c, d]),
                    _ => {
                        return Err(file_error(
                            source_name,
                            r_line,
                            format!(
                                "marker {id}: row {} of the 3x4 transform must be 4 numbers, found \"{}\"",
                                rows.len() + 1,
                                excerpt(r_text)
                            ),
                        ));
                    }
                }
            }
            let r = Matrix3::from_fn(|i, j| rows[i][j]);
            let err = (r.transpose() * r - Matrix3::identity()).abs().max();
            if err > 2e-3 || r.determinant() <= 0.0 {
                return Err(file_error(
                    source_name,
                    id_line,
                    format!(
                        "marker {id}: the 3x3 part of the transform is not a rotation \
                         (|RᵀR - I| = {err:.2e}, det = {:.4})",
                        r.determinant()
                    ),
                ));
            }
            let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r));
            let t = Vector3::new(rows[0][3], rows[1][3], rows[2][3]) * 1e-3;
            markers.push(MultimarkerMarker {
                id,
                width_m: width_mm * 1e-3,
                set_from_marker: Isometry3::from_parts(Translation3::from(t), rotation),
                line: id_line,
            });
        }
        if let Some((line, extra)) = lines.next() {
            return Err(file_error(
                source_name,
                line,
                format!(
                    "unexpected \"{}\" after the {n} markers the file declares",
                    excerpt(extra)
                ),
            ));
        }
        Ok(MultimarkerConfig {
            source: source_name.to_string(),
            markers,
        })
    }

    /// The file text (millimetres, ARToolKit layout) that [`MultimarkerConfig::parse`]
    /// reads back.
    pub fn to_dat(&self) -> String {
        let mut s = format!(
            "# ARToolKit-style multimarker file ({} markers): barcode id, width [mm],\n\
             # then the 3x4 transform [R | t] (mm) with p_set = T * p_marker.\n\n{}\n",
            self.markers.len(),
            self.markers.len()
        );
        for m in &self.markers {
            let r = m.set_from_marker.rotation.to_rotation_matrix();
            let t = m.set_from_marker.translation.vector * 1e3;
            s.push_str(&format!("\n{}\n{}\n", m.id, fmt_num(m.width_m * 1e3)));
            for i in 0..3 {
                s.push_str(&format!(
                    "{} {} {} {}\n",
                    fmt_num(r[(i, 0)]),
                    fmt_num(r[(i, 1)]),
                    fmt_num(r[(i, 2)]),
                    fmt_num(t[i])
                ));
            }
        }
        s
    }

    /// ARToolKit5's `multi-barcode-4x3.dat`: 12 markers, ids 0..11, 40 mm wide,
    /// centres x ∈ {-105, -35, 35, 105} mm, y ∈ {70, 0, -70} mm, row-major from the top
    /// left, all facing +z.
    pub fn grid_4x3() -> Self {
        let mut markers = Vec::with_capacity(12);
        for (j, y) in [70.0, 0.0, -70.0].into_iter().enumerate() {
            for (i, x) in [-105.0, -35.0, 35.0, 105.0].into_iter().enumerate() {
                markers.push(MultimarkerMarker {
                    id: 4 * j + i,
                    width_m: 0.04,
                    set_from_marker: Isometry3::translation(x * 1e-3, y * 1e-3, 0.0),
                    line: 0,
                });
            }
        }
        MultimarkerConfig {
            source: "multi-barcode-4x3".into(),
            markers,
        }
    }

    /// The non-planar three-face corner (`notes/marker-convention.md`): the floor
    /// z = 0 and the walls x = 0 and y = 0 of a cube corner, seen from inside, each
    /// with 2x2 markers 40 mm wide centred at 35 and 85 mm from the corner's edges,
    /// every marker's z axis pointing into the open space (towards (+, +, +)).
    /// Ids: floor 0..3 (`(x, y)` = (35, 35), (85, 35), (35, 85), (85, 85) mm), wall
    /// x = 0 4..7 (`(y, z)` in the same order, marker x along +y, y along +z), wall
    /// y = 0 8..11 (`(x, z)`, marker x along -x, y along +z).
    pub fn three_face_corner() -> Self {
        let (ex, ey, ez) = (Vector3::x(), Vector3::y(), Vector3::z());
        type Place = fn(f64, f64) -> Vector3<f64>;
        let faces: [(Matrix3<f64>, Place); 3] = [
            (Matrix3::from_columns(&[ex, ey, ez]), |a, b| {
                Vector3::new(a, b, 0.0)
            }),
            (Matrix3::from_columns(&[ey, ez, ex]), |a, b| {
                Vector3::new(0.0, a, b)
            }),
            (Matrix3::from_columns(&[-ex, ez, ey]), |a, b| {
                Vector3::new(a, 0.0, b)
            }),
        ];
        let mut markers = Vec::with_capacity(12);
        for (f, (r, at)) in faces.iter().enumerate() {
            let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(r));
            for (k, (a, b)) in [(35.0, 35.0), (85.0, 35.0), (35.0, 85.0), (85.0, 85.0)]
                .into_iter()
                .enumerate()
            {
                markers.push(MultimarkerMarker {
                    id: 4 * f + k,
                    width_m: 0.04,
                    set_from_marker: Isometry3::from_parts(
                        Translation3::from(at(a * 1e-3, b * 1e-3)),
                        rotation,
                    ),
                    line: 0,
                });
            }
        }
        MultimarkerConfig {
            source: "three-face corner".into(),
            markers,
        }
    }

    /// The marker with barcode id `id`.
    pub fn marker(&self, id: usize) -> Option<&MultimarkerMarker> {
        self.markers.iter().find(|m| m.id == id)
    }

    /// Corner `c` (0..4, OpenCV order) of marker `id` in the set frame.
    pub fn corner(&self, id: usize, c: usize) -> Option<Point3<f64>> {
        self.marker(id).filter(|_| c < 4).map(|m| m.corners()[c])
    }

    /// Checks that every id exists in `dict`.
    pub fn check_dictionary(&self, dict: &MarkerDictionary) -> Result<(), VisionError> {
        match self.markers.iter().find(|m| m.id >= dict.marker_count()) {
            Some(m) => Err(file_error(
                &self.source,
                m.line,
                format!(
                    "barcode id {} is not in {} (ids 0..{})",
                    m.id,
                    dict.name(),
                    dict.marker_count()
                ),
            )),
            None => Ok(()),
        }
    }

    /// Whether all marker corners lie on one plane.
    pub fn is_planar(&self) -> bool {
        let pts: Vec<Point3<f64>> = self.markers.iter().flat_map(|m| m.corners()).collect();
        plane_of(&pts).is_some()
    }

    /// The set's flat faces: markers grouped by orientation and plane (markers turned
    /// in their plane relative to each other form separate faces).
    pub fn faces(&self) -> Vec<MultimarkerFace> {
        let mut faces: Vec<MultimarkerFace> = Vec::new();
        for m in &self.markers {
            let r = m.set_from_marker.rotation;
            let local = r.inverse() * m.set_from_marker.translation.vector;
            let found = faces.iter_mut().find(|f| {
                f.set_from_face.rotation.angle_to(&r) < 1e-6
                    && (f.set_from_face.inverse()
                        * Point3::from(m.set_from_marker.translation.vector))
                    .z
                    .abs()
                        < 1e-7
            });
            match found {
                Some(f) => {
                    let p = f.set_from_face.inverse()
                        * Point3::from(m.set_from_marker.translation.vector);
                    f.markers.push((m.id, Point2::new(p.x, p.y), m.width_m));
                }
                None => faces.push(MultimarkerFace {
                    set_from_face: Isometry3::from_parts(
                        Translation3::from(r * Vector3::new(0.0, 0.0, local.z)),
                        r,
                    ),
                    markers: vec![(m.id, Point2::new(local.x, local.y), m.width_m)],
                }),
            }
        }
        faces
    }
}

fn fmt_num(v: f64) -> String {
    let v = if v.abs() < 1e-12 { 0.0 } else { v };
    let s = format!("{v:.6}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    s.to_string()
}

/// A multimarker set found in an image.
#[derive(Debug, Clone, PartialEq)]
pub struct MultimarkerDetection {
    /// `T_camera_set`.
    pub camera_from_target: Isometry3<f64>,
    /// The 2-D/3-D correspondences: corner id `4·marker id + c`, set-frame points
    /// (metres), pixels.
    pub detection: BoardDetection,
    /// Ids of the markers used, ascending.
    pub markers: Vec<usize>,
    /// Reprojection error of each corner (px), in the detection's order.
    pub residuals_px: Vec<f64>,
    pub rms_px: f64,
    /// Whether the corners used were coplanar (IPPE) or not (SQPnP).
    pub planar: bool,
}

/// Detects the markers of `config` (ids of `dictionary`) and fits `camera_from_target`
/// to all their corners at once. Markers of the dictionary that are not in the set,
/// and ids seen more than once, are ignored.
pub fn detect_multimarker(
    img: &GrayImage,
    config: &MultimarkerConfig,
    dictionary: &MarkerDictionary,
    camera: &CameraModel,
) -> Result<MultimarkerDetection, VisionError> {
    config.check_dictionary(dictionary)?;
    let (corners, ids) = raw_markers(img, dictionary, true)?;
    let ids: Vec<i32> = ids.to_vec();
    let quads = refined_quads(img, dictionary, &corners)?;
    let mut seen: BTreeMap<usize, Vec<Point2<f64>>> = BTreeMap::new();
    let mut all_refined = true;
    for (k, (quad, ok)) in quads.into_iter().enumerate() {
        let id = ids[k];
        if id < 0 || quad.len() != 4 || config.marker(id as usize).is_none() {
            continue;
        }
        if ids.iter().filter(|&&other| other == id).count() > 1 {
            continue;
        }
        all_refined &= ok;
        seen.insert(id as usize, quad);
    }
    if seen.is_empty() {
        return Err(VisionError::MarkersNotFound {
            what: format!("marker of the multimarker set {}", config.source),
            dictionary: dictionary.name(),
            width: img.width(),
            height: img.height(),
        });
    }
    let mut det = BoardDetection {
        target_points: Vec::new(),
        corner_ids: Vec::new(),
        pixels: Vec::new(),
        method: CornerMethod::ArucoMarkers,
        refined: all_refined,
    };
    for (&id, quad) in &seen {
        let m = config.marker(id).expect("filtered above");
        for (c, (p, uv)) in m.corners().into_iter().zip(quad).enumerate() {
            det.corner_ids.push(4 * id + c);
            det.target_points.push(p);
            det.pixels.push(*uv);
        }
    }
    let (pose, planar) = multimarker_pose(&det.target_points, &det.pixels, camera)?;
    Ok(MultimarkerDetection {
        camera_from_target: pose.camera_from_target,
        detection: det,
        markers: seen.keys().copied().collect(),
        residuals_px: pose.residuals_px,
        rms_px: pose.rms_px,
        planar,
    })
}

/// `T_set_plane` of a coplanar point set (z = the plane normal, origin at the
/// centroid), or `None` when the points are not coplanar (RMS distance from the best
/// plane above 1e-4 of their spread) or span no plane.
fn plane_of(points: &[Point3<f64>]) -> Option<Isometry3<f64>> {
    let n = points.len() as f64;
    let c = points.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = p.coords - c;
        cov += d * d.transpose();
    }
    cov /= n;
    let eig = SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let (l0, l1, l2) = (
        eig.eigenvalues[order[0]],
        eig.eigenvalues[order[1]],
        eig.eigenvalues[order[2]].max(0.0),
    );
    if l1 <= 1e-12 * l0.max(1e-30) || l2.sqrt() > 1e-4 * l0.sqrt() {
        return None;
    }
    // The normal is the eigenvector of the smallest eigenvalue; the in-plane axes are
    // built from it (the other two eigenvectors are not unique when their eigenvalues
    // are equal, e.g. for a square layout).
    let z = eig.eigenvectors.column(order[2]).normalize();
    let far = points
        .iter()
        .map(|p| p.coords - c)
        .max_by(|a, b| a.norm_squared().total_cmp(&b.norm_squared()))
        .unwrap_or_else(Vector3::x);
    let x = (far - z * far.dot(&z)).normalize();
    let y = z.cross(&x);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Some(Isometry3::from_parts(
        Translation3::from(c),
        UnitQuaternion::from_rotation_matrix(&r),
    ))
}

fn pose_from(rvec: &Mat, tvec: &Mat) -> Result<Isometry3<f64>, VisionError> {
    let r = vec3(rvec)?;
    let t = vec3(tvec)?;
    Ok(Isometry3::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_scaled_axis(r),
    ))
}

fn vec3(m: &Mat) -> Result<Vector3<f64>, VisionError> {
    let v = m.data_typed::<f64>().cv("pose vector")?;
    match v {
        [x, y, z] if [x, y, z].iter().all(|c| c.is_finite()) => Ok(Vector3::new(*x, *y, *z)),
        _ => Err(VisionError::Pose(format!(
            "solver returned a non-finite or malformed vector {v:?}"
        ))),
    }
}

fn mats_of(pose: &Isometry3<f64>) -> Result<(Mat, Mat), VisionError> {
    let r = pose.rotation.scaled_axis();
    let t = pose.translation.vector;
    Ok((
        Mat::from_slice_2d(&[[r.x], [r.y], [r.z]]).cv("rvec")?,
        Mat::from_slice_2d(&[[t.x], [t.y], [t.z]]).cv("tvec")?,
    ))
}

/// A pose and its per-point residuals (px).
type Fitted = (Isometry3<f64>, Vec<f64>);

/// Levenberg–Marquardt from `start` over all points; returns the pose and its
/// residuals (px), `None` if a point ends behind the camera.
fn refine(
    object: &Vector<Point3d>,
    image: &Vector<Point2d>,
    camera: &CameraModel,
    points: &[Point3<f64>],
    pixels: &[Point2<f64>],
    start: &Isometry3<f64>,
) -> Result<Option<Fitted>, VisionError> {
    let (k, dist) = camera_matrices(camera)?;
    let (mut rvec, mut tvec) = mats_of(start)?;
    let criteria = TermCriteria::new(
        opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
        100,
        1e-12,
    )
    .cv("TermCriteria")?;
    calib3d::solve_pnp_refine_lm(object, image, &k, &dist, &mut rvec, &mut tvec, criteria)
        .cv("solvePnPRefineLM")?;
    let pose = pose_from(&rvec, &tvec)?;
    let residuals: Option<Vec<f64>> = points
        .iter()
        .zip(pixels)
        .map(|(p, uv)| camera.project(&(pose * p)).map(|q| (q - uv).norm()))
        .collect();
    Ok(residuals.map(|r| (pose, r)))
}

fn rms(r: &[f64]) -> f64 {
    (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt()
}

/// `camera_from_target` from 3-D target points (any layout) and their pixels: IPPE +
/// LM when the points are coplanar, SQPnP + LM otherwise (see the module docs). Returns
/// the pose and whether the points were coplanar.
pub fn multimarker_pose(
    points: &[Point3<f64>],
    pixels: &[Point2<f64>],
    camera: &CameraModel,
) -> Result<(PoseEstimate, bool), VisionError> {
    let n = points.len();
    if pixels.len() != n {
        return Err(VisionError::Pose(format!(
            "{n} target points but {} pixels",
            pixels.len()
        )));
    }
    if n < 4 {
        return Err(VisionError::TooFewCorners {
            found: n,
            needed: 4,
        });
    }
    if points
        .iter()
        .any(|p| !p.coords.iter().all(|v| v.is_finite()))
        || pixels
            .iter()
            .any(|p| !p.coords.iter().all(|v| v.is_finite()))
    {
        return Err(VisionError::Pose("non-finite target point or pixel".into()));
    }
    let object: Vector<Point3d> = points.iter().map(|p| Point3d::new(p.x, p.y, p.z)).collect();
    let image: Vector<Point2d> = pixels.iter().map(|p| Point2d::new(p.x, p.y)).collect();
    let (k, dist) = camera_matrices(camera)?;
    let behind = || VisionError::Pose("the estimated pose puts a corner behind the camera".into());
    let planar = plane_of(points);
    let (pose, residuals) = if let Some(set_from_plane) = planar {
        let plane_from_set = set_from_plane.inverse();
        let local: Vector<Point3d> = points
            .iter()
            .map(|p| {
                let q = plane_from_set * p;
                Point3d::new(q.x, q.y, 0.0)
            })
            .collect();
        let mut rvecs = Vector::<Mat>::new();
        let mut tvecs = Vector::<Mat>::new();
        let mut errors = Mat::default();
        let found = calib3d::solve_pnp_generic(
            &local,
            &image,
            &k,
            &dist,
            &mut rvecs,
            &mut tvecs,
            false,
            calib3d::SolvePnPMethod::SOLVEPNP_IPPE,
            &Mat::default(),
            &Mat::default(),
            &mut errors,
        )
        .cv("solvePnPGeneric(IPPE)")?;
        let mut candidates = Vec::new();
        for s in 0..(found.max(0) as usize).min(rvecs.len()) {
            let camera_from_plane =
                pose_from(&rvecs.get(s).cv("rvec")?, &tvecs.get(s).cv("tvec")?)?;
            if let Some(c) = refine(
                &object,
                &image,
                camera,
                points,
                pixels,
                &(camera_from_plane * plane_from_set),
            )? {
                candidates.push(c);
            }
        }
        candidates.sort_by(|a, b| rms(&a.1).total_cmp(&rms(&b.1)));
        let mut it = candidates.into_iter();
        let best = it.next().ok_or_else(|| {
            VisionError::Pose("IPPE found no solution in front of the camera".into())
        })?;
        if let Some(second) = it.next() {
            let (e1, e2) = (rms(&best.1), rms(&second.1));
            let angle = best.0.rotation.angle_to(&second.0.rotation);
            if e2 <= AMBIGUITY_RATIO * e1 + AMBIGUITY_MARGIN_PX && angle > 1f64.to_radians() {
                return Err(VisionError::AmbiguousPose(format!(
                    "the two planar solutions fit the {n} corners with {e1:.3} px and {e2:.3} px \
                     RMS and differ by {:.1}°: more markers or a less frontal view are needed",
                    angle.to_degrees()
                )));
            }
        }
        best
    } else {
        let mut rvec = Mat::default();
        let mut tvec = Mat::default();
        let ok = calib3d::solve_pnp(
            &object,
            &image,
            &k,
            &dist,
            &mut rvec,
            &mut tvec,
            false,
            calib3d::SOLVEPNP_SQPNP,
        )
        .cv("solvePnP(SQPnP)")?;
        if !ok {
            return Err(VisionError::Pose("SQPnP found no solution".into()));
        }
        let start = pose_from(&rvec, &tvec)?;
        refine(&object, &image, camera, points, pixels, &start)?.ok_or_else(behind)?
    };
    let rms_px = rms(&residuals);
    Ok((
        PoseEstimate {
            camera_from_target: pose,
            residuals_px: residuals,
            rms_px,
        },
        planar.is_some(),
    ))
}

/// Largest side, in pixels, of a face image [`render_face`] draws.
const MAX_FACE_SIDE: f64 = 30_000.0;

/// Draws one face of a set (OpenCV's `drawMarker`, one-cell black border) on a white
/// sheet reaching `margin_m` beyond the markers, at `px_per_m`. Returns the image and
/// the face-frame `(x, y)` of the image's top-left corner (x right, y up: pixel
/// `(col, row)` covers x ∈ [x0 + col/px_per_m, x0 + (col+1)/px_per_m) and
/// y ∈ (y0 - (row+1)/px_per_m, y0 - row/px_per_m]). Marker edges land on pixel
/// boundaries (rounded to the nearest one unless `px_per_m` makes them exact).
pub fn render_face(
    face: &MultimarkerFace,
    dictionary: &MarkerDictionary,
    px_per_m: f64,
    margin_m: f64,
) -> Result<(GrayImage, Point2<f64>), VisionError> {
    if face.markers.is_empty() {
        return Err(VisionError::InvalidTarget("a face without markers".into()));
    }
    if !(px_per_m.is_finite() && px_per_m > 0.0 && margin_m.is_finite() && margin_m >= 0.0) {
        return Err(VisionError::InvalidTarget(format!(
            "resolution {px_per_m} px/m and margin {margin_m} m must be positive and finite"
        )));
    }
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for (_, c, w) in &face.markers {
        x0 = x0.min(c.x - w / 2.0);
        x1 = x1.max(c.x + w / 2.0);
        y0 = y0.min(c.y - w / 2.0);
        y1 = y1.max(c.y + w / 2.0);
    }
    let (left, top) = (x0 - margin_m, y1 + margin_m);
    let cols = ((x1 + margin_m - left) * px_per_m).round();
    let rows = ((top - (y0 - margin_m)) * px_per_m).round();
    if !(cols >= 1.0 && rows >= 1.0 && cols <= MAX_FACE_SIDE && rows <= MAX_FACE_SIDE) {
        return Err(VisionError::InvalidTarget(format!(
            "a {cols}x{rows} px face image: need 1 to {MAX_FACE_SIDE} px per side"
        )));
    }
    let (cols, rows) = (cols as usize, rows as usize);
    let mut px = vec![255u8; cols * rows];
    let cv_dict = dictionary.opencv()?;
    let cells = f64::from(cv_dict.marker_size() + 2);
    for (id, c, w) in &face.markers {
        if *id >= dictionary.marker_count() {
            return Err(VisionError::InvalidTarget(format!(
                "marker id {id} is not in {}",
                dictionary.name()
            )));
        }
        let side = (w * px_per_m).round();
        if side < cells {
            return Err(VisionError::InvalidTarget(format!(
                "marker {id}: {side} px is fewer than its {cells} cells"
            )));
        }
        let mut m = Mat::default();
        opencv::aruco::draw_marker(&cv_dict, *id as i32, side as i32, &mut m, 1)
            .cv("drawMarker")?;
        let side = side as usize;
        let data = m.data_bytes().cv("drawMarker data")?;
        let c0 = ((c.x - w / 2.0 - left) * px_per_m).round() as i64;
        let r0 = ((top - (c.y + w / 2.0)) * px_per_m).round() as i64;
        for r in 0..side {
            for k in 0..side {
                let (rr, cc) = (r0 + r as i64, c0 + k as i64);
                if rr >= 0 && cc >= 0 && (rr as usize) < rows && (cc as usize) < cols {
                    px[rr as usize * cols + cc as usize] = data[r * side + k];
                }
            }
        }
    }
    Ok((
        GrayImage::from_raw(cols as u32, rows as u32, &px)?,
        Point2::new(left, top),
    ))
}
