//! Rerun recordings of calibration runs: the only crate that links the rerun SDK.
//!
//! The math, protocol and vision crates never see rerun (scripts/check-deps enforces
//! it); the agent and the coordinator hold a [`Recorder`] and call its `log_*`
//! methods with plain types: nalgebra isometries, protocol messages, byte slices.
//! A [`Recorder::disabled`] recorder accepts every call and does nothing, so callers
//! never branch on whether a recording was asked for.
//!
//! # Where things are in a recording
//!
//! One 3-D scene, `world`, is the frame of base 1 (right handed, z up, metres). Each
//! arm is a [`Base`]: `base1` is the reference robot, `base2` the robot whose base
//! the calibration locates. An agent alone logs its own arm as `base1`.
//!
//! | entity path | archetype | when |
//! |---|---|---|
//! | `world` | ViewCoordinates (z up) | static |
//! | `world/base1`, `world/base2` | Transform3D `base1_from_base` + axes | static, [`Recorder::log_base`]; base 2 again with the result |
//! | `world/target` | Transform3D `base1_from_target` + axes | static, [`Recorder::log_target`] |
//! | `world/target/points` | Points3D: the target's model points | static, [`Recorder::log_target`] |
//! | `world/base{i}/flange` | Transform3D `base_from_flange` + axes | per capture |
//! | `world/base{i}/flange_trail` | LineStrips3D: the flange positions so far | per capture |
//! | `world/base{i}/flange/camera` | Transform3D `flange_from_camera` | static, [`Recorder::log_hand_eye`] (the newest estimate wins) |
//! | `world/base{i}/flange/camera/image` | Pinhole (the frustum) + Image | pinhole static, image per capture |
//! | `world/base{i}/flange/camera/image/detected` | Points2D: detected corners (green) | per capture |
//! | `world/base{i}/flange/camera/image/reprojected` | Points2D: model points projected with the capture's board pose (magenta) | per capture |
//! | `world/base{i}/flange/camera/image/residuals` | LineStrips2D: detected to reprojected | per capture |
//! | `world/base{i}/flange/camera/depth` | Points3D: the depth image as a point cloud, camera frame | per capture |
//! | `metrics/base{i}/rms_px` | Scalars: the capture's reprojection RMS (px) | per capture |
//! | `metrics/base{i}/rejected` | Scalars: rejected captures so far | per capture |
//! | `log/base{i}` | TextLog: each capture, and the reason when it was rejected (WARN) | per capture |
//! | `world/uncertainty` | Ellipsoids3D: 95% region of base 2's origin (magnified as labelled) | static, [`Recorder::log_result`] |
//! | `world/touches` | Points3D: verify's touch points in base 1, coloured by error (green 0, red at the predicted 95% bound and over) | static, [`Recorder::log_touches`] |
//! | `world/touches/errors` | LineStrips3D: from robot 1's tip to robot 2's tip mapped into base 1 | static, [`Recorder::log_touches`] |
//! | `metrics/touch_error_mm`, `metrics/touch_bound95_mm` | Scalars on the `touch` timeline | [`Recorder::log_touches`] |
//! | `result/summary` | TextDocument (markdown): the transform, sigma, predicted error | static, [`Recorder::log_result`] |
//!
//! Timelines: `capture` (the capture's sequence number) and `time` (wall clock or
//! the controller's timestamp), both set by [`Recorder::set_capture_time`]; `touch`
//! (the touch's row) for verify. Rerun keeps the time per thread: set it on the
//! thread that logs. What does not change over a run (bases, target, result,
//! touches) is static so that it shows whichever timeline the viewer selects;
//! a newer static value replaces the older.
//!
//! The frustum: a pinhole's descendants live in its 2-D image space, so the depth
//! cloud (3-D, camera frame) is a sibling of `image`, not a child.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use b2b_calib::camera::CameraModel;
use b2b_protocol::messages::{BoardObservation, Capture, Intrinsics};
use b2b_protocol::{CalibrationResult, Covariance6, ProtocolError, Verdict};
use nalgebra::{
    Isometry3, Matrix3, Matrix3x6, Matrix6, Point3, Rotation3, UnitQuaternion, Vector3,
};

/// `sqrt` of the 95% quantile of chi-square with 3 degrees of freedom: the
/// scale from a 3-D covariance's standard deviations to its 95% ellipsoid.
pub const CHI3_95_SCALE: f64 = 2.795_483_482_915_108;

/// How long [`Recorder::finish`] waits for the sink.
pub const FINISH_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);

/// Timeline of the capture sequence number.
pub const TIMELINE_CAPTURE: &str = "capture";
/// Timeline of wall-clock (or controller) time.
pub const TIMELINE_TIME: &str = "time";
/// Timeline of verify's touches.
pub const TIMELINE_TOUCH: &str = "touch";

/// Errors of this crate.
#[derive(Debug, thiserror::Error)]
pub enum VizError {
    /// Rerun could not open the sink or serialise a value.
    #[error("rerun recording")]
    Recording(#[from] rerun::RecordingStreamError),
    /// The recording could not be flushed to its sink.
    #[error("rerun flush")]
    Flush(#[from] rerun::sink::SinkFlushError),
    /// A value handed to a `log_*` call that cannot be drawn.
    #[error("{what}: {reason}")]
    Input { what: String, reason: String },
    /// A protocol value that does not validate.
    #[error(transparent)]
    Protocol(#[from] ProtocolError),
    /// An `.rrd` file that cannot be read back.
    #[error("{path}: {reason}")]
    Rrd { path: PathBuf, reason: String },
}

fn input(what: &str, reason: impl Into<String>) -> VizError {
    VizError::Input {
        what: what.to_owned(),
        reason: reason.into(),
    }
}

/// Which arm: `One` is the reference (world) base, `Two` the base the calibration
/// locates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Base {
    One,
    Two,
}

impl Base {
    /// `base1` or `base2`.
    pub fn name(self) -> &'static str {
        match self {
            Base::One => "base1",
            Base::Two => "base2",
        }
    }

    fn index(self) -> usize {
        match self {
            Base::One => 0,
            Base::Two => 1,
        }
    }

    fn color(self) -> rerun::Color {
        match self {
            Base::One => rerun::Color::from_rgb(40, 120, 220),
            Base::Two => rerun::Color::from_rgb(230, 130, 30),
        }
    }
}

/// The entity paths of a recording (see the crate documentation).
pub mod paths {
    use super::Base;

