//! The calibration target of a scene as the generator needs it: its printed surfaces,
//! the points that must be in view, where to look from, what `dataset.json` says about
//! it, and the extra files (an ARToolKit multimarker file) the dataset carries.
//!
//! A [`TargetModel`] is a renderable, not another description of the target: the
//! target it stands for is its `manifest`, the `dataset.json` block every other path
//! reads into the one `b2b_vision::Target` (the simulator links no OpenCV, so it
//! stops at the file schema). Its `centre` and `view_axis` are the ones
//! `b2b_vision::Target` computes (tested in `pipeline/tests/targets.rs`).

use std::path::PathBuf;
use std::sync::Arc;

use b2b_dataset::Target;
use nalgebra::{Point3, Vector3};

use crate::markers::{self, PlacedMarker};
use crate::scene::{BoardSpec, MultimarkerLayout, SceneTarget};
use crate::texture::{Checkerboard, Texture};
use crate::{Iso3, SimError};

/// The multimarker file's name in the dataset (`target.config`).
pub const MULTIMARKER_FILE: &str = "multimarker.dat";

/// One printed planar surface of the target, in the target frame.
#[derive(Debug, Clone)]
pub struct TargetQuad {
    pub target_from_quad: Iso3,
    pub min: [f64; 2],
    pub max: [f64; 2],
    pub texture: Arc<dyn Texture>,
}

/// A target ready for planning, rendering and writing.
#[derive(Debug, Clone)]
pub struct TargetModel {
    /// What `dataset.json` says.
    pub manifest: Target,
    pub quads: Vec<TargetQuad>,
    /// Points (target frame) that must all be in the image, each with the outward
    /// normal of its printed face (towards where it can be seen from).
    pub key_points: Vec<(Point3<f64>, Vector3<f64>)>,
    /// The point viewpoints look at (before jitter), target frame.
    pub centre: Point3<f64>,
    /// Unit direction from the target towards the middle of the viewing cone.
    pub view_axis: Vector3<f64>,
    /// The markers of a multimarker target (set frame), empty otherwise.
    pub markers: Vec<PlacedMarker>,
    /// Files to write into the dataset: path relative to it, contents.
    pub files: Vec<(PathBuf, String)>,
}

fn quad(texture: Arc<dyn Texture>, min: [f64; 2], max: [f64; 2]) -> TargetQuad {
    TargetQuad {
        target_from_quad: Iso3::identity(),
        min,
        max,
        texture,
    }
}

impl TargetModel {
    /// A printed checkerboard (the frame of shared/dataset-format.md).
    pub fn checkerboard(b: &BoardSpec) -> TargetModel {
        let board = Checkerboard::new(b.inner_corners, b.square_m, b.margin_m);
        let (min, max) = board.extent();
        let down = -Vector3::z();
        TargetModel {
            manifest: Target::Checkerboard {
                inner_corners: b.inner_corners,
                square_m: b.square_m,
            },
            quads: vec![quad(Arc::new(board), min, max)],
            key_points: b2b_calib::synth::board_points(
                b.inner_corners[0] as usize,
                b.inner_corners[1] as usize,
                b.square_m,
            )
            .into_iter()
            .map(|p| (p, down))
            .collect(),
            centre: Point3::new(
                (b.inner_corners[0] - 1) as f64 * b.square_m / 2.0,
                (b.inner_corners[1] - 1) as f64 * b.square_m / 2.0,
                0.0,
            ),
            view_axis: down,
            markers: vec![],
            files: vec![],
        }
    }

