//! The live capture source: an arm behind KUKA FRI and a camera behind iceoryx2 (a real
//! cart, or the simulated one, which the agent cannot tell apart).
//!
//! Per viewpoint: move there through FRI (every command checked by the safety guard),
//! wait until the measured joints are still (measured over a window, not a fixed
//! sleep), take the first frame whose exposure started after that, check the arm was
//! still through it, detect the target, and decide. In the automatic routine a badly
//! placed board (off-centre, or not found where it was expected) is re-centred in a
//! closed loop from the detection (or the board estimate so far) and retried a bounded
//! number of times; captures too similar to an earlier one or blurred are rejected with
//! the reason; the routine stops when the hand-eye covariance is below the bound.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::Context;
use b2b_calib::camera::CameraModel;
use b2b_pipeline::Observation;
use b2b_protocol::RejectedCapture;
use b2b_robot::{Arm, Joints};
use kuka_fri::{FriClient, SafetyGuard, SessionState};
use nalgebra::{Isometry3, Point2, Point3};

use crate::agent::{CaptureSource, Progress, SourceCapture};
use crate::plan::{Plan, PlanConfig, PlanScene, Viewpoint, plan_viewpoints, reach, recentre};

type Iso3 = Isometry3<f64>;

/// A grey frame from the camera process.
#[derive(Debug, Clone)]
pub struct LiveFrame {
    pub number: u64,
    /// Start of the exposure, ns since the Unix epoch.
    pub timestamp_ns: u64,
    pub camera: CameraModel,
    pub grey: Vec<u8>,
    /// The aligned depth image of the same frame number and its unit (m), when the
    /// source has a depth stream and it arrived.
    pub depth: Option<(b2b_vision::features::DepthImage, f64)>,
}

/// Frames from the camera process.
pub trait FrameSource {
    /// The first frame whose exposure started at or after `after_ns`.
    fn frame_after(&mut self, after_ns: u64, timeout: Duration) -> anyhow::Result<LiveFrame>;
    /// Frames that arrived but were never looked at (the queue overflowed while the
    /// arm moved; the camera never waits for the agent).
    fn dropped(&self) -> u64;
}

/// The calibration target as the agent knows it (configuration, not truth): the
/// pipeline's one target model, and its points.
#[derive(Debug, Clone)]
pub struct LiveTarget {
    pub spec: b2b_pipeline::TargetSpec,
    pub points: Vec<Point3<f64>>,
}

impl LiveTarget {
    pub fn new(spec: b2b_pipeline::TargetSpec) -> Self {
        LiveTarget {
            points: spec.all_points(),
            spec,
        }
    }

    /// The board centre every message and plan uses ([`b2b_pipeline::TargetSpec::centre`]).
    pub fn centre(&self) -> Point3<f64> {
        self.spec.centre()
    }

    /// Detects the target in a frame and fits its pose, or says why not.
    pub fn observe(
        &self,
        robot: &str,
        frame: &LiveFrame,
        base_from_flange: Iso3,
        row: usize,
    ) -> (Result<Observation, RejectedCapture>, Option<f64>) {
        let name = format!("frame {}", frame.number);
        let reject = |reason: String| RejectedCapture {
            robot: robot.to_owned(),
            image: Some(name.clone()),
            row: Some(row),
            reason,
        };
        let img = match b2b_vision::GrayImage::from_raw(
            frame.camera.width,
            frame.camera.height,
            &frame.grey,
        ) {
            Ok(i) => i,
            Err(e) => return (Err(reject(b2b_pipeline::error_chain(&e))), None),
        };
        let sharpness = img.laplacian_variance().ok();
        let (detection, pose) = match self.spec.detect(&img, &frame.camera) {
            Ok(d) => d,
            Err(e) => return (Err(reject(b2b_pipeline::error_chain(&e))), sharpness),
        };
        (
            Ok(Observation {
                row,
                image: Some(name.clone()),
                camera_from_target: pose.camera_from_target,
                board: b2b_calib::refine::BoardCapture {
                    base_from_flange,
                    target_points: detection.target_points,
                    pixels: detection.pixels,
                },
                pnp_rms_px: pose.rms_px,
                residuals_px: pose.residuals_px,
            }),
            sharpness,
        )
    }
}

