//! Fiducial targets without OpenCV: marker dictionaries, printed sheets of markers and
//! squares, and the multimarker layouts of `notes/marker-convention.md`.
//!
//! The simulator must not link OpenCV (ARCHITECTURE.md), yet its targets must be exactly
//! what OpenCV detects. So the marker codes of OpenCV 4.6's predefined dictionaries are
//! embedded ([`codes`], generated from OpenCV once), and the board layouts (ChArUco,
//! grid) are written out here; `tests/markers_opencv.rs` checks every embedded marker
//! against `aruco::drawMarker` and the boards against `CharucoBoard::draw` /
//! `GridBoard::draw` pixel for pixel, and `tests/detection.rs` detects rendered targets
//! with the vision crate against the ground truth.
//!
//! A [`Sheet`] is a printed page: white paper with axis-aligned blocks on it (a black
//! square is a 1x1 block, a marker an `(n+2)²` block). Its texture regions (see
//! [`crate::texture`]) are exact and convex: every block cell is one region, and the
//! paper around the blocks is cut into the rectangles of the grid spanned by all block
//! edges, so only pixels that straddle a printed edge are supersampled.

mod codes;

use nalgebra::{Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::texture::{PAPER_WHITE, TONER_BLACK, TexSample, Texture};
use crate::{Iso3, SimError};

/// One of OpenCV's predefined dictionaries (the subset the simulator embeds).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Dictionary {
    name: &'static str,
    bits: usize,
    count: usize,
    codes: &'static [u64],
}

const DICTIONARIES: [(&str, usize, usize, &[u64]); 10] = [
    ("DICT_4X4_50", 4, 50, &codes::DICT_4X4),
    ("DICT_4X4_100", 4, 100, &codes::DICT_4X4),
    ("DICT_4X4_250", 4, 250, &codes::DICT_4X4),
    ("DICT_5X5_50", 5, 50, &codes::DICT_5X5),
    ("DICT_5X5_100", 5, 100, &codes::DICT_5X5),
    ("DICT_5X5_250", 5, 250, &codes::DICT_5X5),
    ("DICT_6X6_50", 6, 50, &codes::DICT_6X6),
    ("DICT_6X6_100", 6, 100, &codes::DICT_6X6),
    ("DICT_6X6_250", 6, 250, &codes::DICT_6X6),
    ("DICT_APRILTAG_36h11", 6, 587, &codes::DICT_APRILTAG_36H11),
];

impl Dictionary {
    /// Every dictionary the simulator can print.
    pub fn all() -> impl Iterator<Item = Dictionary> {
        DICTIONARIES
            .iter()
            .map(|&(name, bits, count, codes)| Dictionary {
                name,
                bits,
                count,
                codes,
            })
    }

    /// By OpenCV name (`DICT_4X4_50` … `DICT_6X6_250`, `DICT_APRILTAG_36h11`).
    pub fn parse(name: &str) -> Result<Dictionary, SimError> {
        Dictionary::all().find(|d| d.name == name).ok_or_else(|| {
            let known: Vec<&str> = DICTIONARIES.iter().map(|d| d.0).collect();
            SimError::invalid(
                "dictionary",
                format!("`{name}` is not one the simulator can print ({known:?})"),
            )
        })
    }

    /// OpenCV's name.
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// Inner bits per side (`n`; the marker is `n + 2` cells wide with its border).
    pub fn bits(&self) -> usize {
        self.bits
    }

    /// Valid ids are `0..count()`.
    pub fn count(&self) -> usize {
        self.count
    }

    /// Marker `id` as OpenCV draws it with a one-cell border: `(n+2)²` grey levels,
    /// row-major from the top-left of the printed image, 0 = black, 255 = white.
    pub fn marker_bitmap(&self, id: usize) -> Result<Vec<u8>, SimError> {
        if id >= self.count {
            return Err(SimError::invalid(
                "marker id",
                format!("{id} is not in {} (ids 0..{})", self.name, self.count),
            ));
        }
        let (n, code) = (self.bits, self.codes[id]);
        let w = n + 2;
        let mut px = vec![0u8; w * w];
        for r in 0..n {
            for c in 0..n {
                let bit = (code >> (n * n - 1 - (r * n + c))) & 1;
                px[(r + 1) * w + c + 1] = if bit == 1 { 255 } else { 0 };
            }
        }
        Ok(px)
    }
}

