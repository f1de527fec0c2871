//! The scene file: JSON describing the cell to simulate (`sim generate --scene FILE`).
//!
//! The world frame is robot 1's base (`base1`), so the ground truth
//! `T_base1_base2` is given directly. Poses are `{"t": [x, y, z], "rpy_deg": [r, p, y]}`
//! (fixed-axis roll, pitch, yaw: `R = Rz(y)·Ry(p)·Rx(r)`) or
//! `{"t": [...], "q": [qx, qy, qz, qw]}`. Unknown fields are errors (a misspelt
//! optional field would otherwise silently fall back to its default), and every error
//! names the file and the field. See `datasets/*/scene.json` for complete examples:
//! the target is either `board` (a checkerboard) or `target` (ChArUco, ArUco grid, or a
//! multimarker set: a planar grid, a single marker, or the three-face corner).

use std::path::{Path, PathBuf};

use b2b_dataset::Intrinsics;
use b2b_robot::IiwaModel;
use nalgebra::{Quaternion, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

use crate::render::{Lighting, Optics};
use crate::robot_error::RobotErrorModel;
use crate::sensor::{DepthModel, SensorNoise};
use crate::{Iso3, SimError};

/// A pose in the scene file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseSpec {
    pub t: [f64; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rpy_deg: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub q: Option<[f64; 4]>,
}

impl PoseSpec {
    /// The isometry; `field` names this pose in errors.
    pub fn to_iso(&self, file: &Path, field: &str) -> Result<Iso3, SimError> {
        let bad = |reason: String| SimError::SceneValue {
            file: file.to_owned(),
            field: field.to_owned(),
            reason,
        };
        if self.t.iter().any(|v| !v.is_finite() || v.abs() > 10.0) {
            return Err(bad(format!(
                "translation {:?} must be finite metres (|t| <= 10)",
                self.t
            )));
        }
        let rotation = match (self.rpy_deg, self.q) {
            (Some(_), Some(_)) => return Err(bad("give either rpy_deg or q, not both".into())),
            (None, None) => UnitQuaternion::identity(),
            (Some(rpy), None) => {
                if rpy.iter().any(|v| !v.is_finite()) {
                    return Err(bad(format!("rpy_deg {rpy:?} is not finite")));
                }
                let [r, p, y] = rpy.map(f64::to_radians);
                UnitQuaternion::from_euler_angles(r, p, y)
            }
            (None, Some([x, y, z, w])) => {
                let n = (x * x + y * y + z * z + w * w).sqrt();
                if !n.is_finite() || (n - 1.0).abs() > 1e-6 {
                    return Err(bad(format!(
                        "quaternion [qx, qy, qz, qw] has norm {n}, not 1"
                    )));
                }
                UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
            }
        };
        let [x, y, z] = self.t;
        Ok(Iso3::from_parts(Translation3::new(x, y, z), rotation))
    }
}

/// The checkerboard on the table: the printed sheet the scene places (its margin and
/// `T_base1_target`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardSpec {
    /// Inner corners `[columns, rows]`.
    pub inner_corners: [u32; 2],
    pub square_m: f64,
    /// White border around the squares, m.
    #[serde(default = "default_margin")]
    pub margin_m: f64,
    /// `T_base1_target` (target z points into the board, so a board lying printed side
    /// up has z pointing down).
    pub base1_from_target: PoseSpec,
}

fn default_margin() -> f64 {
    0.015
}

fn default_marker_margin() -> f64 {
    0.01
}

