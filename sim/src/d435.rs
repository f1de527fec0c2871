//! A RealSense D435 as it delivers frames: colour 1280x720 and depth 848x480 from
//! two sensors, each with its own intrinsics, the depth in the depth sensor's
//! frame with a factory extrinsic between the two, depth units of 1 mm, and each
//! stream on its own clock.
//!
//! [`write_recording`] lays the frames out for `scripts/realsense-bag.py`, which
//! records them into a librealsense `.bag` with librealsense's own recorder (a
//! software device): the camera process then plays them through librealsense as
//! it would a camera. The truth kept beside them (the true depth as the colour
//! camera sees it) is what the aligned depth is checked against.

use std::path::Path;

use b2b_calib::camera::CameraModel;
use nalgebra::{Translation3, UnitQuaternion, Vector3};

use crate::Iso3;
use crate::error::SimError;
use crate::render::{RenderSettings, Renderer, SceneGeometry};
use crate::sensor::{DepthModel, RgbImage, SensorNoise, expose_rgb};

/// The two sensors and what is between them.
#[derive(Debug, Clone, PartialEq)]
pub struct D435 {
    /// Colour: a D435's factory model carries no distortion.
    pub colour: CameraModel,
    /// Depth (the left infrared imager's geometry).
    pub depth: CameraModel,
    /// `depth_from_colour`: the colour imager sits about 15 mm beside the left
    /// infrared one, turned by a fraction of a degree.
    pub depth_from_colour: Iso3,
    /// Metres per depth unit.
    pub depth_unit_m: f64,
    /// Frames per second of each stream.
    pub fps: f64,
    /// How the depth sensor measures what it sees ([`D435::exact`] from
    /// [`D435::factory`]: quantised to the unit, no noise, dropouts or edge
    /// losses); its unit is [`D435::depth_unit_m`].
    pub depth_model: DepthModel,
}

impl D435 {
    /// Numbers of the kind a D435's factory calibration reports.
    pub fn factory() -> D435 {
        D435 {
            colour: CameraModel::new(1280, 720, [909.7, 909.9, 643.2, 357.8], &[0.0; 5])
                .expect("a valid camera"),
            depth: CameraModel::new(848, 480, [421.4, 421.4, 422.1, 241.6], &[0.0; 5])
                .expect("a valid camera"),
            depth_from_colour: Iso3::from_parts(
                Translation3::new(-0.0148, -0.0001, -0.0003),
                UnitQuaternion::from_scaled_axis(Vector3::new(0.002, -0.003, 0.001)),
            ),
            depth_unit_m: 0.001,
            fps: 30.0,
            depth_model: D435::exact(0.001),
        }
    }

    /// The sensor model without its noise, dropouts or edge losses: depth
    /// quantised to `unit_m`, 0 where nothing was hit.
    pub fn exact(unit_m: f64) -> DepthModel {
        DepthModel {
            subpixel: 0.0,
            min_m: 0.0,
            max_m: 65535.0 * unit_m,
            edge_jump: f64::INFINITY,
            dropout: 0.0,
            unit_m,
            ..DepthModel::default()
        }
    }
}

/// One capture of both sensors.
#[derive(Debug, Clone)]
pub struct D435Frame {
    pub colour: RgbImage,
    /// 848x480, in [`D435::depth_unit_m`], 0 where nothing was hit.
    pub depth: Vec<u16>,
    /// The true z-depth (m) of each colour pixel, 0 where nothing was hit: what
    /// depth aligned to colour should show.
    pub colour_depth_m: Vec<f32>,
}

/// Renders the scene from each colour camera pose (`colour_from_world`).
pub fn render(
    camera: &D435,
    geometry: &SceneGeometry,
    colour_from_world: &[Iso3],
    settings: &RenderSettings,
) -> Result<Vec<D435Frame>, SimError> {
    let colour = Renderer::new(&camera.colour)?;
    let depth = Renderer::new(&camera.depth)?;
    let mut settings = settings.clone();
    settings.colour = true;
    let mut rng: crate::Rng = rand::SeedableRng::seed_from_u64(1);
    let model = DepthModel {
        unit_m: camera.depth_unit_m,
        ..camera.depth_model
    };
    colour_from_world
        .iter()
        .map(|pose| {
            let c = colour.render(pose, geometry, &settings);
            let d = depth.render(&(camera.depth_from_colour * pose), geometry, &settings);
            Ok(D435Frame {
                colour: expose_rgb(&c, &SensorNoise::none(), &mut rng),
                depth: model.measure(&d, &mut rng).data,
                colour_depth_m: c.depth_m,
            })
        })
        .collect()
}