/// An axis-aligned bitmap printed on a [`Sheet`].
#[derive(Debug, Clone, PartialEq)]
pub struct Block {
    /// The block's corner with the smallest `x` and `y`, m.
    pub min_m: [f64; 2],
    pub cell_m: f64,
    pub cols: usize,
    pub rows: usize,
    /// Row-major grey levels (0 = black, 255 = white), `cols · rows`.
    pub pixels: Vec<u8>,
    /// Bitmap row 0 is at the largest `y` (a frame with y up) instead of the smallest.
    pub row0_at_max_y: bool,
}

impl Block {
    fn max_m(&self) -> [f64; 2] {
        [
            self.min_m[0] + self.cols as f64 * self.cell_m,
            self.min_m[1] + self.rows as f64 * self.cell_m,
        ]
    }
}

const NO_BLOCK: u32 = u32::MAX;
const BLOCK_REGION: u32 = 0x8000_0000;

/// White paper with non-overlapping [`Block`]s printed on it (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Sheet {
    blocks: Vec<Block>,
    xs: Vec<f64>,
    ys: Vec<f64>,
    /// Block index of each grid cell, `(ys.len() + 1) × (xs.len() + 1)`, row-major.
    cell_block: Vec<u32>,
    pub white: f32,
    pub black: f32,
}

impl Sheet {
    /// A sheet of paper and toner; errors on overlapping or malformed blocks.
    pub fn new(blocks: Vec<Block>) -> Result<Sheet, SimError> {
        if blocks.len() >= 1 << 19 {
            return Err(SimError::invalid("sheet", "too many blocks"));
        }
        for (i, b) in blocks.iter().enumerate() {
            if b.cols == 0
                || b.rows == 0
                || b.cols * b.rows >= 1 << 12
                || b.pixels.len() != b.cols * b.rows
                || !(b.cell_m > 0.0 && b.cell_m.is_finite())
                || b.min_m.iter().any(|v| !v.is_finite())
            {
                return Err(SimError::invalid(
                    "sheet",
                    format!("block {i} is malformed (at most 4095 cells, sizes must agree)"),
                ));
            }
        }
        let axis = |k: usize| {
            let mut v: Vec<f64> = blocks
                .iter()
                .flat_map(|b| [b.min_m[k], b.max_m()[k]])
                .collect();
            v.sort_by(f64::total_cmp);
            v.dedup();
            v
        };
        let (xs, ys) = (axis(0), axis(1));
        let mid = |edges: &[f64], i: usize| -> f64 {
            match (i.checked_sub(1).map(|j| edges[j]), edges.get(i)) {
                (Some(a), Some(&b)) => 0.5 * (a + b),
                (Some(a), None) => a + 1.0,
                (None, Some(&b)) => b - 1.0,
                (None, None) => 0.0,
            }
        };
        let mut cell_block = vec![NO_BLOCK; (xs.len() + 1) * (ys.len() + 1)];
        for iy in 0..=ys.len() {
            for ix in 0..=xs.len() {
                let (x, y) = (mid(&xs, ix), mid(&ys, iy));
                let inside: Vec<usize> = (0..blocks.len())
                    .filter(|&k| {
                        let (lo, hi) = (blocks[k].min_m, blocks[k].max_m());
                        x > lo[0] && x < hi[0] && y > lo[1] && y < hi[1]
                    })
                    .collect();
                match inside.as_slice() {
                    [] => {}
                    [k] => cell_block[iy * (xs.len() + 1) + ix] = *k as u32,
                    _ => {
                        return Err(SimError::invalid(
                            "sheet",
                            format!("blocks {inside:?} overlap at ({x}, {y})"),
                        ));
                    }
                }
            }
        }
        Ok(Sheet {
            blocks,
            xs,
            ys,
            cell_block,
            white: PAPER_WHITE,
            black: TONER_BLACK,
        })
    }

    /// The printed blocks.
    pub fn blocks(&self) -> &[Block] {
        &self.blocks
    }