/// A marker target on the table (instead of `board`): the physical object the scene
/// places (its print margin and `T_base1_target`), not another target model; the
/// generator writes what `dataset.json` says of it ([`crate::target::TargetModel`]'s
/// `manifest`). The JSON tag is `kind`, as in `dataset.json`'s `target`; frames are
/// those of shared/dataset-format.md (ChArUco and grid: OpenCV's, z into the board)
/// and notes/marker-convention.md (multimarker).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum SceneTarget {
    /// A ChArUco board (OpenCV 4.6 layout; an odd number of rows).
    Charuco {
        squares: [u32; 2],
        square_m: f64,
        marker_m: f64,
        dictionary: String,
        /// White border around the squares, m.
        #[serde(default = "default_marker_margin")]
        margin_m: f64,
        base1_from_target: PoseSpec,
    },
    /// An ArUco grid board (OpenCV 4.6 `GridBoard`).
    ArucoGrid {
        markers: [u32; 2],
        marker_m: f64,
        separation_m: f64,
        dictionary: String,
        #[serde(default)]
        first_id: u32,
        #[serde(default = "default_marker_margin")]
        margin_m: f64,
        base1_from_target: PoseSpec,
    },
    /// A multimarker set; the generator writes its ARToolKit file into the dataset.
    Multimarker {
        dictionary: String,
        layout: MultimarkerLayout,
        /// White border around the markers of a planar layout, m.
        #[serde(default = "default_marker_margin")]
        margin_m: f64,
        /// `T_base1_set`.
        base1_from_target: PoseSpec,
    },
}

/// The markers of a multimarker set. The JSON tag is `shape`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case", deny_unknown_fields)]
pub enum MultimarkerLayout {
    /// Planar `markers = [columns, rows]` at `pitch_m`, centred on the set origin
    /// (ARToolKit5's multi-barcode-4x3.dat is `[4, 3]`, 0.04 m, pitch 0.07 m); `[1, 1]`
    /// is a single marker whose frame is the set frame.
    Grid {
        markers: [u32; 2],
        marker_m: f64,
        pitch_m: f64,
        #[serde(default)]
        first_id: u32,
    },
    /// The three-face corner: `per_side x per_side` markers on each of the floor and
    /// two walls, each face `face_m` square.
    Corner {
        per_side: u32,
        marker_m: f64,
        pitch_m: f64,
        face_m: f64,
        #[serde(default)]
        first_id: u32,
    },
}

/// One cart.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotSpec {
    pub id: String,
    pub model: IiwaModel,
    /// The camera's true intrinsics (`k1, k2, p1, p2[, k3]`); unknown fields are an
    /// error, as everywhere in a scene.
    #[serde(deserialize_with = "strict_intrinsics")]
    pub camera: Intrinsics,
    /// What the camera's own calibration says (a RealSense's factory intrinsics),
    /// when that is not the truth: the cart publishes it with every frame and
    /// `sim generate` writes it into `dataset.json`; the images are rendered through
    /// `camera`. Absent: the camera reports the truth.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[serde(deserialize_with = "strict_reported")]
    pub reported_camera: Option<Intrinsics>,
    /// `false`: the camera reports no intrinsics at all (a camera without a
    /// factory calibration): the cart publishes frames without them and `sim
    /// generate` leaves the robot's `camera` block out of `dataset.json`.
    #[serde(default = "reports_intrinsics", skip_serializing_if = "is_true")]
    pub reports_intrinsics: bool,
    /// `T_flange_camera` (camera optical frame: x right, y down, z forward).
    pub flange_from_camera: PoseSpec,
    #[serde(default)]
    pub error: RobotErrorModel,
    /// `T_base1_base` of this robot: required for the third robot on (`robots[2..]`),
    /// refused on the first two (robot 1's base is `base1`, robot 2's is the scene's
    /// `base1_from_base2`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base1_from_base: Option<PoseSpec>,
}

/// Where to look from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewpointSpec {
    /// Captures per robot.
    pub count: usize,
    /// Camera-to-board-centre distance range, m.
    #[serde(default = "default_distance")]
    pub distance_m: [f64; 2],
    /// Largest angle of the viewing direction from the board normal, deg.
    #[serde(default = "default_tilt")]
    pub max_tilt_deg: f64,
    /// Largest roll about the viewing direction, deg.
    #[serde(default = "default_roll")]
    pub max_roll_deg: f64,
    /// Random offset of the looked-at point from the board centre, m.
    #[serde(default = "default_jitter")]
    pub look_jitter_m: f64,
    /// Every inner corner must be at least this far inside the image, px.
    #[serde(default = "default_margin_px")]
    pub min_margin_px: f64,
}

fn reports_intrinsics() -> bool {
    true
}

fn is_true(v: &bool) -> bool {
    *v
}