/// When each frame of a recording was exposed, per stream (ms on the
/// recording's clock): the colour frame of capture `k` at `colour_ms[k]`, and
/// its depth frame at each time in `depth_ms[k]`: none (dropped), one, or more
/// (depth at a higher rate, the scene still).
#[derive(Debug, Clone, PartialEq)]
pub struct Timing {
    pub colour_ms: Vec<f64>,
    pub depth_ms: Vec<Vec<f64>>,
}

impl Timing {
    /// `n` captures `interval_ms` apart from `start_ms`, each depth frame
    /// `depth_lag_ms` after its colour frame.
    pub fn regular(n: usize, start_ms: f64, interval_ms: f64, depth_lag_ms: f64) -> Timing {
        let colour_ms: Vec<f64> = (0..n).map(|k| start_ms + interval_ms * k as f64).collect();
        let depth_ms = colour_ms.iter().map(|t| vec![t + depth_lag_ms]).collect();
        Timing {
            colour_ms,
            depth_ms,
        }
    }
}

/// Writes `frames` into `dir` for `scripts/realsense-bag.py`: `manifest.json`
/// (both streams' intrinsics, the extrinsic, the depth unit, and per frame its
/// stream, number, timestamp and file) and the raw pixels (`colour_NNN.rgb`,
/// RGB8 rows; `depth_NNN.z16`, little-endian u16 rows), timed by `timing`.
/// Colour frames are numbered from 1 in capture order, depth frames from 1 in
/// time order.
pub fn write_recording(
    dir: &Path,
    camera: &D435,
    frames: &[D435Frame],
    timing: &Timing,
) -> Result<(), SimError> {
    if timing.colour_ms.len() != frames.len() || timing.depth_ms.len() != frames.len() {
        return Err(SimError::invalid(
            "timing",
            format!(
                "{} colour and {} depth times for {} frames",
                timing.colour_ms.len(),
                timing.depth_ms.len(),
                frames.len()
            ),
        ));
    }
    std::fs::create_dir_all(dir).map_err(|e| SimError::io(dir, e))?;
    let intrinsics = |c: &CameraModel| {
        serde_json::json!({
            "width": c.width, "height": c.height,
            "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
            "dist": &c.dist[..5],
        })
    };
    let r = camera.depth_from_colour.rotation.to_rotation_matrix();
    let t = camera.depth_from_colour.translation.vector;
    let mut list = Vec::new();
    let mut depth_times: Vec<(f64, usize)> = Vec::new();
    for (k, f) in frames.iter().enumerate() {
        let c = format!("colour_{k:03}.rgb");
        std::fs::write(dir.join(&c), &f.colour.data).map_err(|e| SimError::io(dir.join(&c), e))?;
        list.push(serde_json::json!({"stream": "colour", "number": k + 1, "timestamp_ms": timing.colour_ms[k], "file": c}));
        if !timing.depth_ms[k].is_empty() {
            let d = format!("depth_{k:03}.z16");
            let bytes: Vec<u8> = f.depth.iter().flat_map(|v| v.to_le_bytes()).collect();
            std::fs::write(dir.join(&d), bytes).map_err(|e| SimError::io(dir.join(&d), e))?;
            depth_times.extend(timing.depth_ms[k].iter().map(|t| (*t, k)));
        }
    }
    depth_times.sort_by(|a, b| a.0.total_cmp(&b.0));
    for (n, (t, k)) in depth_times.iter().enumerate() {
        list.push(serde_json::json!({"stream": "depth", "number": n + 1, "timestamp_ms": t, "file": format!("depth_{k:03}.z16")}));
    }
    let manifest = serde_json::json!({
        "colour": intrinsics(&camera.colour),
        "depth": intrinsics(&camera.depth),
        "fps": camera.fps,
        "depth_unit_m": camera.depth_unit_m,
        "depth_from_colour": {
            "rotation": (0..9).map(|i| r[(i / 3, i % 3)]).collect::<Vec<_>>(),
            "translation_m": [t.x, t.y, t.z],
        },
        "frames": list,
    });
    let file = dir.join("manifest.json");
    std::fs::write(&file, manifest.to_string()).map_err(|e| SimError::io(&file, e))
}