    /// Grey level (0..=255) at `(x, y)`: what a 255-level print of the sheet shows.
    pub fn level(&self, x: f64, y: f64) -> u8 {
        match self.locate(x, y) {
            Located::Paper(_) => 255,
            Located::Cell(b, i) => self.blocks[b].pixels[i],
        }
    }

    fn locate(&self, x: f64, y: f64) -> Located {
        let ix = self.xs.partition_point(|&e| e <= x);
        let iy = self.ys.partition_point(|&e| e <= y);
        let cell = iy * (self.xs.len() + 1) + ix;
        let b = self.cell_block[cell];
        if b == NO_BLOCK {
            return Located::Paper(cell as u32);
        }
        let block = &self.blocks[b as usize];
        let i = ((x - block.min_m[0]) / block.cell_m).floor();
        let j = ((y - block.min_m[1]) / block.cell_m).floor();
        let i = i.clamp(0.0, (block.cols - 1) as f64) as usize;
        let mut j = j.clamp(0.0, (block.rows - 1) as f64) as usize;
        if block.row0_at_max_y {
            j = block.rows - 1 - j;
        }
        Located::Cell(b as usize, j * block.cols + i)
    }
}

enum Located {
    Paper(u32),
    Cell(usize, usize),
}

impl Texture for Sheet {
    fn sample(&self, x: f64, y: f64) -> TexSample {
        match self.locate(x, y) {
            Located::Paper(cell) => TexSample {
                reflectance: self.white,
                region: cell,
            },
            Located::Cell(b, i) => {
                let level = self.blocks[b].pixels[i] as f32 / 255.0;
                TexSample {
                    reflectance: self.black + (self.white - self.black) * level,
                    region: BLOCK_REGION | ((b as u32) << 12) | i as u32,
                }
            }
        }
    }
}

/// A marker bitmap as a block with its centre at `centre_m` and side `width_m`.
fn marker_block(
    dict: &Dictionary,
    id: usize,
    centre_m: [f64; 2],
    width_m: f64,
    row0_at_max_y: bool,
) -> Result<Block, SimError> {
    let cells = dict.bits() + 2;
    let cell_m = width_m / cells as f64;
    Ok(Block {
        min_m: [centre_m[0] - width_m / 2.0, centre_m[1] - width_m / 2.0],
        cell_m,
        cols: cells,
        rows: cells,
        pixels: dict.marker_bitmap(id)?,
        row0_at_max_y,
    })
}

/// A ChArUco board in OpenCV 4.6's layout and target frame (x right, y down, z into the
/// board; origin at the outer corner of square (0, 0), which is black): squares
/// `(x, y)` with `x + y` odd hold markers, ids `0, 1, …` row by row from the top.
/// Only boards with an odd number of rows are accepted: OpenCV 4.6 changed the layout
/// of even-row boards (the vision crate's docs explain the trap).
pub fn charuco_sheet(
    squares: [u32; 2],
    square_m: f64,
    marker_m: f64,
    dictionary: &str,
) -> Result<Sheet, SimError> {
    let dict = Dictionary::parse(dictionary)?;
    let [c, r] = squares.map(|v| v as usize);
    if c < 2 || r < 3 || r % 2 == 0 || c > 100 || r > 100 {
        return Err(SimError::invalid(
            "ChArUco board",
            format!("{c}x{r} squares: need 2..=100 columns and an odd number 3..=99 of rows"),
        ));
    }
    if !(marker_m > 0.0 && marker_m < square_m) {
        return Err(SimError::invalid(
            "ChArUco board",
            format!("marker {marker_m} m must be smaller than the square {square_m} m"),
        ));
    }
    let mut blocks = vec![];
    let mut id = 0;
    for y in 0..r {
        for x in 0..c {
            let lo = [x as f64 * square_m, y as f64 * square_m];
            if (x + y) % 2 == 0 {
                blocks.push(Block {
                    min_m: lo,
                    cell_m: square_m,
                    cols: 1,
                    rows: 1,
                    pixels: vec![0],
                    row0_at_max_y: false,
                });
            } else {
                let centre = [lo[0] + square_m / 2.0, lo[1] + square_m / 2.0];
                blocks.push(marker_block(&dict, id, centre, marker_m, false)?);
                id += 1;
            }
        }
    }
    Sheet::new(blocks)
}