    pub const WORLD: &str = "world";
    pub const TARGET: &str = "world/target";
    pub const TARGET_POINTS: &str = "world/target/points";
    pub const UNCERTAINTY: &str = "world/uncertainty";
    pub const TOUCHES: &str = "world/touches";
    pub const TOUCH_ERRORS: &str = "world/touches/errors";
    pub const TOUCH_ERROR_MM: &str = "metrics/touch_error_mm";
    pub const TOUCH_BOUND_MM: &str = "metrics/touch_bound95_mm";
    pub const SUMMARY: &str = "result/summary";
    pub const VERDICT: &str = "result/verdict";

    pub fn base(b: Base) -> String {
        format!("world/{}", b.name())
    }
    pub fn flange(b: Base) -> String {
        format!("world/{}/flange", b.name())
    }
    pub fn flange_trail(b: Base) -> String {
        format!("world/{}/flange_trail", b.name())
    }
    pub fn camera(b: Base) -> String {
        format!("world/{}/flange/camera", b.name())
    }
    pub fn image(b: Base) -> String {
        format!("world/{}/flange/camera/image", b.name())
    }
    pub fn detected(b: Base) -> String {
        format!("world/{}/flange/camera/image/detected", b.name())
    }
    pub fn reprojected(b: Base) -> String {
        format!("world/{}/flange/camera/image/reprojected", b.name())
    }
    pub fn residuals(b: Base) -> String {
        format!("world/{}/flange/camera/image/residuals", b.name())
    }
    pub fn depth(b: Base) -> String {
        format!("world/{}/flange/camera/depth", b.name())
    }
    pub fn rms(b: Base) -> String {
        format!("metrics/{}/rms_px", b.name())
    }
    pub fn rejected(b: Base) -> String {
        format!("metrics/{}/rejected", b.name())
    }
    pub fn log(b: Base) -> String {
        format!("log/{}", b.name())
    }
}

/// Pixel layout of an image handed to [`Recorder::log_image`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelFormat {
    /// One byte per pixel.
    Gray,
    /// Three bytes per pixel, red first.
    Rgb,
    /// Three bytes per pixel, blue first (OpenCV's order); converted to RGB.
    Bgr,
}

impl PixelFormat {
    fn channels(self) -> usize {
        match self {
            PixelFormat::Gray => 1,
            PixelFormat::Rgb | PixelFormat::Bgr => 3,
        }
    }
}

/// A borrowed 8-bit image, rows top to bottom without padding.
#[derive(Debug, Clone, Copy)]
pub struct ImageView<'a> {
    pub pixels: &'a [u8],
    pub width: u32,
    pub height: u32,
    pub format: PixelFormat,
}

/// One verify touch: the same physical point measured by both pointers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Touch {
    /// Row in `touch_points.csv` (the `touch` timeline).
    pub row: usize,
    pub tip1_in_base1: Point3<f64>,
    pub tip2_in_base2: Point3<f64>,
    /// The predicted 95% bound of this touch's error (m).
    pub bound95_m: f64,
}

/// A rerun recording, or nothing.
#[derive(Debug)]
pub struct Recorder {
    rec: rerun::RecordingStream,
    /// Flange positions so far, per base (for the trail).
    trails: Mutex<[Vec<[f32; 3]>; 2]>,
    /// Rejected captures so far, per base.
    rejected: Mutex<[u64; 2]>,
}

fn f32x3(v: &Vector3<f64>) -> [f32; 3] {
    [v.x as f32, v.y as f32, v.z as f32]
}

fn transform(a_from_b: &Isometry3<f64>) -> rerun::Transform3D {
    let q = a_from_b.rotation.quaternion();
    rerun::Transform3D::from_translation_rotation(
        f32x3(&a_from_b.translation.vector),
        rerun::Quaternion::from_xyzw([q.i as f32, q.j as f32, q.k as f32, q.w as f32]),
    )
}

fn app_id_of(app_id: &str) -> Result<rerun::ApplicationId, VizError> {
    rerun::ApplicationId::try_from(app_id.to_owned()).map_err(|e| input("app_id", e.to_string()))
}

impl Recorder {
    fn wrap(rec: rerun::RecordingStream) -> Result<Self, VizError> {
        let r = Recorder {
            rec,
            trails: Mutex::new([Vec::new(), Vec::new()]),
            rejected: Mutex::new([0, 0]),
        };
        r.rec
            .log_static(paths::WORLD, &rerun::ViewCoordinates::RIGHT_HAND_Z_UP())?;
        Ok(r)
    }

    /// Records to an `.rrd` file (created or truncated). The file is complete once
    /// the recorder is finished or dropped.
    pub fn save(app_id: &str, path: &Path) -> Result<Self, VizError> {
        let rec = rerun::RecordingStreamBuilder::new(app_id_of(app_id)?).save(path)?;
        Self::wrap(rec)
    }

    /// Streams to a running viewer at a gRPC proxy address such as
    /// `rerun+http://127.0.0.1:9876/proxy` (what `rerun` listens on by default).
    /// The address is checked now; the connection is made in the background and
    /// data is buffered until it is up.
    pub fn connect(app_id: &str, addr: &str) -> Result<Self, VizError> {
        let rec = rerun::RecordingStreamBuilder::new(app_id_of(app_id)?).connect_grpc_opts(addr)?;
        Self::wrap(rec)
    }