fn default_distance() -> [f64; 2] {
    [0.35, 0.6]
}
fn default_tilt() -> f64 {
    35.0
}
fn default_roll() -> f64 {
    30.0
}
fn default_jitter() -> f64 {
    0.03
}
fn default_margin_px() -> f64 {
    15.0
}

/// Pointer-tip touch pairs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TouchSpec {
    pub count: usize,
    /// Touched points are drawn uniformly in this box of `base1`, m.
    pub region_min: [f64; 3],
    pub region_max: [f64; 3],
    /// Pointer length along the flange z axis, m.
    #[serde(default = "default_tool")]
    pub tool_length_m: f64,
    /// Per-axis σ of where the tip really touches relative to the point, m.
    #[serde(default)]
    pub tip_sigma_m: f64,
}

fn default_tool() -> f64 {
    0.12
}

/// A textured box (for the RGB-D features method).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxSpec {
    /// `T_base1_box`, the box centre.
    pub pose: PoseSpec,
    pub size_m: [f64; 3],
    /// Seed of the printed texture.
    #[serde(default)]
    pub texture_seed: u64,
}

/// Random occluders (a cable, a hand) floating between camera and board.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OccluderSpec {
    /// Probability that a capture has an occluder.
    pub probability: f64,
    /// Put the occluder on the line of sight to a random point of the target (so it
    /// always hides part of it) instead of anywhere in the view.
    #[serde(default)]
    pub over_target: bool,
    /// Side length range, m.
    #[serde(default = "default_occluder_size")]
    pub size_m: [f64; 2],
    #[serde(default = "default_occluder_reflectance")]
    pub reflectance: f32,
}

fn default_occluder_size() -> [f64; 2] {
    [0.01, 0.05]
}
fn default_occluder_reflectance() -> f32 {
    0.15
}

/// A whole scene file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// The dataset's name.
    pub name: String,
    #[serde(default)]
    pub license: String,
    /// A checkerboard target; give either `board` or `target`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub board: Option<BoardSpec>,
    /// A marker target.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<SceneTarget>,
    /// `T_base1_base2`.
    pub base1_from_base2: PoseSpec,
    /// Two or more robots with distinct ids (robot 1 defines `base1`; from the third on,
    /// each gives its own [`RobotSpec::base1_from_base`]).
    pub robots: Vec<RobotSpec>,
    pub viewpoints: ViewpointSpec,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub touch_points: Option<TouchSpec>,
    pub lighting: Lighting,
    /// When given, capture `k` is lit with `lux_levels[k % len]` instead of
    /// `lighting.lux` (the seed's 145 / 243 / 352 lx experiment).
    #[serde(default)]
    pub lux_levels: Vec<f64>,
    /// With `lux_levels`: capture every viewpoint once per level (captures
    /// `L·v .. L·v + L - 1` of viewpoint `v` at levels `0..L`, the robot standing
    /// still), so that each level sees the same poses.
    #[serde(default)]
    pub lux_per_viewpoint: bool,
    #[serde(default = "Optics::realsense")]
    pub optics: Optics,
    #[serde(default)]
    pub noise: SensorNoise,
    /// Table top height in `base1` (a uniform grey plane), m.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table_z_m: Option<f64>,
    /// Print a random texture ([`crate::texture::NoiseTexture`]) of this seed on the
    /// table instead of uniform grey (feature-rich scenes for the RGB-D method).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table_texture_seed: Option<u64>,
    #[serde(default)]
    pub boxes: Vec<BoxSpec>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub occluders: Option<OccluderSpec>,
    /// Render colour images (RGB PNG) instead of grey.
    #[serde(default)]
    pub colour: bool,
    /// When given, a RealSense-like depth image is written with every capture.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth: Option<DepthModel>,
    /// Samples per pixel over continuously varying textures
    /// ([`crate::render::RenderSettings::varying_samples`]; default 13). Fewer
    /// render a textured scene faster and its texture with more aliasing.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub texture_samples: Option<usize>,
}

impl Scene {
    /// Reads and validates a scene file.
    pub fn load(file: &Path) -> Result<Scene, SimError> {
        let text = std::fs::read_to_string(file).map_err(|e| SimError::io(file, e))?;
        Scene::parse(&text, file)
    }