/// What the live source does.
#[derive(Debug, Clone)]
pub enum LiveMode {
    /// `agent run`: visit the planned viewpoints once, no re-centring, no early stop.
    Program,
    /// `agent auto`: the automatic pre-operative routine.
    Auto(AutoConfig),
}

/// Settings of the automatic routine.
#[derive(Debug, Clone)]
pub struct AutoConfig {
    /// Tries per viewpoint (the first one included).
    pub max_tries: usize,
    /// Re-centre when the board centre is further than this fraction of the image
    /// size from the image centre.
    pub off_centre: f64,
    /// Stop when the hand-eye's 1-sigma translation (m) and rotation (rad) are below
    /// these, with at least `min_good` captures.
    pub stop_sigma_t_m: f64,
    pub stop_sigma_r_rad: f64,
    pub min_good: usize,
    /// Reject a capture closer than this to an earlier one (m, rad).
    pub similar_t_m: f64,
    pub similar_r_rad: f64,
    /// Reject a capture whose sharpness is below this fraction of the median so far.
    pub blur_fraction: f64,
}

impl Default for AutoConfig {
    fn default() -> Self {
        AutoConfig {
            max_tries: 4,
            off_centre: 0.12,
            stop_sigma_t_m: 0.1e-3,
            stop_sigma_r_rad: 0.01f64.to_radians(),
            min_good: 20,
            similar_t_m: 5e-3,
            similar_r_rad: 2f64.to_radians(),
            blur_fraction: 0.3,
        }
    }
}

/// Settings of a live source.
#[derive(Debug, Clone)]
pub struct LiveConfig {
    pub robot: String,
    pub mode: LiveMode,
    pub plan: PlanConfig,
    /// The board's pose in this robot's base, approximately (a setup sheet).
    pub board_approx: Iso3,
    /// The camera mount, approximately (the drawing).
    pub mount_approx: Iso3,
    /// Stillness: every joint within `still_tol_rad` over `still_window`.
    pub still_window: Duration,
    pub still_tol_rad: f64,
    pub settle_timeout: Duration,
    pub frame_timeout: Duration,
    /// Local features lifted with the depth frame, published with each capture for
    /// the RGB-D method (`None`: not computed; frames without depth carry none).
    pub features: Option<b2b_pipeline::rgbd::RgbdOptions>,
}

/// Compute and motion time of the routine, per capture.
#[derive(Debug, Clone, Copy, Default)]
pub struct LiveTimings {
    pub captures: usize,
    pub plan_ms: f64,
    pub detect_ms: f64,
    pub decide_ms: f64,
    pub motion_ms: f64,
    pub frame_wait_ms: f64,
    pub retries: usize,
}

/// The live source.
pub struct LiveSource {
    cfg: LiveConfig,
    fri: FriClient,
    frames: Box<dyn FrameSource>,
    arm: Arm,
    guard: SafetyGuard,
    target: LiveTarget,
    camera: Option<CameraModel>,
    plan: Option<Plan>,
    next_viewpoint: usize,
    captured: u64,
    board_estimate: Option<Iso3>,
    /// The board pose the current plan was made for.
    planned_for: Option<Iso3>,
    plans: usize,
    visited: usize,
    sharpness: Vec<f64>,
    timings: LiveTimings,
    stopped_because: Option<String>,
}

impl std::fmt::Debug for LiveSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveSource")
            .field("robot", &self.cfg.robot)
            .field("captured", &self.captured)
            .finish_non_exhaustive()
    }
}

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// A rotation angle and translation distance between two poses.
fn pose_distance(a: &Iso3, b: &Iso3) -> (f64, f64) {
    let d = a.inverse() * b;
    (d.translation.vector.norm(), d.rotation.angle())
}