    /// A recorder that drops everything.
    pub fn disabled() -> Self {
        Recorder {
            rec: rerun::RecordingStream::disabled(),
            trails: Mutex::new([Vec::new(), Vec::new()]),
            rejected: Mutex::new([0, 0]),
        }
    }

    /// Whether anything is recorded.
    pub fn is_enabled(&self) -> bool {
        self.rec.is_enabled()
    }

    /// The underlying stream, for what this crate does not cover.
    pub fn stream(&self) -> &rerun::RecordingStream {
        &self.rec
    }

    /// Sets the `capture` and `time` timelines for what this thread logs next.
    pub fn set_capture_time(&self, capture: u64, unix_time_s: f64) {
        self.rec
            .set_time_sequence(TIMELINE_CAPTURE, capture.min(i64::MAX as u64) as i64);
        if unix_time_s.is_finite() {
            self.rec
                .set_timestamp_secs_since_epoch(TIMELINE_TIME, unix_time_s);
        }
    }

    /// Places a base in the world (`base1_from_base`: the identity for base 1).
    /// Static, so it shows on every timeline; a newer estimate replaces it.
    pub fn log_base(&self, base: Base, base1_from_base: &Isometry3<f64>) -> Result<(), VizError> {
        let path = paths::base(base);
        self.rec
            .log_static(path.as_str(), &transform(base1_from_base))?;
        self.rec
            .log_static(path.as_str(), &rerun::TransformAxes3D::new(0.2))?;
        Ok(())
    }

    /// Places the target (board or markers) in base 1 and draws its model points
    /// (target frame, metres). Static, like the bases.
    pub fn log_target(
        &self,
        base1_from_target: &Isometry3<f64>,
        target_points: &[[f64; 3]],
    ) -> Result<(), VizError> {
        self.rec
            .log_static(paths::TARGET, &transform(base1_from_target))?;
        self.rec
            .log_static(paths::TARGET, &rerun::TransformAxes3D::new(0.05))?;
        if !target_points.is_empty() {
            let pts = target_points
                .iter()
                .map(|p| [p[0] as f32, p[1] as f32, p[2] as f32]);
            self.rec.log_static(
                paths::TARGET_POINTS,
                &rerun::Points3D::new(pts)
                    .with_radii([0.002])
                    .with_colors([rerun::Color::from_rgb(20, 20, 20)]),
            )?;
        }
        Ok(())
    }

    /// The flange pose of a capture, and the trail of flange positions so far.
    pub fn log_flange(
        &self,
        base: Base,
        base_from_flange: &Isometry3<f64>,
    ) -> Result<(), VizError> {
        self.rec
            .log(paths::flange(base).as_str(), &transform(base_from_flange))?;
        self.rec.log_static(
            paths::flange(base).as_str(),
            &rerun::TransformAxes3D::new(0.05),
        )?;
        if !self.is_enabled() {
            return Ok(());
        }
        let trail = {
            let mut trails = self.trails.lock().unwrap_or_else(|e| e.into_inner());
            let t = &mut trails[base.index()];
            t.push(f32x3(&base_from_flange.translation.vector));
            t.clone()
        };
        self.rec.log(
            paths::flange_trail(base).as_str(),
            &rerun::LineStrips3D::new([trail])
                .with_colors([base.color()])
                .with_radii([0.002]),
        )?;
        Ok(())
    }

    /// The hand-eye (`flange_from_camera`) and the camera's intrinsics: draws the
    /// camera frustum at the flange. Static: the newest estimate replaces the last.
    pub fn log_hand_eye(
        &self,
        base: Base,
        flange_from_camera: &Isometry3<f64>,
        camera: &Intrinsics,
    ) -> Result<(), VizError> {
        self.rec
            .log_static(paths::camera(base).as_str(), &transform(flange_from_camera))?;
        self.log_pinhole(base, camera)
    }

    /// The camera's intrinsics alone (the frustum, at the flange until a hand-eye
    /// is logged).
    pub fn log_pinhole(&self, base: Base, camera: &Intrinsics) -> Result<(), VizError> {
        use b2b_protocol::messages::Validate;
        camera.validate()?;
        self.rec.log_static(
            paths::image(base).as_str(),
            &rerun::Pinhole::from_focal_length_and_resolution(
                [camera.fx as f32, camera.fy as f32],
                [camera.width as f32, camera.height as f32],
            )
            .with_principal_point([camera.cx as f32, camera.cy as f32])
            .with_camera_xyz(rerun::components::ViewCoordinates::RDF)
            .with_image_plane_distance(0.1)
            .with_color(base.color()),
        )?;
        Ok(())
    }

    /// A camera image (8-bit gray, RGB or BGR).
    pub fn log_image(&self, base: Base, image: ImageView<'_>) -> Result<(), VizError> {
        let expected = image.width as usize * image.height as usize * image.format.channels();
        if image.width == 0 || image.height == 0 || image.pixels.len() != expected {
            return Err(input(
                "image",
                format!(
                    "{} bytes for a {}x{} {:?} image (expected {expected})",
                    image.pixels.len(),
                    image.width,
                    image.height,
                    image.format
                ),
            ));
        }
        if !self.is_enabled() {
            return Ok(());
        }
        let size = [image.width, image.height];
        let archetype = match image.format {
            PixelFormat::Gray => rerun::Image::from_l8(image.pixels.to_vec(), size),
            PixelFormat::Rgb => rerun::Image::from_rgb24(image.pixels.to_vec(), size),
            PixelFormat::Bgr => {
                let rgb: Vec<u8> = image
                    .pixels
                    .chunks_exact(3)
                    .flat_map(|p| [p[2], p[1], p[0]])
                    .collect();
                rerun::Image::from_rgb24(rgb, size)
            }
        };
        self.rec.log(paths::image(base).as_str(), &archetype)?;
        Ok(())
    }