    /// Parses and validates scene text; `file` is only used in errors.
    pub fn parse(text: &str, file: &Path) -> Result<Scene, SimError> {
        let de = &mut serde_json::Deserializer::from_str(text);
        let scene: Scene = serde_path_to_error::deserialize(de).map_err(|e| {
            let field = e.path().to_string();
            let inner = e.into_inner();
            SimError::SceneJson {
                file: file.to_owned(),
                field: if field == "." { String::new() } else { field },
                line: inner.line(),
                column: inner.column(),
                message: inner.to_string(),
            }
        })?;
        scene.validate(file)?;
        Ok(scene)
    }

    /// Range checks, naming the field.
    pub fn validate(&self, file: &Path) -> Result<(), SimError> {
        let bad = |field: &str, reason: String| SimError::SceneValue {
            file: PathBuf::from(file),
            field: field.to_owned(),
            reason,
        };
        if self.robots.len() < 2 {
            return Err(bad(
                "robots",
                format!(
                    "at least two robots are needed, found {}",
                    self.robots.len()
                ),
            ));
        }
        for (k, r) in self.robots.iter().enumerate() {
            if let Some(first) = self.robots[..k].iter().position(|o| o.id == r.id) {
                return Err(bad(
                    &format!("robots[{k}].id"),
                    format!(
                        "robot ids must differ: `{}` is also robots[{first}].id",
                        r.id
                    ),
                ));
            }
            let field = format!("robots[{k}].base1_from_base");
            match (k, &r.base1_from_base) {
                (0, Some(_)) => {
                    return Err(bad(
                        &field,
                        "the first robot's base is base1 itself; leave it out".into(),
                    ));
                }
                (1, Some(_)) => {
                    return Err(bad(
                        &field,
                        "the second robot's base is the scene's `base1_from_base2`; leave it out"
                            .into(),
                    ));
                }
                (0 | 1, None) => {}
                (_, None) => {
                    return Err(bad(
                        &field,
                        "required from the third robot on: where its base stands in base1".into(),
                    ));
                }
                (_, Some(pose)) => {
                    pose.to_iso(file, &field)?;
                }
            }
        }
        match (&self.board, &self.target) {
            (Some(b), None) => Self::validate_board(b, file)?,
            (None, Some(t)) => Self::validate_target(t, file)?,
            _ => {
                return Err(bad(
                    "board",
                    "give exactly one of `board` (a checkerboard) and `target`".into(),
                ));
            }
        }
        if self.lux_per_viewpoint && self.lux_levels.is_empty() {
            return Err(bad("lux_per_viewpoint", "needs `lux_levels`".into()));
        }
        self.base1_from_base2.to_iso(file, "base1_from_base2")?;
        for (i, r) in self.robots.iter().enumerate() {
            let f = |name: &str| format!("robots[{i}].{name}");
            if r.id.is_empty() || r.id.contains(['/', '\\']) {
                return Err(bad(&f("id"), format!("`{}` cannot name a folder", r.id)));
            }
            r.flange_from_camera
                .to_iso(file, &f("flange_from_camera"))?;
            r.error
                .validate()
                .map_err(|e| bad(&f("error"), crate::error::chain(&e)))?;
            self.camera(i)
                .map_err(|e| bad(&f("camera"), crate::error::chain(&e)))?;
        }
        let v = &self.viewpoints;
        if v.count == 0 || v.count > 10_000 {
            return Err(bad(
                "viewpoints.count",
                format!("{} is not in 1..=10000", v.count),
            ));
        }
        if !(v.distance_m[0] > 0.05 && v.distance_m[1] >= v.distance_m[0] && v.distance_m[1] < 5.0)
        {
            return Err(bad(
                "viewpoints.distance_m",
                format!("{:?} is not a distance range", v.distance_m),
            ));
        }
        if !(0.0..=89.0).contains(&v.max_tilt_deg) {
            return Err(bad(
                "viewpoints.max_tilt_deg",
                format!("{} is not in 0..=89", v.max_tilt_deg),
            ));
        }
        if !(0.0..=180.0).contains(&v.max_roll_deg) {
            return Err(bad(
                "viewpoints.max_roll_deg",
                format!("{} is not in 0..=180", v.max_roll_deg),
            ));
        }
        if let Some(t) = &self.touch_points {
            if (0..3).any(|k| {
                t.region_min[k].is_nan()
                    || t.region_max[k].is_nan()
                    || t.region_min[k] > t.region_max[k]
            }) {
                return Err(bad(
                    "touch_points.region_min",
                    "region_min must not exceed region_max".into(),
                ));
            }
            if !(t.tip_sigma_m >= 0.0 && t.tip_sigma_m < 0.1) {
                return Err(bad(
                    "touch_points.tip_sigma_m",
                    format!("{}", t.tip_sigma_m),
                ));
            }
        }
        let l = &self.lighting;
        if !(l.lux > 0.0 && l.lux < 1e6) || self.lux_levels.iter().any(|v| !(*v > 0.0 && *v < 1e6))
        {
            return Err(bad(
                "lighting.lux",
                "illuminance must be positive lux".into(),
            ));
        }
        if !(0.0..=1.0).contains(&l.ambient) {
            return Err(bad(
                "lighting.ambient",
                format!("{} is not in 0..=1", l.ambient),
            ));
        }
        let o = &self.optics;
        if !(o.aperture_m >= 0.0
            && o.aperture_m < 0.05
            && o.focus_m > 0.0
            && o.psf_sigma_px >= 0.0
            && o.psf_sigma_px < 10.0
            && (0.0..=1.0).contains(&o.vignetting))
        {
            return Err(bad("optics", format!("{o:?} out of range")));
        }
        if !(self.noise.e_per_dn >= 0.0 && self.noise.read_noise_dn >= 0.0) {
            return Err(bad("noise", "noise parameters must be >= 0".into()));
        }
        if let Some(o) = &self.occluders
            && (!(0.0..=1.0).contains(&o.probability)
                || o.size_m.iter().any(|v| v.is_nan())
                || o.size_m[0] <= 0.0
                || o.size_m[1] < o.size_m[0])
        {
            return Err(bad("occluders", format!("{o:?} out of range")));
        }
        for (i, bx) in self.boxes.iter().enumerate() {
            bx.pose.to_iso(file, &format!("boxes[{i}].pose"))?;
            if bx.size_m.iter().any(|s| !(*s > 0.0 && *s < 5.0)) {
                return Err(bad(
                    &format!("boxes[{i}].size_m"),
                    format!("{:?}", bx.size_m),
                ));
            }
        }
        if let Some(d) = &self.depth {
            d.validate()
                .map_err(|e| bad("depth", crate::error::chain(&e)))?;
        }
        if let Some(n) = self.texture_samples
            && !(1..=1000).contains(&n)
        {
            return Err(bad("texture_samples", format!("{n} (expected 1 to 1000)")));
        }
        Ok(())
    }