/// An ArUco grid board in OpenCV 4.6's `GridBoard` layout and frame (x right, y down,
/// z into the board): marker `(i, j)`, id `first_id + j·cols + i`, has its top-left
/// corner at `(i·(m + sep), j·(m + sep))`.
pub fn aruco_grid_sheet(
    markers: [u32; 2],
    marker_m: f64,
    separation_m: f64,
    dictionary: &str,
    first_id: u32,
) -> Result<Sheet, SimError> {
    let dict = Dictionary::parse(dictionary)?;
    let [c, r] = markers.map(|v| v as usize);
    if c == 0 || r == 0 || c > 100 || r > 100 || !(marker_m > 0.0 && separation_m >= 0.0) {
        return Err(SimError::invalid(
            "ArUco grid",
            format!("{c}x{r} markers of {marker_m} m, separation {separation_m} m"),
        ));
    }
    let pitch = marker_m + separation_m;
    let mut blocks = vec![];
    for j in 0..r {
        for i in 0..c {
            let id = first_id as usize + j * c + i;
            let centre = [
                i as f64 * pitch + marker_m / 2.0,
                j as f64 * pitch + marker_m / 2.0,
            ];
            blocks.push(marker_block(&dict, id, centre, marker_m, false)?);
        }
    }
    Sheet::new(blocks)
}

/// One marker of a multimarker set: `p_set = set_from_marker · p_marker`, in the
/// marker-local frame of `notes/marker-convention.md` (centre origin, x right, y up in
/// the printed image, z out of the printed face).
#[derive(Debug, Clone, PartialEq)]
pub struct PlacedMarker {
    pub id: usize,
    pub width_m: f64,
    pub set_from_marker: Iso3,
}

impl PlacedMarker {
    /// The four corners in the set frame, in OpenCV's order (top-left, top-right,
    /// bottom-right, bottom-left).
    pub fn corners_in_set(&self) -> [Point3<f64>; 4] {
        let h = self.width_m / 2.0;
        [(-h, h), (h, h), (h, -h), (-h, -h)]
            .map(|(x, y)| self.set_from_marker * Point3::new(x, y, 0.0))
    }
}

/// The planar grid of ARToolKit5's `multi-barcode-4x3.dat` generalised: `cols x rows`
/// markers of `width_m` at `pitch_m`, centred on the set origin, identity rotations,
/// ids `first_id + row·cols + col` with row 0 at the top (+y).
pub fn planar_grid(
    cols: usize,
    rows: usize,
    width_m: f64,
    pitch_m: f64,
    first_id: usize,
) -> Vec<PlacedMarker> {
    let mut out = vec![];
    for j in 0..rows {
        for i in 0..cols {
            let x = (i as f64 - (cols - 1) as f64 / 2.0) * pitch_m;
            let y = ((rows - 1) as f64 / 2.0 - j as f64) * pitch_m;
            out.push(PlacedMarker {
                id: first_id + j * cols + i,
                width_m,
                set_from_marker: Iso3::translation(x, y, 0.0),
            });
        }
    }
    out
}

/// The rotation of each face of the three-face corner: columns are the marker's x, y
/// and z axes in the set frame. Floor z = 0 (identity); wall x = 0 (z = +X, y = +Z,
/// x = +Y); wall y = 0 (z = +Y, y = +Z, x = −X). Every face's markers are upright
/// (y = +Z) on the walls and face the open space of the corner.
pub fn corner_face_rotations() -> [UnitQuaternion<f64>; 3] {
    let r = |x: Vector3<f64>, y: Vector3<f64>, z: Vector3<f64>| {
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
            Matrix3::from_columns(&[x, y, z]),
        ))
    };
    [
        UnitQuaternion::identity(),
        r(Vector3::y(), Vector3::z(), Vector3::x()),
        r(-Vector3::x(), Vector3::z(), Vector3::y()),
    ]
}