    /// Detected corners and the model points reprojected with the estimated pose
    /// (pixels, paired by index), with a line from each to its partner.
    pub fn log_corners(
        &self,
        base: Base,
        detected: &[[f64; 2]],
        reprojected: &[[f64; 2]],
    ) -> Result<(), VizError> {
        if detected.len() != reprojected.len() {
            return Err(input(
                "corners",
                format!(
                    "{} detected and {} reprojected points (must pair up)",
                    detected.len(),
                    reprojected.len()
                ),
            ));
        }
        let f2 = |p: &[f64; 2]| [p[0] as f32, p[1] as f32];
        self.rec.log(
            paths::detected(base).as_str(),
            &rerun::Points2D::new(detected.iter().map(f2))
                .with_radii([rerun::Radius::new_ui_points(3.0)])
                .with_colors([rerun::Color::from_rgb(0, 200, 60)]),
        )?;
        self.rec.log(
            paths::reprojected(base).as_str(),
            &rerun::Points2D::new(reprojected.iter().map(f2))
                .with_radii([rerun::Radius::new_ui_points(2.0)])
                .with_colors([rerun::Color::from_rgb(230, 0, 200)]),
        )?;
        self.rec.log(
            paths::residuals(base).as_str(),
            &rerun::LineStrips2D::new(
                detected
                    .iter()
                    .zip(reprojected)
                    .map(|(a, b)| vec![f2(a), f2(b)]),
            )
            .with_colors([rerun::Color::from_rgb(255, 200, 0)]),
        )?;
        Ok(())
    }

    /// A board observation: its corners, its model points reprojected with its
    /// `T_camera_target` through the camera model, and its RMS.
    pub fn log_observation(
        &self,
        base: Base,
        observation: &BoardObservation,
        camera: &Intrinsics,
    ) -> Result<(), VizError> {
        let reprojected = reproject(observation, camera)?;
        self.log_corners(base, &observation.pixels, &reprojected)?;
        self.log_residual(base, observation.rms_px)
    }

    /// A capture's reprojection RMS (px) on the `metrics` time series.
    pub fn log_residual(&self, base: Base, rms_px: f64) -> Result<(), VizError> {
        if !rms_px.is_finite() {
            return Err(input("rms_px", format!("{rms_px} is not finite")));
        }
        self.rec
            .log(paths::rms(base).as_str(), &rerun::Scalars::single(rms_px))?;
        Ok(())
    }

    /// A rejected capture: the reason in the text log (WARN) and the running count.
    pub fn log_rejection(&self, base: Base, what: &str, reason: &str) -> Result<(), VizError> {
        let count = {
            let mut r = self.rejected.lock().unwrap_or_else(|e| e.into_inner());
            r[base.index()] += 1;
            r[base.index()]
        };
        self.rec.log(
            paths::log(base).as_str(),
            &rerun::TextLog::new(format!("{what} rejected: {reason}"))
                .with_level(rerun::TextLogLevel::WARN),
        )?;
        self.rec.log(
            paths::rejected(base).as_str(),
            &rerun::Scalars::single(count as f64),
        )?;
        Ok(())
    }

    /// The drift watch of one robot (`coordinator watch`) against one
    /// reference (a robot's target, or the scene): the observation's test
    /// statistic `z` and the CUSUM after it, at `unix_time_s`, under
    /// `watch/ROBOT/AGAINST/z` and `watch/ROBOT/AGAINST/cusum`.
    pub fn log_watch(
        &self,
        robot: &str,
        against: &str,
        unix_time_s: f64,
        z: f64,
        cusum: f64,
    ) -> Result<(), VizError> {
        if !(z.is_finite() && cusum.is_finite()) {
            return Err(input("watch", format!("z {z}, CUSUM {cusum}: not finite")));
        }
        if unix_time_s.is_finite() {
            self.rec
                .set_timestamp_secs_since_epoch(TIMELINE_TIME, unix_time_s);
        }
        self.rec.log(
            format!("watch/{robot}/{against}/z"),
            &rerun::Scalars::single(z),
        )?;
        self.rec.log(
            format!("watch/{robot}/{against}/cusum"),
            &rerun::Scalars::single(cusum),
        )?;
        Ok(())
    }

    /// A drift alarm in `watch/alarms` (text log, ERROR).
    pub fn log_alarm(&self, unix_time_s: f64, text: &str) -> Result<(), VizError> {
        if unix_time_s.is_finite() {
            self.rec
                .set_timestamp_secs_since_epoch(TIMELINE_TIME, unix_time_s);
        }
        self.rec.log(
            "watch/alarms",
            &rerun::TextLog::new(text.to_owned()).with_level(rerun::TextLogLevel::ERROR),
        )?;
        Ok(())
    }

    /// A line in a base's text log (INFO).
    pub fn log_text(&self, base: Base, text: &str) -> Result<(), VizError> {
        self.rec.log(
            paths::log(base).as_str(),
            &rerun::TextLog::new(text.to_owned()).with_level(rerun::TextLogLevel::INFO),
        )?;
        Ok(())
    }