    /// How this scene is rendered: ideal settings with its lighting, optics
    /// and texture samples.
    pub fn render_settings(&self) -> crate::render::RenderSettings {
        let mut settings = crate::render::RenderSettings::ideal();
        settings.lighting = self.lighting.clone();
        settings.optics = self.optics.clone();
        if let Some(n) = self.texture_samples {
            settings.varying_samples = n;
        }
        settings
    }

    fn validate_board(b: &BoardSpec, file: &Path) -> Result<(), SimError> {
        let bad = |field: &str, reason: String| SimError::SceneValue {
            file: PathBuf::from(file),
            field: field.to_owned(),
            reason,
        };
        if b.inner_corners.iter().any(|&n| n < 2) {
            return Err(bad(
                "board.inner_corners",
                "need at least 2x2 inner corners".into(),
            ));
        }
        if !(b.square_m > 0.0 && b.square_m < 1.0) {
            return Err(bad(
                "board.square_m",
                format!("{} is not a square size in metres", b.square_m),
            ));
        }
        if !(b.margin_m >= 0.0 && b.margin_m < 1.0) {
            return Err(bad(
                "board.margin_m",
                format!("{} is not a margin in metres", b.margin_m),
            ));
        }
        b.base1_from_target
            .to_iso(file, "board.base1_from_target")?;
        Ok(())
    }