    /// A marker target.
    pub fn build(spec: &SceneTarget) -> Result<TargetModel, SimError> {
        let down = -Vector3::z();
        match spec {
            SceneTarget::Charuco {
                squares,
                square_m,
                marker_m,
                dictionary,
                margin_m,
                ..
            } => {
                let sheet = markers::charuco_sheet(*squares, *square_m, *marker_m, dictionary)?;
                let [c, r] = squares.map(|v| v as usize);
                let s = *square_m;
                let (w, h) = (c as f64 * s, r as f64 * s);
                let mut key_points: Vec<(Point3<f64>, Vector3<f64>)> = vec![];
                for j in 1..r {
                    for i in 1..c {
                        key_points.push((Point3::new(i as f64 * s, j as f64 * s, 0.0), down));
                    }
                }
                for (x, y) in [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)] {
                    key_points.push((Point3::new(x, y, 0.0), down));
                }
                let m = *margin_m;
                Ok(TargetModel {
                    manifest: Target::Charuco {
                        squares: *squares,
                        square_m: s,
                        marker_m: *marker_m,
                        dictionary: dictionary.clone(),
                    },
                    quads: vec![quad(Arc::new(sheet), [-m, -m], [w + m, h + m])],
                    key_points,
                    centre: Point3::new(w / 2.0, h / 2.0, 0.0),
                    view_axis: down,
                    markers: vec![],
                    files: vec![],
                })
            }
            SceneTarget::ArucoGrid {
                markers: count,
                marker_m,
                separation_m,
                dictionary,
                first_id,
                margin_m,
                ..
            } => {
                let sheet = markers::aruco_grid_sheet(
                    *count,
                    *marker_m,
                    *separation_m,
                    dictionary,
                    *first_id,
                )?;
                let [c, r] = count.map(|v| v as usize);
                let pitch = marker_m + separation_m;
                let (w, h) = (
                    c as f64 * pitch - separation_m,
                    r as f64 * pitch - separation_m,
                );
                let key_points = sheet
                    .blocks()
                    .iter()
                    .flat_map(|b| {
                        let (lo, side) = (b.min_m, b.cell_m * b.cols as f64);
                        [(0.0, 0.0), (side, 0.0), (side, side), (0.0, side)]
                            .map(|(dx, dy)| (Point3::new(lo[0] + dx, lo[1] + dy, 0.0), down))
                    })
                    .collect();
                let m = *margin_m;
                Ok(TargetModel {
                    manifest: Target::ArucoGrid {
                        markers: *count,
                        marker_m: *marker_m,
                        separation_m: *separation_m,
                        dictionary: dictionary.clone(),
                        first_id: *first_id,
                    },
                    quads: vec![quad(Arc::new(sheet), [-m, -m], [w + m, h + m])],
                    key_points,
                    centre: Point3::new(w / 2.0, h / 2.0, 0.0),
                    view_axis: down,
                    markers: vec![],
                    files: vec![],
                })
            }
            SceneTarget::Multimarker {
                dictionary,
                layout,
                margin_m,
                ..
            } => {
                let (markers, quads, view_axis, what) = match layout {
                    MultimarkerLayout::Grid {
                        markers: [c, r],
                        marker_m,
                        pitch_m,
                        first_id,
                    } => {
                        let placed = markers::planar_grid(
                            *c as usize,
                            *r as usize,
                            *marker_m,
                            *pitch_m,
                            *first_id as usize,
                        );
                        let sheet = markers::markers_sheet(&placed, &Iso3::identity(), dictionary)?;
                        let hx = (*c as f64 - 1.0) / 2.0 * pitch_m + marker_m / 2.0 + margin_m;
                        let hy = (*r as f64 - 1.0) / 2.0 * pitch_m + marker_m / 2.0 + margin_m;
                        let q = quad(Arc::new(sheet), [-hx, -hy], [hx, hy]);
                        let what = if placed.len() == 1 {
                            "a single marker".to_owned()
                        } else {
                            format!("a planar {c}x{r} multimarker")
                        };
                        (placed, vec![q], Vector3::z(), what)
                    }
                    MultimarkerLayout::Corner {
                        per_side,
                        marker_m,
                        pitch_m,
                        face_m,
                        first_id,
                    } => {
                        let placed = markers::three_face_corner(
                            *per_side as usize,
                            *marker_m,
                            *pitch_m,
                            *face_m,
                            *first_id as usize,
                        );
                        let mut quads = vec![];
                        for face in markers::three_face_corner_faces(*face_m) {
                            let sheet = markers::markers_sheet(&placed, &face, dictionary)?;
                            quads.push(TargetQuad {
                                target_from_quad: face,
                                min: [0.0, 0.0],
                                max: [*face_m, *face_m],
                                texture: Arc::new(sheet),
                            });
                        }
                        let what = "a non-planar three-face corner multimarker (floor z=0, \
                                    walls x=0 and y=0)"
                            .to_owned();
                        (placed, quads, Vector3::new(1.0, 1.0, 1.0).normalize(), what)
                    }
                };
                let key_points = markers
                    .iter()
                    .flat_map(|m| {
                        let n = m.set_from_marker.rotation * Vector3::z();
                        m.corners_in_set().map(|p| (p, n))
                    })
                    .collect();
                let centre = Point3::from(
                    markers
                        .iter()
                        .map(|m| m.set_from_marker.translation.vector)
                        .sum::<Vector3<f64>>()
                        / markers.len() as f64,
                );
                let comment = format!(
                    "ARToolKit multimarker file written by b2b-sim: {what}.\n\
                     Barcode ids are ids of {dictionary}; widths and translations in mm;\n\
                     each 3x4 [R|t] maps marker-local points into the set frame."
                );
                let text = markers::artoolkit_multimarker_file(&markers, &comment);
                Ok(TargetModel {
                    manifest: Target::Multimarker {
                        config: PathBuf::from(MULTIMARKER_FILE),
                        dictionary: dictionary.clone(),
                    },
                    quads,
                    key_points,
                    centre,
                    view_axis,
                    markers,
                    files: vec![(PathBuf::from(MULTIMARKER_FILE), text)],
                })
            }
        }
    }
}