    /// Everything about one capture message: sets the timelines (the capture
    /// index, and the controller time or else now), the flange, the board
    /// observation or the rejection, and the pinhole. Images and depth are logged
    /// separately (the message carries neither).
    pub fn log_capture(&self, base: Base, capture: &Capture) -> Result<(), VizError> {
        use b2b_protocol::messages::Validate;
        capture.validate()?;
        let time = capture.controller_time_s.unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64())
        });
        self.set_capture_time(capture.index, time);
        let base_from_flange = capture.base_from_flange.to_isometry("T_base_flange")?;
        self.log_flange(base, &base_from_flange)?;
        self.log_pinhole(base, &capture.camera)?;
        let what = match &capture.image {
            Some(image) => format!("capture {} ({image})", capture.index),
            None => format!("capture {}", capture.index),
        };
        match (&capture.observation, &capture.rejected) {
            (Some(o), _) => {
                self.log_observation(base, o, &capture.camera)?;
                self.log_text(
                    base,
                    &format!("{what}: {} corners, rms {:.3} px", o.pixels.len(), o.rms_px),
                )
            }
            (None, Some(reason)) => self.log_rejection(base, &what, reason),
            (None, None) => Ok(()),
        }
    }

    /// A depth point cloud in the camera frame (metres), e.g. from
    /// [`depth_to_points`].
    pub fn log_depth_points(
        &self,
        base: Base,
        points_in_camera: &[[f32; 3]],
    ) -> Result<(), VizError> {
        self.rec.log(
            paths::depth(base).as_str(),
            &rerun::Points3D::new(points_in_camera.iter().copied())
                .with_radii([0.001])
                .with_colors([rerun::Color::from_rgb(120, 160, 200)]),
        )?;
        Ok(())
    }

    /// The 95% region of base 2's origin in base 1 from the result's covariance,
    /// drawn `magnify` times larger (sub-millimetre ellipsoids are invisible in a
    /// metre-sized scene; the label says the factor).
    pub fn log_uncertainty(
        &self,
        base1_from_base2: &Isometry3<f64>,
        covariance: &Covariance6,
        magnify: f64,
    ) -> Result<(), VizError> {
        if !(magnify.is_finite() && magnify > 0.0) {
            return Err(input(
                "magnify",
                format!("{magnify} is not a positive factor"),
            ));
        }
        let e = translation_ellipsoid(base1_from_base2, covariance, CHI3_95_SCALE)?;
        let q = e.rotation.quaternion();
        let half = e.half_sizes * magnify;
        self.rec.log_static(
            paths::UNCERTAINTY,
            &rerun::Ellipsoids3D::from_centers_and_half_sizes(
                [f32x3(&e.center.coords)],
                [f32x3(&half)],
            )
            .with_quaternions([rerun::Quaternion::from_xyzw([
                q.i as f32, q.j as f32, q.k as f32, q.w as f32,
            ])])
            .with_colors([rerun::Color::from_unmultiplied_rgba(230, 60, 60, 160)])
            .with_labels([format!(
                "95% of base2 origin x{magnify}: semi-axes {:.2} {:.2} {:.2} mm",
                e.half_sizes.x * 1e3,
                e.half_sizes.y * 1e3,
                e.half_sizes.z * 1e3
            )]),
        )?;
        Ok(())
    }

    /// A base-to-base result: base 2 where the result puts it, both hand-eyes
    /// (without intrinsics: the frusta appear once [`Recorder::log_pinhole`] was
    /// called for that base), the uncertainty and a markdown summary.
    /// `robots` names the robot ids of base 1 and base 2 in `result.hand_eye`.
    pub fn log_result(
        &self,
        result: &CalibrationResult,
        robots: [&str; 2],
        magnify: f64,
    ) -> Result<(), VizError> {
        result.validate()?;
        let base1_from_base2 = result.base1_from_base2.to_isometry("T_base1_base2")?;
        self.log_base(Base::One, &Isometry3::identity())?;
        self.log_base(Base::Two, &base1_from_base2)?;
        for (base, robot) in [(Base::One, robots[0]), (Base::Two, robots[1])] {
            if let Some(p) = result.hand_eye.get(robot) {
                let flange_from_camera = p.to_isometry(&format!("hand_eye.{robot}"))?;
                self.rec.log_static(
                    paths::camera(base).as_str(),
                    &transform(&flange_from_camera),
                )?;
            }
        }
        self.log_uncertainty(&base1_from_base2, &result.covariance, magnify)?;
        self.rec.log_static(
            paths::SUMMARY,
            &rerun::TextDocument::from_markdown(summary_markdown(result, &base1_from_base2)),
        )?;
        Ok(())
    }

    /// A command's verdict against the tolerance (`result/verdict`): a
    /// document headed `VERDICT: PASS` or `VERDICT: FAIL` with every reason,
    /// and the same line in the text log (an error on FAIL).
    pub fn log_verdict(&self, verdict: &Verdict, line: &str) -> Result<(), VizError> {
        let mut doc = format!(
            "# {line}\n\nTolerance (p95 touch error): {:.2} mm.\n",
            verdict.tolerance_mm
        );
        for r in &verdict.reasons {
            doc.push_str(&format!("\n- {r}"));
        }
        self.rec
            .log_static(paths::VERDICT, &rerun::TextDocument::from_markdown(doc))?;
        let level = if verdict.pass {
            rerun::TextLogLevel::INFO
        } else {
            rerun::TextLogLevel::ERROR
        };
        self.rec.log(
            paths::VERDICT,
            &rerun::TextLog::new(line.to_owned()).with_level(level),
        )?;
        Ok(())
    }

    /// Verify's touches: robot 1's tips in base 1 coloured by error against each
    /// touch's predicted 95% bound, the error vectors, and the errors on the
    /// `touch` timeline.
    pub fn log_touches(
        &self,
        base1_from_base2: &Isometry3<f64>,
        touches: &[Touch],
    ) -> Result<(), VizError> {
        let mut positions = Vec::with_capacity(touches.len());
        let mut colors = Vec::with_capacity(touches.len());
        let mut labels = Vec::with_capacity(touches.len());
        let mut strips = Vec::with_capacity(touches.len());
        for t in touches {
            let mapped = base1_from_base2 * t.tip2_in_base2;
            let err = (t.tip1_in_base1 - mapped).norm();
            if !(err.is_finite() && t.bound95_m.is_finite() && t.bound95_m > 0.0) {
                return Err(input(
                    &format!("touch row {}", t.row),
                    format!(
                        "error {err} m or bound {} m is not a positive number",
                        t.bound95_m
                    ),
                ));
            }
            positions.push(f32x3(&t.tip1_in_base1.coords));
            colors.push(error_color(err / t.bound95_m));
            labels.push(format!("{}: {:.2} mm", t.row, err * 1e3));
            strips.push(vec![f32x3(&t.tip1_in_base1.coords), f32x3(&mapped.coords)]);
        }
        self.rec.log_static(
            paths::TOUCHES,
            &rerun::Points3D::new(positions)
                .with_colors(colors)
                .with_labels(labels)
                .with_radii([0.004]),
        )?;
        self.rec.log_static(
            paths::TOUCH_ERRORS,
            &rerun::LineStrips3D::new(strips).with_colors([rerun::Color::from_rgb(200, 0, 0)]),
        )?;
        for t in touches {
            let err = (t.tip1_in_base1 - base1_from_base2 * t.tip2_in_base2).norm();
            self.rec
                .set_time_sequence(TIMELINE_TOUCH, t.row.min(i64::MAX as usize) as i64);
            self.rec
                .log(paths::TOUCH_ERROR_MM, &rerun::Scalars::single(err * 1e3))?;
            self.rec.log(
                paths::TOUCH_BOUND_MM,
                &rerun::Scalars::single(t.bound95_m * 1e3),
            )?;
        }
        self.rec.disable_timeline(TIMELINE_TOUCH);
        Ok(())
    }

    /// Flushes everything and closes the sink (an `.rrd` file is complete after
    /// this returns). Waits at most [`FINISH_TIMEOUT`] for a viewer that is slow
    /// or gone; an unreachable viewer is an error here, never a hang.
    pub fn finish(self) -> Result<(), VizError> {
        let flushed = self.rec.flush_with_timeout(FINISH_TIMEOUT);
        self.rec.disconnect();
        flushed?;
        Ok(())
    }
}