    fn validate_target(t: &SceneTarget, file: &Path) -> Result<(), SimError> {
        let bad = |field: &str, reason: String| SimError::SceneValue {
            file: PathBuf::from(file),
            field: field.to_owned(),
            reason,
        };
        let metres = |field: &str, v: f64| {
            if v > 0.0 && v < 2.0 {
                Ok(())
            } else {
                Err(bad(field, format!("{v} is not a length in metres")))
            }
        };
        let (pose, margin) = match t {
            SceneTarget::Charuco {
                square_m,
                marker_m,
                base1_from_target,
                margin_m,
                ..
            } => {
                metres("target.square_m", *square_m)?;
                metres("target.marker_m", *marker_m)?;
                (base1_from_target, margin_m)
            }
            SceneTarget::ArucoGrid {
                marker_m,
                separation_m,
                base1_from_target,
                margin_m,
                ..
            } => {
                metres("target.marker_m", *marker_m)?;
                if !(*separation_m >= 0.0 && *separation_m < 1.0) {
                    return Err(bad("target.separation_m", format!("{separation_m}")));
                }
                (base1_from_target, margin_m)
            }
            SceneTarget::Multimarker {
                layout,
                base1_from_target,
                margin_m,
                ..
            } => {
                match layout {
                    MultimarkerLayout::Grid {
                        markers,
                        marker_m,
                        pitch_m,
                        ..
                    } => {
                        metres("target.layout.marker_m", *marker_m)?;
                        if markers.iter().any(|&n| n == 0 || n > 100) {
                            return Err(bad("target.layout.markers", format!("{markers:?}")));
                        }
                        if *pitch_m < *marker_m && markers.iter().any(|&n| n > 1) {
                            return Err(bad(
                                "target.layout.pitch_m",
                                format!("{pitch_m} is less than the marker side {marker_m}"),
                            ));
                        }
                    }
                    MultimarkerLayout::Corner {
                        per_side,
                        marker_m,
                        pitch_m,
                        face_m,
                        ..
                    } => {
                        metres("target.layout.marker_m", *marker_m)?;
                        metres("target.layout.face_m", *face_m)?;
                        let span = (*per_side as f64 - 1.0) * pitch_m + marker_m;
                        if *per_side == 0
                            || *per_side > 20
                            || (*per_side > 1 && pitch_m < marker_m)
                            || span > *face_m
                        {
                            return Err(bad(
                                "target.layout",
                                format!(
                                    "{per_side} markers of {marker_m} m at {pitch_m} m do not fit a {face_m} m face"
                                ),
                            ));
                        }
                    }
                }
                (base1_from_target, margin_m)
            }
        };
        if !(*margin >= 0.0 && *margin < 1.0) {
            return Err(bad("target.margin_m", format!("{margin}")));
        }
        pose.to_iso(file, "target.base1_from_target")?;
        // Layout errors (dictionary, ids, overlaps) name the field too.
        crate::target::TargetModel::build(t).map_err(|e| bad("target", crate::error::chain(&e)))?;
        Ok(())
    }

    /// The target model and `T_base1_target`.
    pub fn target_model(
        &self,
        file: &Path,
    ) -> Result<(crate::target::TargetModel, Iso3), SimError> {
        use crate::target::TargetModel;
        match (&self.board, &self.target) {
            (Some(b), None) => Ok((
                TargetModel::checkerboard(b),
                b.base1_from_target
                    .to_iso(file, "board.base1_from_target")?,
            )),
            (None, Some(t)) => {
                let pose = match t {
                    SceneTarget::Charuco {
                        base1_from_target, ..
                    }
                    | SceneTarget::ArucoGrid {
                        base1_from_target, ..
                    }
                    | SceneTarget::Multimarker {
                        base1_from_target, ..
                    } => base1_from_target,
                };
                Ok((
                    TargetModel::build(t)?,
                    pose.to_iso(file, "target.base1_from_target")?,
                ))
            }
            _ => Err(SimError::SceneValue {
                file: file.to_owned(),
                field: "board".into(),
                reason: "give exactly one of `board` (a checkerboard) and `target`".into(),
            }),
        }
    }