/// Where the face's 2-D coordinates `(a, b)` (its x and y axes) sit for face `k` of
/// the corner: the face spans `[0, face_m]²` of the two set axes it lies in.
fn corner_face_frame(k: usize, face_m: f64) -> Iso3 {
    let rot = corner_face_rotations()[k];
    // Put the face's local (0, 0) so that the face covers the positive quadrant.
    let origin = match k {
        0 => Vector3::zeros(),
        1 => Vector3::zeros(),
        _ => Vector3::new(face_m, 0.0, 0.0),
    };
    Iso3::from_parts(Translation3::from(origin), rot)
}

/// The non-planar three-face corner of `notes/marker-convention.md`: floor (ids
/// `first_id..+n²`), wall x = 0 (next `n²`), wall y = 0 (last `n²`), `n x n` markers
/// per face of side `face_m`, at `pitch_m`, centred on each face, row 0 at the face's
/// top (+y of the face).
pub fn three_face_corner(
    per_side: usize,
    width_m: f64,
    pitch_m: f64,
    face_m: f64,
    first_id: usize,
) -> Vec<PlacedMarker> {
    let mut out = vec![];
    let offset = (face_m - (per_side - 1) as f64 * pitch_m) / 2.0;
    for k in 0..3 {
        let set_from_face = corner_face_frame(k, face_m);
        // Face-local coordinates: x in face's x direction from 0..face_m. For the wall
        // y = 0 the face's x runs along −X from X = face_m.
        for j in 0..per_side {
            for i in 0..per_side {
                let a = offset + i as f64 * pitch_m;
                let b = offset + (per_side - 1 - j) as f64 * pitch_m;
                out.push(PlacedMarker {
                    id: first_id + k * per_side * per_side + j * per_side + i,
                    width_m,
                    set_from_marker: set_from_face * Iso3::translation(a, b, 0.0),
                });
            }
        }
    }
    out
}

/// `set_from_face` of the corner's face `k` (its quad covers `[0, face_m]²`).
pub fn three_face_corner_faces(face_m: f64) -> [Iso3; 3] {
    [0, 1, 2].map(|k| corner_face_frame(k, face_m))
}

/// The printed sheet of the markers lying in the `z = 0` plane of `set_from_plane`
/// (markers whose frame is the plane's turned by under 1e-6 rad), in the plane's coordinates.
pub fn markers_sheet(
    markers: &[PlacedMarker],
    set_from_plane: &Iso3,
    dictionary: &str,
) -> Result<Sheet, SimError> {
    let dict = Dictionary::parse(dictionary)?;
    let mut blocks = vec![];
    for m in markers {
        let plane_from_marker = set_from_plane.inverse() * m.set_from_marker;
        let t = plane_from_marker.translation.vector;
        let r = plane_from_marker.rotation;
        if t.z.abs() > 1e-9 || r.angle() > 1e-6 {
            continue;
        }
        blocks.push(marker_block(&dict, m.id, [t.x, t.y], m.width_m, true)?);
    }
    Sheet::new(blocks)
}