/// Green (0) through yellow to red (1 and over): an error as a fraction of its bound.
fn error_color(fraction: f64) -> rerun::Color {
    let f = fraction.clamp(0.0, 1.0);
    let (r, g) = if f < 0.5 {
        ((510.0 * f) as u8, 200)
    } else {
        (255, (200.0 * 2.0 * (1.0 - f)) as u8)
    };
    rerun::Color::from_rgb(r, g, 0)
}

fn summary_markdown(result: &CalibrationResult, base1_from_base2: &Isometry3<f64>) -> String {
    let t = base1_from_base2.translation.vector;
    let (roll, pitch, yaw) = base1_from_base2.rotation.euler_angles();
    let sd: Vec<f64> = (0..6)
        .map(|i| result.covariance[i][i].max(0.0).sqrt())
        .collect();
    let used: Vec<String> = result
        .captures
        .used
        .iter()
        .map(|(r, n)| format!("{r}: {n}"))
        .collect();
    let mut head = String::new();
    if let Some(v) = &result.verdict {
        head.push_str(if v.pass {
            "# VERDICT: PASS\n\n"
        } else {
            "# VERDICT: FAIL\n\n"
        });
        for r in &v.reasons {
            head.push_str(&format!("- {r}\n"));
        }
        head.push('\n');
    }
    for f in &result.findings {
        head.push_str(&format!("**Finding ({}):** {}\n\n", f.kind, f.message));
    }
    head + &format!(
        "# base1_from_base2 ({method})\n\n\
         | | x | y | z |\n|---|---|---|---|\n\
         | translation (mm) | {:.3} | {:.3} | {:.3} |\n\
         | rotation roll/pitch/yaw (deg) | {:.4} | {:.4} | {:.4} |\n\
         | sigma translation (mm) | {:.3} | {:.3} | {:.3} |\n\
         | sigma rotation (deg) | {:.4} | {:.4} | {:.4} |\n\n\
         Predicted touch error: mean {:.3} mm, 95% {:.3} mm.\n\n\
         Captures used: {}; rejected: {}.\n",
        t.x * 1e3,
        t.y * 1e3,
        t.z * 1e3,
        roll.to_degrees(),
        pitch.to_degrees(),
        yaw.to_degrees(),
        sd[3] * 1e3,
        sd[4] * 1e3,
        sd[5] * 1e3,
        sd[0].to_degrees(),
        sd[1].to_degrees(),
        sd[2].to_degrees(),
        result.predicted_touch_error_m.mean * 1e3,
        result.predicted_touch_error_m.p95 * 1e3,
        used.join(", "),
        result.captures.rejected.len(),
        method = result.method,
    )
}

/// Projects an observation's model points with its `T_camera_target` through the
/// camera (OpenCV distortion), paired with its detected pixels.
pub fn reproject(
    observation: &BoardObservation,
    camera: &Intrinsics,
) -> Result<Vec<[f64; 2]>, VizError> {
    let model = CameraModel::new(
        camera.width,
        camera.height,
        [camera.fx, camera.fy, camera.cx, camera.cy],
        &camera.dist,
    )
    .map_err(|e| input("camera", e.to_string()))?;
    let camera_from_target = observation
        .camera_from_target
        .to_isometry("observation.T_camera_target")?;
    observation
        .target_points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let p_in_camera = camera_from_target * Point3::new(p[0], p[1], p[2]);
            model
                .project(&p_in_camera)
                .map(|px| [px.x, px.y])
                .ok_or_else(|| {
                    input(
                        &format!("observation.target_points[{i}]"),
                        "behind the camera under T_camera_target",
                    )
                })
        })
        .collect()
}