    /// `T_base1_base` of robot `i` (0-based, the order of `robots`): the identity for
    /// the first, `base1_from_base2` for the second, its own `base1_from_base` for the
    /// others.
    pub fn base1_from_base(&self, i: usize, file: &Path) -> Result<Iso3, SimError> {
        match i {
            0 => Ok(Iso3::identity()),
            1 => self.base1_from_base2.to_iso(file, "base1_from_base2"),
            _ => {
                let field = format!("robots[{i}].base1_from_base");
                match self.robots.get(i).and_then(|r| r.base1_from_base.as_ref()) {
                    Some(pose) => pose.to_iso(file, &field),
                    None => Err(SimError::SceneValue {
                        file: file.to_owned(),
                        field,
                        reason: format!("missing (the scene has {} robots)", self.robots.len()),
                    }),
                }
            }
        }
    }

    /// Robot `i`'s camera model.
    pub fn camera(&self, i: usize) -> Result<b2b_calib::camera::CameraModel, SimError> {
        camera_model(&self.robots[i].camera)
    }

    /// The intrinsics robot `i`'s camera reports ([`RobotSpec::reported_camera`],
    /// else the true ones).
    pub fn reported_camera(&self, i: usize) -> Result<b2b_calib::camera::CameraModel, SimError> {
        let r = &self.robots[i];
        let reported = r.reported_camera.as_ref().unwrap_or(&r.camera);
        if (reported.width, reported.height) != (r.camera.width, r.camera.height) {
            return Err(SimError::invalid(
                "reported_camera",
                format!(
                    "size {}x{}, the camera renders {}x{}",
                    reported.width, reported.height, r.camera.width, r.camera.height
                ),
            ));
        }
        camera_model(reported)
    }
}

fn camera_model(c: &Intrinsics) -> Result<b2b_calib::camera::CameraModel, SimError> {
    if c.width == 0 || c.height == 0 || c.width > 8192 || c.height > 8192 {
        return Err(SimError::invalid(
            "camera",
            format!("size {}x{}", c.width, c.height),
        ));
    }
    if c.dist.len() > 5 {
        return Err(SimError::invalid(
            "camera",
            "dist takes at most k1, k2, p1, p2, k3",
        ));
    }
    Ok(b2b_dataset::camera_model(c)?)
}

/// The fields a scene's camera block may have.
const CAMERA_FIELDS: [&str; 7] = ["width", "height", "fx", "fy", "cx", "cy", "dist"];

/// A scene's camera block: the one intrinsics type, read strictly (an unknown
/// field, a misspelt `dist`, is an error as everywhere in a scene).
fn strict_intrinsics<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Intrinsics, D::Error> {
    use serde::de::Error;
    let value = serde_json::Value::deserialize(d)?;
    if let Some(field) = value
        .as_object()
        .and_then(|map| map.keys().find(|k| !CAMERA_FIELDS.contains(&k.as_str())))
    {
        return Err(D::Error::unknown_field(field, &CAMERA_FIELDS));
    }
    serde_json::from_value(value).map_err(D::Error::custom)
}