impl LiveSource {
    /// Connects: waits for the FRI session to reach COMMANDING_ACTIVE (the robot
    /// application's overlay) and for the first frame.
    pub fn connect(
        cfg: LiveConfig,
        fri: FriClient,
        frames: Box<dyn FrameSource>,
        arm: Arm,
        guard: SafetyGuard,
        target: LiveTarget,
    ) -> anyhow::Result<Self> {
        fri.wait_for_joints(Duration::from_secs(15))
            .context("no joint state from the FRI controller")?;
        Ok(LiveSource {
            cfg,
            fri,
            frames,
            arm,
            guard,
            target,
            camera: None,
            plan: None,
            next_viewpoint: 0,
            captured: 0,
            board_estimate: None,
            planned_for: None,
            plans: 0,
            visited: 0,
            sharpness: vec![],
            timings: LiveTimings::default(),
            stopped_because: None,
        })
    }

    /// The measured joints now.
    fn measured(&self) -> anyhow::Result<Joints> {
        Ok(self
            .fri
            .latest()
            .context("no joint state from the FRI controller")?
            .q)
    }

    /// Waits until the arm is still; returns the host time it was found still.
    fn wait_still(&self) -> anyhow::Result<u64> {
        let deadline = Instant::now() + self.cfg.settle_timeout;
        loop {
            if self
                .fri
                .is_still(self.cfg.still_window, self.cfg.still_tol_rad)
            {
                return Ok(now_ns());
            }
            anyhow::ensure!(
                Instant::now() < deadline,
                "the arm did not come to rest within {:?}",
                self.cfg.settle_timeout
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Still arm, then a frame exposed after it, then the arm checked still again.
    fn still_frame(&mut self) -> anyhow::Result<(LiveFrame, Joints, f64)> {
        let still_at = self.wait_still()?;
        let waited = Instant::now();
        let frame = self.frames.frame_after(still_at, self.cfg.frame_timeout)?;
        self.timings.frame_wait_ms += ms(waited.elapsed());
        anyhow::ensure!(
            self.fri
                .is_still(self.cfg.still_window, self.cfg.still_tol_rad),
            "the arm moved during the exposure of frame {}",
            frame.number
        );
        let js = self
            .fri
            .latest()
            .context("no joint state from the FRI controller")?;
        let t = js.timestamp.as_duration().as_secs_f64();
        Ok((frame, js.q, t))
    }

    fn move_to(&mut self, q: Joints) -> anyhow::Result<()> {
        let started = Instant::now();
        if self.fri.state() != SessionState::CommandingActive {
            self.fri
                .wait_for_state(SessionState::CommandingActive, Duration::from_secs(10))
                .context("the FRI session is not commanding (is the robot application's overlay running?)")?;
        }
        let r = self.fri.move_to(q).map_err(anyhow::Error::from);
        self.timings.motion_ms += ms(started.elapsed());
        r
    }

    /// Plans from the current pose. With `first_view`, the board estimate comes from
    /// detecting the board where the arm stands now; otherwise from configuration.
    fn make_plan(&mut self, first_view: bool) -> anyhow::Result<()> {
        let count = self.cfg.plan.count;
        self.make_plan_of(first_view, count)
    }

    fn make_plan_of(&mut self, first_view: bool, count: usize) -> anyhow::Result<()> {
        let (frame, q, _) = self.still_frame()?;
        self.camera = Some(frame.camera.clone());
        let base_from_flange = self.arm.fk(&q);
        if first_view {
            let (observed, _) = self
                .target
                .observe(&self.cfg.robot, &frame, base_from_flange, 0);
            match observed {
                Ok(o) => {
                    self.board_estimate =
                        Some(base_from_flange * self.cfg.mount_approx * o.camera_from_target);
                }
                Err(r) => tracing::warn!(
                    "{}: no board in the first view ({}); planning from the configured board position",
                    self.cfg.robot,
                    r.reason
                ),
            }
        }
        let started = Instant::now();
        let camera = frame.camera.clone();
        let board = self.board_estimate.unwrap_or(self.cfg.board_approx);
        let scene = PlanScene {
            arm: &self.arm,
            guard: &self.guard,
            camera: &camera,
            base_from_target: board,
            flange_from_camera: self.cfg.mount_approx,
            target_points: &self.target.points,
            view_axis: self.target.spec.view_axis(),
        };
        let cfg = PlanConfig {
            count: count.max(3),
            phase: self.plans as f64 * 0.7,
            ..self.cfg.plan.clone()
        };
        let plan = plan_viewpoints(&scene, &q, &cfg)?;
        self.plans += 1;
        self.planned_for = Some(board);
        self.next_viewpoint = 0;
        self.timings.plan_ms += ms(started.elapsed());
        anyhow::ensure!(
            !plan.viewpoints.is_empty(),
            "no viewpoint of the board is reachable safely: {:?}",
            plan.dropped
        );
        self.plan = Some(plan);
        Ok(())
    }

    /// The plan (after the first capture call, or [`LiveSource::plan_only`]).
    pub fn plan(&self) -> Option<&Plan> {
        self.plan.as_ref()
    }

    /// Plans without moving (`--dry-run`).
    pub fn plan_only(&mut self) -> anyhow::Result<&Plan> {
        let first_view = matches!(self.cfg.mode, LiveMode::Auto(_));
        self.make_plan(first_view)?;
        self.plan.as_ref().context("no plan")
    }

    fn reject(&self, row: usize, reason: String) -> RejectedCapture {
        RejectedCapture {
            robot: self.cfg.robot.clone(),
            image: None,
            row: Some(row),
            reason,
        }
    }

    /// Where the board should be, in the camera at `base_from_flange`.
    fn predicted_centre(
        &self,
        base_from_flange: &Iso3,
        progress: &Progress,
    ) -> Option<Point3<f64>> {
        let board = progress
            .base_from_target
            .last()
            .copied()
            .or(self.board_estimate)
            .unwrap_or(self.cfg.board_approx);
        let centre = self.target.centre();
        Some((base_from_flange * self.cfg.mount_approx).inverse() * (board * centre))
    }

    /// One viewpoint: move, settle, capture, detect, decide (and re-centre in auto).
    fn visit(
        &mut self,
        v: &Viewpoint,
        progress: &Progress,
        stop: &AtomicBool,
    ) -> anyhow::Result<SourceCapture> {
        let row = self.captured as usize + 1;
        let auto = match &self.cfg.mode {
            LiveMode::Auto(a) => Some(a.clone()),
            LiveMode::Program => None,
        };
        let tries = auto.as_ref().map_or(1, |a| a.max_tries.max(1));
        let mut target_q = v.q;
        let mut last_reason = String::new();
        for attempt in 0..tries {
            anyhow::ensure!(!stop.load(Ordering::SeqCst), "interrupted");
            if attempt > 0 {
                self.timings.retries += 1;
            }
            if let Err(e) = self.move_to(target_q) {
                last_reason = format!("motion refused or aborted: {e:#}");
                break;
            }
            let (frame, q, controller_t) = match self.still_frame() {
                Ok(x) => x,
                Err(e) => {
                    last_reason = format!("{e:#}");
                    continue;
                }
            };
            let camera = frame.camera.clone();
            let base_from_flange = self.arm.fk(&q);
            let detect_started = Instant::now();
            let (observed, sharpness) =
                self.target
                    .observe(&self.cfg.robot, &frame, base_from_flange, row);
            self.timings.detect_ms += ms(detect_started.elapsed());
            let decide_started = Instant::now();
            let features = match (&self.cfg.features, &frame.depth) {
                (Some(options), Some((depth, unit))) => {
                    let started = Instant::now();
                    let set = frame_features(&frame, depth, *unit, options);
                    self.timings.detect_ms += ms(started.elapsed());
                    set.map_err(|e| tracing::warn!("frame {}: no features: {e:#}", frame.number))
                        .ok()
                }
                _ => None,
            };
            let capture = |observed| SourceCapture {
                index: row as u64 - 1,
                image: Some(format!("frame {}", frame.number)),
                base_from_flange,
                controller_time_s: Some(controller_t),
                camera: camera.clone(),
                observed,
                pixels: Some(frame.grey.clone()),
                features: features.clone(),
                target_centre: self.target.centre(),
            };
            let Some(a) = &auto else {
                self.timings.decide_ms += ms(decide_started.elapsed());
                return Ok(capture(observed));
            };
            // Where is the board, and is it placed well?
            let (centre_in_camera, badly_placed) = match &observed {
                Ok(o) => {
                    let n = o.board.pixels.len().max(1) as f64;
                    let c = o
                        .board
                        .pixels
                        .iter()
                        .fold(Point2::origin(), |acc, p| acc + p.coords / n);
                    let off = ((c.x - camera.cx) / camera.width as f64)
                        .abs()
                        .max(((c.y - camera.cy) / camera.height as f64).abs());
                    let centre = self.target.centre();
                    (
                        Some(o.camera_from_target * centre),
                        (off > a.off_centre).then(|| {
                            format!("board off-centre by {:.0}% of the image", off * 100.0)
                        }),
                    )
                }
                Err(r) => (
                    self.predicted_centre(&base_from_flange, progress),
                    Some(format!("board not found ({})", r.reason)),
                ),
            };
            if let Some(why) = badly_placed {
                last_reason = why;
                if attempt + 1 < tries
                    && let Some(c) = centre_in_camera
                {
                    let base_from_camera = base_from_flange * self.cfg.mount_approx;
                    let wanted = recentre(&base_from_camera, &c, None);
                    let camera_for_plan = camera.clone();
                    let scene = PlanScene {
                        arm: &self.arm,
                        guard: &self.guard,
                        camera: &camera_for_plan,
                        base_from_target: self.cfg.board_approx,
                        flange_from_camera: self.cfg.mount_approx,
                        target_points: &self.target.points,
                        view_axis: self.target.spec.view_axis(),
                    };
                    match reach(&scene, &wanted, &q) {
                        Ok((q_new, _))
                            if crate::plan::leg_is_safe(
                                &self.guard,
                                &q,
                                &q_new,
                                self.cfg.plan.path_step_rad,
                            ) =>
                        {
                            target_q = q_new;
                            self.timings.decide_ms += ms(decide_started.elapsed());
                            continue;
                        }
                        Ok(_) => last_reason += "; the re-centred pose has no safe path",
                        Err(e) => last_reason += &format!("; the re-centred pose: {e}"),
                    }
                }
                // A usable (if off-centre) board is still a capture.
                self.timings.decide_ms += ms(decide_started.elapsed());
                if observed.is_ok() {
                    return Ok(capture(observed));
                }
                return Ok(capture(Err(self.reject(
                    row,
                    format!("{last_reason} after {} tries", attempt + 1),
                ))));
            }
            // Too similar to one already taken?
            if let Some((k, _)) = progress.good_poses.iter().enumerate().find(|(_, p)| {
                let (t, r) = pose_distance(p, &base_from_flange);
                t < a.similar_t_m && r < a.similar_r_rad
            }) {
                self.timings.decide_ms += ms(decide_started.elapsed());
                return Ok(capture(Err(
                    self.reject(row, format!("too similar to good capture {}", k + 1))
                )));
            }
            // Blurred?
            if let Some(s) = sharpness {
                if self.sharpness.len() >= 3 {
                    let mut sorted = self.sharpness.clone();
                    sorted.sort_by(f64::total_cmp);
                    let median = sorted[sorted.len() / 2];
                    if s < a.blur_fraction * median {
                        self.timings.decide_ms += ms(decide_started.elapsed());
                        return Ok(capture(Err(self.reject(
                            row,
                            format!(
                                "blurred: sharpness {s:.0} < {:.0}% of the median {median:.0}",
                                a.blur_fraction * 100.0
                            ),
                        ))));
                    }
                }
                if observed.is_ok() {
                    self.sharpness.push(s);
                }
            }
            self.timings.decide_ms += ms(decide_started.elapsed());
            return Ok(capture(observed));
        }
        Ok(SourceCapture {
            index: row as u64 - 1,
            image: None,
            base_from_flange: self.arm.fk(&self.measured()?),
            controller_time_s: None,
            camera: self.camera.clone().context("no camera intrinsics yet")?,
            observed: Err(self.reject(row, last_reason)),
            pixels: None,
            features: None,
            target_centre: self.target.centre(),
        })
    }

    /// A board pose seen from a good capture (approximate mount): the first one
    /// replaces the configured position for planning.
    fn observed_board(&mut self, base_from_target: Iso3) {
        if self.board_estimate.is_none() || self.plans <= 1 {
            self.board_estimate = Some(base_from_target);
        }
    }

    /// Compute and motion timings so far.
    pub fn timings(&self) -> LiveTimings {
        self.timings
    }

    /// The FRI client (for shutdown).
    pub fn into_fri(self) -> FriClient {
        self.fri
    }
}

fn sigmas(cov: &[[f64; 6]; 6]) -> (f64, f64) {
    let r = (0..3)
        .map(|i| cov[i][i])
        .fold(0.0, f64::max)
        .max(0.0)
        .sqrt();
    let t = (3..6)
        .map(|i| cov[i][i])
        .fold(0.0, f64::max)
        .max(0.0)
        .sqrt();
    (t, r)
}

impl CaptureSource for LiveSource {
    fn describe(&self) -> String {
        match self.cfg.mode {
            LiveMode::Program => format!("{}: visiting the planned viewpoints", self.cfg.robot),
            LiveMode::Auto(_) => format!("{}: automatic routine", self.cfg.robot),
        }
    }

    fn expected(&self) -> Option<u64> {
        Some(self.cfg.plan.count as u64)
    }

    fn next(
        &mut self,
        progress: &Progress,
        stop: &AtomicBool,
    ) -> anyhow::Result<Option<SourceCapture>> {
        if self.plan.is_none() {
            let first_view = matches!(self.cfg.mode, LiveMode::Auto(_));
            self.make_plan(first_view)?;
        }
        if let (LiveMode::Auto(a), Some(he)) = (&self.cfg.mode, &progress.hand_eye) {
            let (t, r) = sigmas(&he.covariance);
            if progress.good >= a.min_good && t <= a.stop_sigma_t_m && r <= a.stop_sigma_r_rad {
                self.stopped_because = Some(format!(
                    "data sufficient after {} good captures: hand-eye sigma {:.3} mm, {:.4} deg",
                    progress.good,
                    t * 1e3,
                    r.to_degrees()
                ));
                return Ok(None);
            }
        }
        if let LiveMode::Auto(a) = &self.cfg.mode {
            let exhausted = self
                .plan
                .as_ref()
                .is_none_or(|p| self.next_viewpoint >= p.viewpoints.len());
            let planned_off = match (self.board_estimate, self.planned_for) {
                (Some(b), Some(p)) => (b.translation.vector - p.translation.vector).norm() > 0.01,
                _ => false,
            };
            let budget = 2 * self.cfg.plan.count;
            if planned_off || (exhausted && progress.good < a.min_good && self.visited < budget) {
                // Re-plan around the board where the camera actually sees it (or, when
                // the plan ran out before enough good captures, new viewpoints).
                let left = if planned_off {
                    self.cfg.plan.count.saturating_sub(self.visited)
                } else {
                    (a.min_good - progress.good) * 3 / 2 + 2
                };
                let left = left.min(budget - self.visited);
                if left > 0 {
                    self.make_plan_of(false, left)?;
                }
            }
        }
        let Some(v) = self
            .plan
            .as_ref()
            .and_then(|p| p.viewpoints.get(self.next_viewpoint))
            .cloned()
        else {
            self.stopped_because = Some("plan exhausted".into());
            return Ok(None);
        };
        self.next_viewpoint += 1;
        let cap = self.visit(&v, progress, stop)?;
        self.visited += 1;
        if let Ok(o) = &cap.observed {
            self.observed_board(
                cap.base_from_flange * self.cfg.mount_approx * o.camera_from_target,
            );
        }
        self.captured += 1;
        self.timings.captures += 1;
        Ok(Some(cap))
    }

    fn summary(&self) -> Option<String> {
        let t = &self.timings;
        let n = t.captures.max(1) as f64;
        Some(format!(
            "{} captures ({}), {} retries; plans: {} in {:.0} ms; per capture: compute {:.1} ms (detect {:.1}, decide {:.2}; with the plans amortised {:.1}), motion {:.0} ms, frame wait {:.0} ms; frames passed over while moving {}",
            t.captures,
            self.stopped_because.as_deref().unwrap_or("stopped"),
            t.retries,
            self.plans,
            t.plan_ms,
            (t.detect_ms + t.decide_ms) / n,
            t.detect_ms / n,
            t.decide_ms / n,
            (t.plan_ms + t.detect_ms + t.decide_ms) / n,
            t.motion_ms / n,
            t.frame_wait_ms / n,
            self.frames.dropped()
        ))
    }
}

/// The RGB-D method's features of a frame (detected in the grey image, lifted with
/// the depth of the same frame number).
fn frame_features(
    frame: &LiveFrame,
    depth: &b2b_vision::features::DepthImage,
    unit_m: f64,
    options: &b2b_pipeline::rgbd::RgbdOptions,
) -> anyhow::Result<b2b_protocol::messages::FeatureSet> {
    let gray =
        b2b_vision::GrayImage::from_raw(frame.camera.width, frame.camera.height, &frame.grey)?;
    let (features, points) =
        b2b_pipeline::rgbd::detect_and_lift(&frame.camera, &gray, depth, unit_m, options)?;
    Ok(b2b_pipeline::rgbd::feature_set(&features, &points)?)
}

/// Grey frames from the camera process's iceoryx2 colour service (and, when asked
/// for, the depth frames of the same numbers).
pub struct IceoryxFrames {
    subscriber: b2b_frames::FrameSubscriber,
    depth: Option<b2b_frames::FrameSubscriber>,
    /// A depth frame has arrived at least once (until then a camera without a
    /// depth stream is not waited for long).
    depth_seen: bool,
}

impl std::fmt::Debug for IceoryxFrames {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("IceoryxFrames").finish_non_exhaustive()
    }
}

impl IceoryxFrames {
    /// Subscribes to `robot`'s colour stream under `prefix`.
    pub fn new(prefix: &str, robot: &str) -> anyhow::Result<Self> {
        let name = b2b_frames::service_name_in(prefix, robot, b2b_frames::Stream::Colour);
        Ok(IceoryxFrames {
            subscriber: b2b_frames::FrameSubscriber::new(&name)?,
            depth: None,
            depth_seen: false,
        })
    }

    /// Also subscribes to `robot`'s depth stream: each frame then comes with the
    /// depth frame of the same number.
    pub fn with_depth(mut self, prefix: &str, robot: &str) -> anyhow::Result<Self> {
        let name = b2b_frames::service_name_in(prefix, robot, b2b_frames::Stream::Depth);
        self.depth = Some(b2b_frames::FrameSubscriber::new(&name)?);
        Ok(self)
    }

    /// The depth frame numbered `number`: older ones are skipped; a newer one, or
    /// none within `timeout`, means it is missing (a warning, not an error: the
    /// capture still has its colour frame).
    fn depth_of(
        &mut self,
        number: u64,
        timeout: Duration,
    ) -> anyhow::Result<Option<(b2b_vision::features::DepthImage, f64)>> {
        let Some(sub) = self.depth.as_mut() else {
            return Ok(None);
        };
        let timeout = if self.depth_seen {
            timeout
        } else {
            timeout.min(Duration::from_millis(300))
        };
        let deadline = Instant::now() + timeout;
        while let Some(left) = deadline.checked_duration_since(Instant::now()) {
            let Some(frame) = sub.wait_next(left.min(Duration::from_millis(100)))? else {
                continue;
            };
            let h = *frame.header();
            self.depth_seen = true;
            if h.frame_number < number {
                continue;
            }
            if h.frame_number > number {
                tracing::warn!(
                    "depth frame {number} missing (next is {}): capture without depth",
                    h.frame_number
                );
                return Ok(None);
            }
            anyhow::ensure!(
                h.stream_kind()? == b2b_frames::StreamKind::Z16,
                "the depth service carries {} frames",
                h.stream_kind()?.name()
            );
            anyhow::ensure!(
                h.depth_unit_m > 0.0 && h.depth_unit_m.is_finite(),
                "depth frame {number} has no depth unit"
            );
            let mut data = Vec::with_capacity(h.width as usize * h.height as usize);
            for y in 0..h.height {
                let row = frame.row(y).context("short depth frame")?;
                data.extend(
                    row.chunks_exact(2)
                        .map(|b| u16::from_le_bytes([b[0], b[1]])),
                );
            }
            let depth = b2b_vision::features::DepthImage {
                width: h.width,
                height: h.height,
                data,
            };
            return Ok(Some((depth, h.depth_unit_m)));
        }
        tracing::warn!("depth frame {number} did not arrive within {timeout:?}");
        Ok(None)
    }
}

/// Converts a received frame to grey (RGB is averaged with the BT.601 weights).
fn to_live(frame: &b2b_frames::Frame) -> anyhow::Result<LiveFrame> {
    let h = *frame.header();
    let kind = h.stream_kind()?;
    anyhow::ensure!(
        h.fx > 0.0 && h.fy > 0.0,
        "frame {} carries no intrinsics",
        h.frame_number
    );
    let camera = CameraModel::new(h.width, h.height, [h.fx, h.fy, h.cx, h.cy], &h.dist)?;
    let mut grey = Vec::with_capacity(h.width as usize * h.height as usize);
    for y in 0..h.height {
        let row = frame.row(y).context("short frame")?;
        match kind {
            b2b_frames::StreamKind::Gray8 => grey.extend_from_slice(row),
            b2b_frames::StreamKind::Rgb8 => grey.extend(row.chunks_exact(3).map(|p| {
                (0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2]))
                    .round() as u8
            })),
            other => anyhow::bail!("the colour service carries {} frames", other.name()),
        }
    }
    Ok(LiveFrame {
        number: h.frame_number,
        timestamp_ns: h.timestamp_ns,
        camera,
        grey,
        depth: None,
    })
}

impl FrameSource for IceoryxFrames {
    fn frame_after(&mut self, after_ns: u64, timeout: Duration) -> anyhow::Result<LiveFrame> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            anyhow::ensure!(
                !left.is_zero(),
                "no camera frame exposed after the arm came to rest within {timeout:?} ({})",
                self.subscriber.service_name()
            );
            if let Some(frame) = self
                .subscriber
                .wait_next(left.min(Duration::from_millis(200)))?
                && frame.header().timestamp_ns >= after_ns
            {
                let mut live = to_live(&frame)?;
                drop(frame);
                live.depth = self.depth_of(live.number, Duration::from_secs(2))?;
                return Ok(live);
            }
        }
    }

    fn dropped(&self) -> u64 {
        self.subscriber.stats().dropped + self.depth.as_ref().map_or(0, |d| d.stats().dropped)
    }
}