/// Unprojects a depth image (row-major, `metres_per_unit` per count, 0 = no
/// reading) into camera-frame points, taking every `stride`-th pixel in both
/// directions. Ignores lens distortion: depth streams are rectified.
pub fn depth_to_points(
    depth: &[u16],
    width: u32,
    height: u32,
    camera: &Intrinsics,
    metres_per_unit: f64,
    stride: usize,
) -> Result<Vec<[f32; 3]>, VizError> {
    let (w, h) = (width as usize, height as usize);
    if w == 0 || h == 0 || depth.len() != w * h {
        return Err(input(
            "depth",
            format!("{} values for a {width}x{height} image", depth.len()),
        ));
    }
    if stride == 0 || !(metres_per_unit.is_finite() && metres_per_unit > 0.0) {
        return Err(input(
            "depth",
            format!("stride {stride} and scale {metres_per_unit} must be positive"),
        ));
    }
    if !(camera.fx > 0.0 && camera.fy > 0.0 && camera.cx.is_finite() && camera.cy.is_finite()) {
        return Err(input("depth camera", "focal lengths must be positive"));
    }
    let mut out = Vec::with_capacity((w / stride + 1) * (h / stride + 1));
    for v in (0..h).step_by(stride) {
        for u in (0..w).step_by(stride) {
            let d = depth[v * w + u];
            if d == 0 {
                continue;
            }
            let z = f64::from(d) * metres_per_unit;
            let x = (u as f64 - camera.cx) / camera.fx * z;
            let y = (v as f64 - camera.cy) / camera.fy * z;
            out.push([x as f32, y as f32, z as f32]);
        }
    }
    Ok(out)
}

/// An ellipsoid: centre, semi-axes along its own axes, and its orientation.
#[derive(Debug, Clone, PartialEq)]
pub struct Ellipsoid {
    pub center: Point3<f64>,
    pub half_sizes: Vector3<f64>,
    pub rotation: UnitQuaternion<f64>,
}

/// The uncertainty region of base 2's origin in base 1: the pose covariance is
/// over the left perturbation `[r, t]`, under which the origin `p` moves by
/// `r x p + t`, so its covariance is `J Σ Jᵀ` with `J = [-[p]x | I]`. `scale`
/// multiplies the standard deviations ([`CHI3_95_SCALE`] for 95%).
pub fn translation_ellipsoid(
    base1_from_base2: &Isometry3<f64>,
    covariance: &Covariance6,
    scale: f64,
) -> Result<Ellipsoid, VizError> {
    b2b_protocol::validate_covariance("covariance", covariance)?;
    let sigma = Matrix6::from_fn(|i, j| covariance[i][j]);
    let p = base1_from_base2.translation.vector;
    let mut j = Matrix3x6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(-p.cross_matrix()));
    j.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&Matrix3::identity());
    let cov_p = j * sigma * j.transpose();
    let cov_p = (cov_p + cov_p.transpose()) * 0.5;
    let eig = cov_p.symmetric_eigen();
    let mut axes = eig.eigenvectors;
    if axes.determinant() < 0.0 {
        let c = -axes.column(2);
        axes.set_column(2, &c);
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(axes));
    let half_sizes = eig.eigenvalues.map(|l| scale * l.max(0.0).sqrt());
    Ok(Ellipsoid {
        center: Point3::from(p),
        half_sizes,
        rotation,
    })
}

/// What an `.rrd` holds for one entity path.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct EntitySummary {
    /// Component identifiers, e.g. `Points3D:positions`, `Transform3D:translation`.
    pub components: BTreeSet<String>,
    /// Timelines its data was logged on.
    pub timelines: BTreeSet<String>,
    /// Rows logged on a timeline (static rows are not counted).
    pub rows: usize,
}