/// The ARToolKit multimarker file (facts.md §3.1; millimetres) of `markers`.
pub fn artoolkit_multimarker_file(markers: &[PlacedMarker], comment: &str) -> String {
    let mut s = String::new();
    for line in comment.lines() {
        s.push_str(&format!("# {line}\n"));
    }
    s.push_str(&format!("\n{}\n", markers.len()));
    let num = |v: f64| {
        // Round to a nanometre, and never print "-0".
        let v = (v * 1e6).round() / 1e6;
        let v = if v == 0.0 { 0.0 } else { v };
        format!("{v:.6}")
    };
    for m in markers {
        let r = m.set_from_marker.rotation.to_rotation_matrix();
        let t = m.set_from_marker.translation.vector * 1000.0;
        s.push_str(&format!("\n{:02}\n{}\n", m.id, num(m.width_m * 1000.0)));
        for i in 0..3 {
            s.push_str(&format!(
                "{} {} {} {}\n",
                num(r[(i, 0)]),
                num(r[(i, 1)]),
                num(r[(i, 2)]),
                num(t[i])
            ));
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dictionaries_parse_and_ids_are_checked() {
        let d = Dictionary::parse("DICT_4X4_50").unwrap();
        assert_eq!((d.bits(), d.count()), (4, 50));
        assert!(d.marker_bitmap(50).is_err());
        assert!(Dictionary::parse("DICT_4X4_51").is_err());
        let px = d.marker_bitmap(0).unwrap();
        assert_eq!(px.len(), 36);
        // The border is black.
        assert!((0..6).all(|k| px[k] == 0 && px[30 + k] == 0 && px[6 * k] == 0));
        // Different ids give different markers.
        assert_ne!(px, d.marker_bitmap(1).unwrap());
    }

    #[test]
    fn the_4x3_layout_is_artoolkits() {
        let m = planar_grid(4, 3, 0.04, 0.07, 0);
        assert_eq!(m.len(), 12);
        let c = |k: usize| m[k].set_from_marker.translation.vector * 1000.0;
        assert!((c(0) - Vector3::new(-105.0, 70.0, 0.0)).norm() < 1e-9);
        assert!((c(11) - Vector3::new(105.0, -70.0, 0.0)).norm() < 1e-9);
        let text = artoolkit_multimarker_file(&m, "test");
        let lines: Vec<&str> = text
            .lines()
            .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
            .collect();
        assert_eq!(lines[0], "12");
        assert_eq!(lines[1], "00");
        assert_eq!(lines[2], "40.000000");
        assert_eq!(lines[3], "1.000000 0.000000 0.000000 -105.000000");
        assert_eq!(lines.len(), 1 + 12 * 5);
    }

    #[test]
    fn corner_faces_point_into_the_open_space() {
        let markers = three_face_corner(2, 0.04, 0.06, 0.13, 0);
        assert_eq!(markers.len(), 12);
        let viewer = Point3::new(1.0, 1.0, 1.0);
        for m in &markers {
            let z = m.set_from_marker.rotation * Vector3::z();
            let c = m.set_from_marker * Point3::origin();
            // Every marker lies on its face inside [0, 0.13]³ and faces the viewer.
            assert!(c.iter().all(|v| (-1e-12..=0.13).contains(v)), "{c}");
            assert!(z.dot(&(viewer - c)) > 0.0);
            // Upright on the walls: marker y is world +z.
            if m.id >= 4 {
                assert!((m.set_from_marker.rotation * Vector3::y() - Vector3::z()).norm() < 1e-12);
            }
        }
        // Each face's sheet holds exactly its four markers.
        for (k, face) in three_face_corner_faces(0.13).iter().enumerate() {
            let sheet = markers_sheet(&markers, face, "DICT_4X4_50").unwrap();
            assert_eq!(sheet.blocks().len(), 4, "face {k}");
            for b in sheet.blocks() {
                let hi = b.max_m();
                assert!(b.min_m.iter().chain(&hi).all(|v| (0.0..=0.13).contains(v)));
            }
        }
    }

    #[test]
    fn sheet_regions_are_exact() {
        let sheet = charuco_sheet([5, 3], 0.04, 0.028, "DICT_5X5_100").unwrap();
        // Square (0, 0) is black, (1, 0) holds marker 0 with a black border.
        assert_eq!(sheet.level(0.02, 0.02), 0);
        assert_eq!(sheet.level(0.041, 0.001), 255);
        assert_eq!(sheet.level(0.04 + 0.0065, 0.0065), 0);
        // Paper regions differ across a block, cells within a block differ.
        let a = sheet.sample(0.041, 0.001).region;
        let b = sheet.sample(0.079, 0.039).region;
        assert_ne!(a, b);
        assert!(charuco_sheet([5, 4], 0.04, 0.028, "DICT_5X5_100").is_err());
        let overlapping = vec![
            marker_block(
                &Dictionary::parse("DICT_4X4_50").unwrap(),
                0,
                [0.0, 0.0],
                0.04,
                true,
            )
            .unwrap(),
            marker_block(
                &Dictionary::parse("DICT_4X4_50").unwrap(),
                1,
                [0.01, 0.0],
                0.04,
                true,
            )
            .unwrap(),
        ];
        assert!(Sheet::new(overlapping).is_err());
    }
}