fn strict_reported<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<Intrinsics>, D::Error> {
    strict_intrinsics(d).map(Some)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn example() -> String {
        std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../datasets/sim-checkerboard-2x12/scene.json"
        ))
        .unwrap()
    }

    #[test]
    fn the_committed_scene_parses() {
        Scene::parse(&example(), Path::new("scene.json")).unwrap();
    }

    /// A scene's camera block is the one intrinsics type read strictly: a misspelt
    /// field is named, not ignored (which would render without its distortion).
    #[test]
    fn a_misspelt_camera_field_is_named() {
        let mut json: serde_json::Value = serde_json::from_str(&example()).unwrap();
        let camera = &mut json["robots"][0]["camera"];
        let dist = camera["dist"].take();
        camera.as_object_mut().unwrap().remove("dist");
        camera["dsit"] = dist;
        let e = Scene::parse(&json.to_string(), Path::new("scene.json")).unwrap_err();
        assert!(e.to_string().contains("unknown field `dsit`"), "{e}");
        // The reported camera too.
        let mut json: serde_json::Value = serde_json::from_str(&example()).unwrap();
        let mut reported = json["robots"][0]["camera"].clone();
        reported["estimated"] = true.into();
        json["robots"][0]["reported_camera"] = reported;
        let e = Scene::parse(&json.to_string(), Path::new("scene.json")).unwrap_err();
        assert!(e.to_string().contains("unknown field `estimated`"), "{e}");
        // Left out: the truth is reported.
        let scene = Scene::parse(&example(), Path::new("scene.json")).unwrap();
        assert!(scene.robots[0].reported_camera.is_none() || example().contains("reported_camera"));
    }

    /// The example with a third robot, a copy of the first with the base `base` (JSON).
    fn three_robots(base: Option<&str>) -> Scene {
        let mut scene = Scene::parse(&example(), Path::new("scene.json")).unwrap();
        let mut third = scene.robots[0].clone();
        third.id = "robot3".into();
        third.base1_from_base = base.map(|t| serde_json::from_str(t).unwrap());
        scene.robots.push(third);
        scene
    }

    #[test]
    fn a_third_robot_needs_its_base_and_only_it() {
        let file = Path::new("s.json");
        let scene = three_robots(Some(r#"{"t": [0.5, -0.9, 0.0], "rpy_deg": [0, 0, 90]}"#));
        scene.validate(file).unwrap();
        let b3 = scene.base1_from_base(2, file).unwrap();
        assert!((b3.translation.vector.y + 0.9).abs() < 1e-12);
        assert_eq!(scene.base1_from_base(0, file).unwrap(), Iso3::identity());
        assert_eq!(
            scene.base1_from_base(1, file).unwrap(),
            scene.base1_from_base2.to_iso(file, "").unwrap()
        );
        // It round-trips through JSON, and a two-robot scene writes no such field.
        let text = serde_json::to_string(&scene).unwrap();
        assert_eq!(Scene::parse(&text, file).unwrap(), scene);
        let two = serde_json::to_string(&Scene::parse(&example(), file).unwrap()).unwrap();
        assert!(!two.contains("\"base1_from_base\""), "{two}");

        let e = three_robots(None).validate(file).unwrap_err().to_string();
        assert!(
            e.contains("s.json")
                && e.contains("robots[2].base1_from_base")
                && e.contains("required"),
            "{e}"
        );
        for k in [0, 1] {
            let mut scene = three_robots(Some(r#"{"t": [0.5, -0.9, 0.0]}"#));
            scene.robots[k].base1_from_base = scene.robots[2].base1_from_base.clone();
            let e = scene.validate(file).unwrap_err().to_string();
            assert!(e.contains(&format!("robots[{k}].base1_from_base")), "{e}");
        }
        let mut scene = three_robots(Some(r#"{"t": [0.5, -0.9, 0.0]}"#));
        scene.robots[2].id = "robot2".into();
        let e = scene.validate(file).unwrap_err().to_string();
        assert!(
            e.contains("robots[2].id") && e.contains("robots[1].id"),
            "{e}"
        );
        let mut scene = three_robots(Some(r#"{"t": [500, -0.9, 0.0]}"#));
        scene.robots.truncate(3);
        let e = scene.validate(file).unwrap_err().to_string();
        assert!(e.contains("robots[2].base1_from_base"), "{e}");
        scene.robots.truncate(1);
        let e = scene.validate(file).unwrap_err().to_string();
        assert!(e.contains("at least two robots"), "{e}");
    }

    #[test]
    fn errors_name_the_file_and_field() {
        let text = example().replace("\"square_m\": 0.025", "\"square_m\": \"big\"");
        let e = Scene::parse(&text, Path::new("s.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("s.json") && e.contains("board.square_m"), "{e}");

        let text = example().replacen("\"model\": \"iiwa7\"", "\"model\": \"iiwa9\"", 1);
        let e = Scene::parse(&text, Path::new("s.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("robots[0].model"), "{e}");

        let text = example().replace("\"count\": 12", "\"count\": 0");
        let e = Scene::parse(&text, Path::new("s.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("viewpoints.count"), "{e}");

        let e = Scene::parse("{", Path::new("s.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("s.json: line 1"), "{e}");
    }
}