/// Reads an `.rrd` recording back (with the decoder the rerun SDK itself
/// carries, `re_log_encoding`) and summarises it per entity path, written
/// without the leading `/` (`world/base1`). For tests and checks of recordings.
pub fn summarize_rrd(path: &Path) -> Result<BTreeMap<String, EntitySummary>, VizError> {
    use rerun::external::re_log_encoding::DecoderApp;
    use rerun::log::{Chunk, LogMsg};
    let rrd_error = |reason: String| VizError::Rrd {
        path: path.to_owned(),
        reason,
    };
    let file = std::fs::File::open(path).map_err(|e| rrd_error(format!("cannot open: {e}")))?;
    let mut out: BTreeMap<String, EntitySummary> = BTreeMap::new();
    let mut messages = 0usize;
    for msg in DecoderApp::decode_lazy(std::io::BufReader::new(file)) {
        let msg = msg.map_err(|e| rrd_error(format!("message {messages}: {e}")))?;
        messages += 1;
        if let LogMsg::ArrowMsg(_, arrow) = msg {
            let chunk = Chunk::from_arrow_msg(&arrow)
                .map_err(|e| rrd_error(format!("message {messages}: {e}")))?;
            let entity = chunk.entity_path().to_string();
            let e = out
                .entry(entity.trim_start_matches('/').to_owned())
                .or_default();
            if !chunk.is_static() {
                e.rows += chunk.num_rows();
            }
            for d in chunk.component_descriptors() {
                e.components.insert(d.component.to_string());
            }
            for t in chunk.timelines().keys() {
                e.timelines.insert(t.to_string());
            }
        }
    }
    if messages == 0 {
        return Err(rrd_error("no rerun messages (empty or not an .rrd)".into()));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use b2b_protocol::Pose;

    fn camera() -> Intrinsics {
        Intrinsics {
            width: 640,
            height: 480,
            fx: 600.0,
            fy: 610.0,
            cx: 320.0,
            cy: 240.0,
            dist: vec![0.0; 5],
            estimated: false,
        }
    }

    #[test]
    fn ellipsoid_of_a_pure_rotation_variance_lies_along_the_lever_arm_motion() {
        // Variance only about z (0.001 rad sd), base 2 one metre along x: its origin
        // moves along y by 1 mm sd.
        let mut c = [[0.0; 6]; 6];
        c[2][2] = 1e-6;
        let t = Isometry3::translation(1.0, 0.0, 0.0);
        let e = translation_ellipsoid(&t, &c, 1.0).unwrap();
        let mut sizes: Vec<f64> = e.half_sizes.iter().copied().collect();
        sizes.sort_by(f64::total_cmp);
        assert!(
            sizes[0].abs() < 1e-12 && sizes[1].abs() < 1e-12,
            "{sizes:?}"
        );
        assert!((sizes[2] - 1e-3).abs() < 1e-12, "{sizes:?}");
        // The long axis, rotated into base 1, is y.
        let k = e.half_sizes.imax();
        let axis = e.rotation * Vector3::ith(k, 1.0);
        assert!(axis.y.abs() > 1.0 - 1e-9, "{axis:?}");
    }

    #[test]
    fn ellipsoid_of_translation_variance_is_its_standard_deviation_times_scale() {
        let mut c = [[0.0; 6]; 6];
        c[3][3] = 4e-6;
        c[4][4] = 1e-6;
        c[5][5] = 9e-6;
        let e = translation_ellipsoid(&Isometry3::identity(), &c, CHI3_95_SCALE).unwrap();
        let mut sizes: Vec<f64> = e.half_sizes.iter().copied().collect();
        sizes.sort_by(f64::total_cmp);
        for (got, sd) in sizes.iter().zip([1e-3, 2e-3, 3e-3]) {
            assert!((got - CHI3_95_SCALE * sd).abs() < 1e-12, "{sizes:?}");
        }
        assert!((e.rotation.to_rotation_matrix().matrix().determinant() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn bad_covariance_is_rejected() {
        let mut c = [[0.0; 6]; 6];
        c[0][0] = f64::NAN;
        assert!(translation_ellipsoid(&Isometry3::identity(), &c, 1.0).is_err());
    }

    #[test]
    fn depth_unprojects_a_fronto_parallel_plane() {
        // A plane at 0.8 m in millimetre counts: every point has z = 0.8 and
        // projects back onto its pixel.
        let cam = camera();
        let (w, h) = (64u32, 48u32);
        let mut depth = vec![800u16; (w * h) as usize];
        depth[5] = 0; // no reading: skipped
        let pts = depth_to_points(&depth, w, h, &cam, 1e-3, 1).unwrap();
        assert_eq!(pts.len(), (w * h) as usize - 1);
        for (n, p) in pts.iter().enumerate() {
            let idx = if n < 5 { n } else { n + 1 };
            let (u, v) = ((idx % w as usize) as f64, (idx / w as usize) as f64);
            assert!((p[2] as f64 - 0.8).abs() < 1e-6);
            let u_back = cam.fx * p[0] as f64 / p[2] as f64 + cam.cx;
            let v_back = cam.fy * p[1] as f64 / p[2] as f64 + cam.cy;
            assert!((u_back - u).abs() < 1e-3 && (v_back - v).abs() < 1e-3);
        }
        let strided = depth_to_points(&depth, w, h, &cam, 1e-3, 4).unwrap();
        assert_eq!(strided.len(), 16 * 12);
        assert!(depth_to_points(&depth[1..], w, h, &cam, 1e-3, 1).is_err());
        assert!(depth_to_points(&depth, w, h, &cam, 1e-3, 0).is_err());
    }

    #[test]
    fn reprojection_with_the_true_pose_lands_on_the_pixels() {
        let cam = camera();
        let camera_from_target = Isometry3::new(
            Vector3::new(-0.1, -0.05, 0.6),
            Vector3::new(0.1, -0.2, 0.05),
        );
        let model = CameraModel::new(640, 480, [600.0, 610.0, 320.0, 240.0], &[0.0; 5]).unwrap();
        let target_points: Vec<[f64; 3]> = (0..12)
            .map(|i| [0.03 * (i % 4) as f64, 0.03 * (i / 4) as f64, 0.0])
            .collect();
        let pixels: Vec<[f64; 2]> = target_points
            .iter()
            .map(|p| {
                let px = model
                    .project(&(camera_from_target * Point3::new(p[0], p[1], p[2])))
                    .unwrap();
                // pinhole by hand, the ground truth
                let q = camera_from_target * Point3::new(p[0], p[1], p[2]);
                assert!((px.x - (600.0 * q.x / q.z + 320.0)).abs() < 1e-9);
                [px.x, px.y]
            })
            .collect();
        let obs = BoardObservation {
            target_points,
            pixels: pixels.clone(),
            camera_from_target: Pose::from_isometry(&camera_from_target),
            residuals_px: vec![0.0; 12],
            rms_px: 0.0,
            target_centre: None,
            target: None,
        };
        let back = reproject(&obs, &cam).unwrap();
        for (a, b) in back.iter().zip(&pixels) {
            assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9);
        }
        // A pose that puts the board behind the camera is an error, not garbage.
        let mut behind = obs.clone();
        behind.camera_from_target = Pose::from_isometry(&Isometry3::translation(0.0, 0.0, -1.0));
        assert!(reproject(&behind, &cam).is_err());
    }

    #[test]
    fn error_colours_go_green_to_red() {
        assert_eq!(error_color(0.0).to_array(), [0, 200, 0, 255]);
        assert_eq!(error_color(1.0).to_array(), [255, 0, 0, 255]);
        assert_eq!(error_color(7.0).to_array(), [255, 0, 0, 255]);
        let mid = error_color(0.5).to_array();
        assert_eq!((mid[0], mid[1]), (255, 200));
    }

    #[test]
    fn disabled_recorder_accepts_everything_but_still_checks_input() {
        let r = Recorder::disabled();
        assert!(!r.is_enabled());
        r.set_capture_time(1, 1.7e9);
        r.log_base(Base::Two, &Isometry3::identity()).unwrap();
        r.log_flange(Base::One, &Isometry3::identity()).unwrap();
        let bad = ImageView {
            pixels: &[0u8; 10],
            width: 4,
            height: 4,
            format: PixelFormat::Gray,
        };
        assert!(r.log_image(Base::One, bad).is_err());
        assert!(r.log_corners(Base::One, &[[0.0; 2]], &[]).is_err());
        r.finish().unwrap();
    }
}
