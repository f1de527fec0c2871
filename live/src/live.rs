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
use std::time::{Duration, Instant};

use b2b_calib::camera::CameraModel;
use b2b_pipeline::Observation;
use b2b_protocol::RejectedCapture;
use b2b_robot::{Arm, Joints};
use kuka_fri::{FriClient, SafetyGuard, SessionState};
use nalgebra::{Isometry3, Point2, Point3};

use crate::ports::{ArmPort, Clock, SystemClock};
use crate::source::{CaptureSource, Progress, SourceCapture};
use crate::{LiveError, Result};
use b2b_routine::plan::{
    Plan, PlanConfig, PlanScene, Viewpoint, leg_is_safe, plan_viewpoints, reach, recentre,
};
use b2b_routine::{BoardInImage, Mode, Routine, Status, Step, View, VisitAction, VisitEvent};
use b2b_vision::Target;

type Iso3 = Isometry3<f64>;

/// A grey frame from the camera process.
#[derive(Debug, Clone)]
pub struct LiveFrame {
    pub number: u64,
    /// Start of the exposure, ns since the Unix epoch.
    pub timestamp_ns: u64,
    pub camera: CameraModel,
    /// The camera process published no intrinsics (a camera without a factory
    /// calibration): `camera` is then a provisional guess from the image size
    /// until the agent has estimated them ([`LiveSource`] puts its estimate in).
    pub intrinsics_given: bool,
    pub grey: Vec<u8>,
    /// The aligned depth image of the same frame number and its unit (m), when the
    /// source has a depth stream and it arrived.
    pub depth: Option<(b2b_vision::features::DepthImage, f64)>,
}

/// Frames from the camera process.
pub trait FrameSource {
    /// The first frame whose exposure started at or after `after_ns`.
    fn frame_after(&mut self, after_ns: u64, timeout: Duration) -> Result<LiveFrame>;
    /// The newest frame whose exposure started at or after `after_ns`: the
    /// queue is drained, so a watch looks at what the camera sees now, not at
    /// what it saw while the agent was busy.
    fn newest_after(&mut self, after_ns: u64, timeout: Duration) -> Result<LiveFrame>;
    /// Frames that arrived but were never looked at (the queue overflowed while the
    /// arm moved; the camera never waits for the agent).
    fn dropped(&self) -> u64;
}

/// How far (rad) a symmetric board's orientation may be from where the agent
/// believes it is for the belief to choose its labelling: a setup sheet and a
/// mount drawing are good to a few degrees, and the labellings of a board that
/// looks the same turned by 180° are 180° apart.
pub const PRIOR_LABELLING_MAX_RAD: f64 = std::f64::consts::FRAC_PI_4;

/// Detects the target (the agent's configuration, not truth) in a frame and fits its
/// pose, or says why not.
///
/// A target with a symmetry (a checkerboard with `cols + rows` even) is
/// labelled by `expected_camera_from_target`, where the agent believes the
/// board is in this view (the setup sheet's board through the mount's
/// drawing, then the board as the captures so far placed it): the labelling
/// within [`PRIOR_LABELLING_MAX_RAD`] of it, or the capture is rejected
/// with the reason. Every capture of one agent is thereby labelled alike.
fn observe_target(
    target: &Target,
    robot: &str,
    frame: &LiveFrame,
    base_from_flange: Iso3,
    expected_camera_from_target: &Iso3,
    row: usize,
) -> (Result<Observation, RejectedCapture>, Option<f64>) {
    let name = format!("frame {}", frame.number);
    let reject = |reason: String| RejectedCapture {
        robot: robot.to_owned(),
        image: Some(name.clone()),
        row: Some(row),
        reason,
    };
    let img =
        match b2b_vision::GrayImage::from_raw(frame.camera.width, frame.camera.height, &frame.grey)
        {
            Ok(i) => i,
            Err(e) => return (Err(reject(b2b_pipeline::error_chain(&e))), None),
        };
    let sharpness = img.laplacian_variance().ok();
    let symmetry = target.symmetry();
    let mut o = match b2b_pipeline::observe(
        &img,
        &frame.camera,
        target,
        base_from_flange,
        !symmetry.is_trivial(),
    ) {
        Ok(o) => Observation {
            row,
            image: Some(name.clone()),
            ..o
        },
        Err(e) => return (Err(reject(b2b_pipeline::error_chain(&e))), sharpness),
    };
    if !symmetry.is_trivial() {
        let l = symmetry.label_by_prior(
            &o.camera_from_target,
            expected_camera_from_target,
            PRIOR_LABELLING_MAX_RAD,
        );
        let Some(k) = l.element else {
            return (
                Err(reject(format!(
                    "{} looks the same turned, and where the board is believed to be cannot \
                         tell which way: the nearest labelling is {:.0}° from it, the next {:.0}° \
                         (needs within {:.0}° and {:.0}° apart; check T_base_target_approx in the \
                         setup)",
                    target.describe(),
                    l.best_rad.to_degrees(),
                    l.runner_up_rad.to_degrees(),
                    PRIOR_LABELLING_MAX_RAD.to_degrees(),
                    PRIOR_LABELLING_MAX_RAD.to_degrees(),
                ))),
                sharpness,
            );
        };
        o.camera_from_target = symmetry.relabel_pose(&o.camera_from_target, k);
        o.board.target_points = symmetry.relabel_points(&o.board.target_points, k);
    }
    (Ok(o), sharpness)
}

/// Settings of a live source.
#[derive(Debug, Clone)]
pub struct LiveConfig {
    pub robot: String,
    pub mode: Mode,
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
}

/// What `agent watch` observes at its watch pose.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum WatchObserve {
    /// The target only.
    Target,
    /// The scene's features lifted with the depth frame only (as where no
    /// target is left in view).
    Features,
    /// Both: the coordinator watches the target while it is in view and the
    /// scene's features where it is not. Once the target has been missing
    /// from [`LOOK_EVERY_WHEN_GONE`] frames in a row it is looked for in
    /// every that-many-th frame only: a failed search is the detector's
    /// slowest case, and the scene's frames should keep their rate.
    Auto,
}

/// Whether a watch frame is searched for the target, after `missing`
/// frames in a row without it (the features-only watch never searches).
pub fn looks_for_target(observe: WatchObserve, missing: usize) -> bool {
    match observe {
        WatchObserve::Features => false,
        WatchObserve::Target => true,
        WatchObserve::Auto => {
            missing < LOOK_EVERY_WHEN_GONE || missing.is_multiple_of(LOOK_EVERY_WHEN_GONE)
        }
    }
}

/// In [`WatchObserve::Auto`], how many frames the target must have been
/// missing from before it is looked for in only one frame in this many
/// (at 5 Hz: once a second, so a target put back is seen within a second).
pub const LOOK_EVERY_WHEN_GONE: usize = 5;

/// The live source: the arm behind the port `A` (the FRI client in production),
/// its waits and timings on the clock `C` (the host's).
pub struct LiveSource<A = FriClient, C = SystemClock> {
    cfg: LiveConfig,
    fri: A,
    clock: C,
    frames: Box<dyn FrameSource>,
    arm: Arm,
    guard: SafetyGuard,
    /// The target as the agent knows it (configuration, not truth).
    target: Target,
    /// Its points, for planning.
    target_points: Vec<Point3<f64>>,
    camera: Option<CameraModel>,
    /// The camera gives no intrinsics (known from the first frame).
    camera_estimated: bool,
    /// The agent's newest estimate of them ([`CaptureSource::use_camera`]),
    /// which replaces the frames' guess.
    estimated_camera: Option<CameraModel>,
    plan: Option<Plan>,
    captured: u64,
    /// The capture policy's decisions (sans I/O).
    routine: Routine,
    timings: LiveTimings,
}

impl<A, C> std::fmt::Debug for LiveSource<A, C> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveSource")
            .field("robot", &self.cfg.robot)
            .field("captured", &self.captured)
            .finish_non_exhaustive()
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

impl<A: ArmPort> LiveSource<A> {
    /// Connects: waits for the arm's first measured joints (the session reaches
    /// COMMANDING_ACTIVE, the robot application's overlay, before the first
    /// motion). Waits and timings on the host's clock.
    pub fn connect(
        cfg: LiveConfig,
        fri: A,
        frames: Box<dyn FrameSource>,
        arm: Arm,
        guard: SafetyGuard,
        target: Target,
    ) -> Result<Self> {
        Self::connect_with_clock(cfg, fri, SystemClock, frames, arm, guard, target)
    }
}

impl<A: ArmPort, C: Clock> LiveSource<A, C> {
    /// [`LiveSource::connect`] with the waits and timings on `clock`.
    pub fn connect_with_clock(
        cfg: LiveConfig,
        fri: A,
        clock: C,
        frames: Box<dyn FrameSource>,
        arm: Arm,
        guard: SafetyGuard,
        target: Target,
    ) -> Result<Self> {
        fri.wait_for_joints(Duration::from_secs(15))
            .map_err(|e| LiveError::NoJointState {
                source: Some(Box::new(e)),
            })?;
        let routine = Routine::new(cfg.mode.clone(), cfg.plan.count);
        Ok(LiveSource {
            cfg,
            fri,
            clock,
            frames,
            arm,
            guard,
            target_points: target.all_points(),
            target,
            camera: None,
            camera_estimated: false,
            estimated_camera: None,
            plan: None,
            captured: 0,
            routine,
            timings: LiveTimings::default(),
        })
    }

    /// The time since `t` on the source's clock.
    fn since(&self, t: Instant) -> Duration {
        self.clock.now().saturating_duration_since(t)
    }

    /// The measured joints now.
    fn measured(&self) -> Result<Joints> {
        Ok(self
            .fri
            .latest()
            .ok_or(LiveError::NoJointState { source: None })?
            .q)
    }

    /// Waits until the arm is still; returns the host time it was found still.
    fn wait_still(&self) -> Result<u64> {
        let deadline = self.clock.now() + self.cfg.settle_timeout;
        loop {
            if self
                .fri
                .is_still(self.cfg.still_window, self.cfg.still_tol_rad)
            {
                return Ok(self.clock.now_ns());
            }
            if self.clock.now() >= deadline {
                return Err(LiveError::NotAtRest {
                    waited: self.cfg.settle_timeout,
                });
            }
            self.clock.sleep(Duration::from_millis(10));
        }
    }

    /// Still arm, then a frame exposed after it, then the arm checked still again.
    fn still_frame(&mut self) -> Result<(LiveFrame, Joints, f64)> {
        let still_at = self.wait_still()?;
        let waited = self.clock.now();
        let frame = self.frames.frame_after(still_at, self.cfg.frame_timeout)?;
        self.timings.frame_wait_ms += ms(self.since(waited));
        self.still_through(frame)
    }

    /// `frame` with the joints it was taken at, the arm checked still after it
    /// (and the agent's estimate of the camera when the frame carries none).
    fn still_through(&self, mut frame: LiveFrame) -> Result<(LiveFrame, Joints, f64)> {
        if !frame.intrinsics_given
            && let Some(c) = &self.estimated_camera
        {
            let size = (frame.camera.width, frame.camera.height);
            if (c.width, c.height) != size {
                return Err(LiveError::FrameSizeChanged {
                    frame: frame.number,
                    size,
                    estimated: (c.width, c.height),
                });
            }
            frame.camera = c.clone();
        }
        if !self
            .fri
            .is_still(self.cfg.still_window, self.cfg.still_tol_rad)
        {
            return Err(LiveError::MovedDuringExposure {
                frame: frame.number,
            });
        }
        let js = self
            .fri
            .latest()
            .ok_or(LiveError::NoJointState { source: None })?;
        let t = js.timestamp.as_duration().as_secs_f64();
        Ok((frame, js.q, t))
    }

    /// The watch's frame: the arm still (else it waits for rest and takes frames
    /// exposed after it), the newest frame exposed at or after `after_ns`, and
    /// the arm checked still again.
    fn watch_frame(&mut self, after_ns: u64) -> Result<(LiveFrame, Joints, f64)> {
        let after_ns = if self
            .fri
            .is_still(self.cfg.still_window, self.cfg.still_tol_rad)
        {
            after_ns
        } else {
            after_ns.max(self.wait_still()?)
        };
        let frame = self.frames.newest_after(after_ns, self.cfg.frame_timeout)?;
        self.still_through(frame)
    }

    fn move_to(&mut self, q: Joints) -> Result<()> {
        let started = self.clock.now();
        if self.fri.state() != SessionState::CommandingActive {
            self.fri
                .wait_for_state(SessionState::CommandingActive, Duration::from_secs(10))
                .map_err(|e| LiveError::NotCommanding(Box::new(e)))?;
        }
        let r = self.fri.move_to(q).map_err(LiveError::from);
        self.timings.motion_ms += ms(self.since(started));
        r
    }

    /// Plans `count` viewpoints from the current pose, the ring starting at
    /// `phase`. With `first_view`, the board estimate comes from detecting the
    /// board where the arm stands now; otherwise from what the routine has seen,
    /// or the configuration.
    fn make_plan(&mut self, count: usize, first_view: bool, phase: f64) -> Result<()> {
        let (frame, q, _) = self.still_frame()?;
        self.camera = Some(frame.camera.clone());
        self.camera_estimated = !frame.intrinsics_given;
        if self.camera_estimated && self.estimated_camera.is_none() {
            tracing::warn!(
                "{}: the camera gives no intrinsics: planning and detecting with a guess \
                 (focal length {:.0} px) until they are estimated from {} captures",
                self.cfg.robot,
                frame.camera.fx,
                b2b_pipeline::MIN_VIEWS_FOR_INTRINSICS
            );
        }
        let base_from_flange = self.arm.fk(&q);
        if first_view {
            let expected = self.expected_view(&base_from_flange, None);
            let (observed, _) = observe_target(
                &self.target,
                &self.cfg.robot,
                &frame,
                base_from_flange,
                &expected,
                0,
            );
            match observed {
                Ok(o) => self
                    .routine
                    .board_seen(base_from_flange * self.cfg.mount_approx * o.camera_from_target),
                Err(r) => tracing::warn!(
                    "{}: no board in the first view ({}); planning from the configured board position",
                    self.cfg.robot,
                    r.reason
                ),
            }
        }
        let started = self.clock.now();
        let camera = frame.camera.clone();
        let board = self
            .routine
            .board_estimate()
            .unwrap_or(self.cfg.board_approx);
        let scene = PlanScene {
            arm: &self.arm,
            envelope: self.guard.envelope(),
            camera: &camera,
            base_from_target: board,
            flange_from_camera: self.cfg.mount_approx,
            target_points: &self.target_points,
            view_axis: self.target.view_axis(),
        };
        let cfg = PlanConfig {
            count,
            phase,
            ..self.cfg.plan.clone()
        };
        let plan = plan_viewpoints(&scene, &q, &cfg)?;
        self.timings.plan_ms += ms(self.since(started));
        if plan.viewpoints.is_empty() {
            return Err(LiveError::NoSafeViewpoint {
                dropped: plan.dropped,
            });
        }
        self.routine.planned(plan.viewpoints.len(), board);
        self.plan = Some(plan);
        Ok(())
    }

    /// The plan (after the first capture call, or [`LiveSource::plan_only`]).
    pub fn plan(&self) -> Option<&Plan> {
        self.plan.as_ref()
    }

    /// Plans without moving (`--dry-run`).
    /// The drift watch during the operation: moves to the first planned
    /// viewpoint (the board in view by the setup sheet) and stays there; every
    /// `period` until `stop`, a still frame's observation goes to `deliver`.
    /// A frame that cannot be had is logged and skipped; what `deliver` fails
    /// with (its own error type) ends the watch.
    pub fn watch<E: From<LiveError>>(
        &mut self,
        period: Duration,
        observe: WatchObserve,
        stop: &AtomicBool,
        deliver: &mut dyn FnMut(SourceCapture) -> Result<(), E>,
    ) -> Result<(), E> {
        let v = self
            .plan_only()?
            .viewpoints
            .first()
            .cloned()
            .ok_or(LiveError::NoWatchViewpoint)?;
        self.move_to(v.q)?;
        let progress = Progress::default();
        let mut row = 0usize;
        // Frames exposed from here on show the arm at rest; each tick takes the
        // newest one not yet looked at, so a moved cart shows up in the first
        // frame the camera exposes after the move, not one frame later.
        let mut after_ns = self.wait_still()?;
        // Frames in a row without the target.
        let mut missing = 0usize;
        while !stop.load(Ordering::SeqCst) {
            let started = self.clock.now();
            row += 1;
            match self.watch_frame(after_ns) {
                Ok((frame, q, t)) => {
                    after_ns = frame.timestamp_ns + 1;
                    let mut capture = if looks_for_target(observe, missing) {
                        let capture = self.look(&frame, &q, t, row, &progress).0;
                        missing = if capture.observed.is_ok() {
                            0
                        } else {
                            missing + 1
                        };
                        capture
                    } else {
                        // No search: the frame's time goes to its features.
                        let why = if observe == WatchObserve::Features {
                            "watching the scene's features, not the target".into()
                        } else {
                            missing += 1;
                            format!(
                                "the target has been out of view for {missing} frames: looked for in every {LOOK_EVERY_WHEN_GONE}th"
                            )
                        };
                        let observed = Err(self.reject(row, why));
                        self.frame_capture(&frame, self.arm.fk(&q), t, row, observed)
                    };
                    if observe != WatchObserve::Target {
                        capture.features = self.features(&frame);
                    }
                    deliver(capture)?;
                }
                Err(e) => {
                    tracing::warn!(
                        "{}: watch: {}",
                        self.cfg.robot,
                        b2b_pipeline::error_chain(&e)
                    );
                    // Whatever went wrong (the arm pushed, the camera late),
                    // only frames exposed from now on count.
                    after_ns = after_ns.max(self.clock.now_ns());
                }
            }
            while self.since(started) < period && !stop.load(Ordering::SeqCst) {
                self.clock.sleep(
                    period
                        .saturating_sub(self.since(started))
                        .min(Duration::from_millis(50)),
                );
            }
        }
        Ok(())
    }

    /// Sets the local features lifted with each frame's depth (`None`: none)
    /// and returns the previous setting. Depth frames come only to a source
    /// connected with features.
    pub fn set_features(
        &mut self,
        features: Option<b2b_pipeline::rgbd::RgbdOptions>,
    ) -> Option<b2b_pipeline::rgbd::RgbdOptions> {
        std::mem::replace(&mut self.cfg.features, features)
    }

    pub fn plan_only(&mut self) -> Result<&Plan> {
        if let Step::Plan {
            count,
            first_view,
            phase,
        } = self.routine.first_plan()
        {
            self.make_plan(count, first_view, phase)?;
        }
        self.plan.as_ref().ok_or(LiveError::NoPlan)
    }

    fn reject(&self, row: usize, reason: String) -> RejectedCapture {
        RejectedCapture {
            robot: self.cfg.robot.clone(),
            image: None,
            row: Some(row),
            reason,
        }
    }

    /// Where the board should be in the camera at `base_from_flange`: as the
    /// good captures so far placed it, else as the first view or the setup
    /// sheet did, seen through the mount's drawing.
    fn expected_view(&self, base_from_flange: &Iso3, progress: Option<&Progress>) -> Iso3 {
        let board = progress
            .and_then(|p| p.base_from_target.last().copied())
            .or(self.routine.board_estimate())
            .unwrap_or(self.cfg.board_approx);
        (base_from_flange * self.cfg.mount_approx).inverse() * board
    }

    /// One viewpoint: the routine decides ([`Routine::step_visit`]); this does
    /// what it asks (move, settle and capture, detect, re-centre) and tells it
    /// what happened.
    fn visit(
        &mut self,
        v: &Viewpoint,
        progress: &Progress,
        stop: &AtomicBool,
    ) -> Result<SourceCapture> {
        let row = self.captured as usize + 1;
        let status = status(progress);
        let (mut visit, mut action) = self.routine.visit(v.q);
        // The last still frame: its capture, the joints it was taken at, and the
        // frame (its features are computed only for the visit's final frame,
        // never for the frames before a re-centring).
        let mut last: Option<(SourceCapture, Joints, LiveFrame)> = None;
        loop {
            if stop.load(Ordering::SeqCst) {
                return Err(LiveError::Interrupted);
            }
            let event = match action {
                VisitAction::MoveTo(q) => match self.move_to(q) {
                    Ok(()) => VisitEvent::Moved,
                    Err(e) => VisitEvent::MoveFailed(b2b_pipeline::error_chain(&e)),
                },
                VisitAction::Capture => match self.still_frame() {
                    Ok((frame, q, controller_t)) => {
                        let (capture, view) = self.look(&frame, &q, controller_t, row, progress);
                        last = Some((capture, q, frame));
                        VisitEvent::Seen(view)
                    }
                    Err(e) => VisitEvent::NoFrame(b2b_pipeline::error_chain(&e)),
                },
                VisitAction::Recentre { centre_in_camera } => {
                    let started = self.clock.now();
                    let (capture, q, _) = last.as_ref().ok_or(LiveError::NoFrame {
                        step: "re-centring",
                    })?;
                    let result = self.recentre(
                        &capture.base_from_flange,
                        &capture.camera,
                        q,
                        &centre_in_camera,
                    );
                    self.timings.decide_ms += ms(self.since(started));
                    VisitEvent::Recentred(result)
                }
                VisitAction::Deliver => {
                    let (mut capture, _, frame) =
                        last.ok_or(LiveError::NoFrame { step: "delivering" })?;
                    capture.features = self.features(&frame);
                    return Ok(capture);
                }
                VisitAction::Reject(reason) => {
                    let (mut capture, _, frame) =
                        last.ok_or(LiveError::NoFrame { step: "rejecting" })?;
                    capture.features = self.features(&frame);
                    capture.observed = Err(self.reject(row, reason));
                    return Ok(capture);
                }
                VisitAction::GiveUp(reason) => {
                    return Ok(SourceCapture {
                        index: row as u64 - 1,
                        image: None,
                        base_from_flange: self.arm.fk(&self.measured()?),
                        controller_time_s: None,
                        camera: self.camera.clone().ok_or(LiveError::NoCamera)?,
                        intrinsics_estimated: self.camera_estimated,
                        observed: Err(self.reject(row, reason)),
                        pixels: None,
                        features: None,
                        target_centre: self.target.centre(),
                        target: None,
                    });
                }
            };
            let started = self.clock.now();
            action = self.routine.step_visit(&mut visit, event, &status);
            self.timings.decide_ms += ms(self.since(started));
        }
    }

    /// Detects the target in a still frame: the capture as it would be
    /// delivered, and what the routine needs to judge it.
    fn look(
        &mut self,
        frame: &LiveFrame,
        q: &Joints,
        controller_t: f64,
        row: usize,
        progress: &Progress,
    ) -> (SourceCapture, View) {
        let camera = &frame.camera;
        let base_from_flange = self.arm.fk(q);
        let detect_started = self.clock.now();
        let expected = self.expected_view(&base_from_flange, Some(progress));
        let (observed, sharpness) = observe_target(
            &self.target,
            &self.cfg.robot,
            frame,
            base_from_flange,
            &expected,
            row,
        );
        self.timings.detect_ms += ms(self.since(detect_started));
        let board = match &observed {
            Ok(o) => {
                let n = o.board.pixels.len().max(1) as f64;
                let c = o
                    .board
                    .pixels
                    .iter()
                    .fold(Point2::origin(), |acc, p| acc + p.coords / n);
                Ok(BoardInImage {
                    centre_px: c,
                    width: camera.width,
                    height: camera.height,
                    principal_px: Point2::new(camera.cx, camera.cy),
                    centre_in_camera: o.camera_from_target * self.target.centre(),
                })
            }
            Err(r) => Err(r.reason.clone()),
        };
        let view = View {
            base_from_flange,
            // Where the board should be, when it was not found: the same belief
            // that labelled a symmetric board.
            predicted_centre_in_camera: board.is_err().then(|| expected * self.target.centre()),
            board,
            sharpness,
        };
        let capture = self.frame_capture(frame, base_from_flange, controller_t, row, observed);
        (capture, view)
    }

    /// A still frame's capture as it would be delivered, with what was observed
    /// in it (no features: [`Self::features`] adds them).
    fn frame_capture(
        &self,
        frame: &LiveFrame,
        base_from_flange: Iso3,
        controller_t: f64,
        row: usize,
        observed: Result<Observation, RejectedCapture>,
    ) -> SourceCapture {
        SourceCapture {
            index: row as u64 - 1,
            image: Some(format!("frame {}", frame.number)),
            base_from_flange,
            controller_time_s: Some(controller_t),
            camera: frame.camera.clone(),
            intrinsics_estimated: !frame.intrinsics_given,
            observed,
            pixels: Some(frame.grey.clone()),
            features: None,
            target_centre: self.target.centre(),
            target: None,
        }
    }

    /// The RGB-D method's features of a visit's final frame, delivered or
    /// rejected (none without a depth image, or when the agent was not asked for
    /// them).
    fn features(&mut self, frame: &LiveFrame) -> Option<b2b_protocol::messages::FeatureSet> {
        let (options, (depth, unit)) = self.cfg.features.as_ref().zip(frame.depth.as_ref())?;
        let started = self.clock.now();
        let features = frame_features(frame, depth, *unit, options)
            .map_err(|e| {
                tracing::warn!(
                    "frame {}: no features: {}",
                    frame.number,
                    b2b_pipeline::error_chain(&e)
                )
            })
            .ok();
        self.timings.detect_ms += ms(self.since(started));
        features
    }

    /// A safe pose from `q` that puts `centre_in_camera` at the image centre.
    fn recentre(
        &self,
        base_from_flange: &Iso3,
        camera: &CameraModel,
        q: &Joints,
        centre_in_camera: &Point3<f64>,
    ) -> Result<Joints, String> {
        let base_from_camera = base_from_flange * self.cfg.mount_approx;
        let wanted = recentre(&base_from_camera, centre_in_camera, None);
        let scene = PlanScene {
            arm: &self.arm,
            envelope: self.guard.envelope(),
            camera,
            base_from_target: self.cfg.board_approx,
            flange_from_camera: self.cfg.mount_approx,
            target_points: &self.target_points,
            view_axis: self.target.view_axis(),
        };
        match reach(&scene, &wanted, q) {
            Ok((q_new, _))
                if leg_is_safe(
                    self.guard.envelope(),
                    &self.arm,
                    q,
                    &q_new,
                    self.cfg.plan.path_step_rad,
                ) =>
            {
                Ok(q_new)
            }
            Ok(_) => Err("the re-centred pose has no safe path".into()),
            Err(e) => Err(format!("the re-centred pose: {e}")),
        }
    }

    /// Compute and motion timings so far.
    pub fn timings(&self) -> LiveTimings {
        self.timings
    }

    /// The arm port (the FRI client, for shutdown).
    pub fn into_arm(self) -> A {
        self.fri
    }
}

impl<C> LiveSource<FriClient, C> {
    /// The FRI client (for shutdown).
    pub fn into_fri(self) -> FriClient {
        self.fri
    }
}

/// What the routine needs of the agent's progress.
fn status(progress: &Progress) -> Status<'_> {
    Status {
        good: progress.good,
        hand_eye_covariance: progress.hand_eye.as_ref().map(|he| &he.covariance),
        good_poses: &progress.good_poses,
    }
}

impl<A: ArmPort, C: Clock> CaptureSource for LiveSource<A, C> {
    fn describe(&self) -> String {
        match self.cfg.mode {
            Mode::Program => format!("{}: visiting the planned viewpoints", self.cfg.robot),
            Mode::Auto(_) => format!("{}: automatic routine", self.cfg.robot),
        }
    }

    fn expected(&self) -> Option<u64> {
        Some(self.cfg.plan.count as u64)
    }

    fn next(&mut self, progress: &Progress, stop: &AtomicBool) -> Result<Option<SourceCapture>> {
        let v = loop {
            match self.routine.next_step(&status(progress)) {
                Step::Plan {
                    count,
                    first_view,
                    phase,
                } => self.make_plan(count, first_view, phase)?,
                Step::Visit(k) => {
                    break self
                        .plan
                        .as_ref()
                        .and_then(|p| p.viewpoints.get(k))
                        .cloned()
                        .ok_or(LiveError::UnplannedViewpoint { index: k })?;
                }
                Step::Stop(_) => return Ok(None),
            }
        };
        let cap = self.visit(&v, progress, stop)?;
        if let Ok(o) = &cap.observed {
            self.routine
                .board_seen(cap.base_from_flange * self.cfg.mount_approx * o.camera_from_target);
        }
        self.captured += 1;
        self.timings.captures += 1;
        Ok(Some(cap))
    }

    fn use_camera(&mut self, camera: &CameraModel) {
        if self.camera_estimated {
            self.estimated_camera = Some(camera.clone());
            self.camera = Some(camera.clone());
        }
    }

    fn summary(&self) -> Option<String> {
        let t = &self.timings;
        let n = t.captures.max(1) as f64;
        Some(format!(
            "{} captures ({}), {} retries; plans: {} in {:.0} ms; per capture: compute {:.1} ms (detect {:.1}, decide {:.2}; with the plans amortised {:.1}), motion {:.0} ms, frame wait {:.0} ms; frames passed over while moving {}",
            t.captures,
            self.routine.stopped_because().unwrap_or("stopped"),
            self.routine.retries(),
            self.routine.plans(),
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
) -> Result<b2b_protocol::messages::FeatureSet> {
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
    pub fn new(prefix: &str, robot: &str) -> Result<Self> {
        let name = b2b_frames::service_name_in(prefix, robot, b2b_frames::Stream::Colour);
        Ok(IceoryxFrames {
            subscriber: b2b_frames::FrameSubscriber::new(&name)?,
            depth: None,
            depth_seen: false,
        })
    }

    /// Also subscribes to `robot`'s depth stream: each frame then comes with the
    /// depth frame of the same number.
    pub fn with_depth(mut self, prefix: &str, robot: &str) -> Result<Self> {
        let name = b2b_frames::service_name_in(prefix, robot, b2b_frames::Stream::Depth);
        self.depth = Some(b2b_frames::FrameSubscriber::new(&name)?);
        Ok(self)
    }

    /// The depth frame of colour frame `colour`: the one numbered like it
    /// (older ones are skipped). A newer one, none within `timeout`, or one
    /// exposed more than [`DEPTH_PAIR_WINDOW_NS`] from the colour frame means the
    /// capture has no depth (a warning, not an error: it still has its colour
    /// frame). A depth frame of another size than its colour frame is an error:
    /// depth must come aligned to colour (the camera process aligns it).
    fn depth_of(
        &mut self,
        colour: &LiveFrame,
        timeout: Duration,
    ) -> Result<Option<(b2b_vision::features::DepthImage, f64)>> {
        let number = colour.number;
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
            let kind = h.stream_kind()?;
            if kind != b2b_frames::StreamKind::Z16 {
                return Err(LiveError::WrongStream {
                    service: "depth",
                    kind,
                });
            }
            if !(h.depth_unit_m > 0.0 && h.depth_unit_m.is_finite()) {
                return Err(LiveError::NoDepthUnit { frame: number });
            }
            let colour_size = (colour.camera.width, colour.camera.height);
            if (h.width, h.height) != colour_size {
                return Err(LiveError::DepthNotAligned {
                    frame: number,
                    depth: (h.width, h.height),
                    colour: colour_size,
                });
            }
            let gap = h.timestamp_ns.abs_diff(colour.timestamp_ns);
            if gap > DEPTH_PAIR_WINDOW_NS {
                tracing::warn!(
                    "depth frame {number} was exposed {:.1} ms from its colour frame (at most {:.1} ms): capture without depth",
                    gap as f64 / 1e6,
                    DEPTH_PAIR_WINDOW_NS as f64 / 1e6
                );
                return Ok(None);
            }
            let mut data = Vec::with_capacity(h.width as usize * h.height as usize);
            for y in 0..h.height {
                let row = frame.row(y).ok_or(LiveError::ShortFrame { depth: true })?;
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

/// The largest gap between a colour frame's and its depth frame's exposure
/// for the two to be one capture: below a frame period at 30 fps (33 ms), so a
/// depth frame one frame off is never taken for this one's. The camera process
/// pairs within half a period; this is the agent's own check of what arrives.
pub const DEPTH_PAIR_WINDOW_NS: u64 = 20_000_000;

/// Converts a received frame to grey (RGB is averaged with the BT.601 weights).
fn to_live(frame: &b2b_frames::Frame) -> Result<LiveFrame> {
    let h = *frame.header();
    let kind = h.stream_kind()?;
    // A camera without intrinsics publishes zero focal lengths; anything else
    // that is not a positive focal length is a broken header.
    let intrinsics_given = !(h.fx == 0.0 && h.fy == 0.0);
    if intrinsics_given && !(h.fx > 0.0 && h.fy > 0.0) {
        return Err(LiveError::BadFocalLengths {
            frame: h.frame_number,
            fx: h.fx,
            fy: h.fy,
        });
    }
    let camera = if intrinsics_given {
        CameraModel::new(h.width, h.height, [h.fx, h.fy, h.cx, h.cy], &h.dist)?
    } else {
        b2b_pipeline::guess_camera(h.width, h.height)?
    };
    let mut grey = Vec::with_capacity(h.width as usize * h.height as usize);
    for y in 0..h.height {
        let row = frame.row(y).ok_or(LiveError::ShortFrame { depth: false })?;
        match kind {
            b2b_frames::StreamKind::Gray8 => grey.extend_from_slice(row),
            b2b_frames::StreamKind::Rgb8 => grey.extend(row.chunks_exact(3).map(|p| {
                (0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2]))
                    .round() as u8
            })),
            kind => {
                return Err(LiveError::WrongStream {
                    service: "colour",
                    kind,
                });
            }
        }
    }
    Ok(LiveFrame {
        number: h.frame_number,
        timestamp_ns: h.timestamp_ns,
        camera,
        intrinsics_given,
        grey,
        depth: None,
    })
}

impl IceoryxFrames {
    /// A received colour frame as a `LiveFrame` (its shared-memory sample
    /// released at once), with the depth frame of the same number when there is
    /// a depth stream.
    fn live_frame(&mut self, frame: b2b_frames::Frame) -> Result<LiveFrame> {
        let mut live = to_live(&frame)?;
        drop(frame);
        live.depth = self.depth_of(&live, Duration::from_secs(2))?;
        Ok(live)
    }
}

impl FrameSource for IceoryxFrames {
    fn frame_after(&mut self, after_ns: u64, timeout: Duration) -> Result<LiveFrame> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(LiveError::NoFrameInTime {
                    waited: timeout,
                    service: self.subscriber.service_name().to_owned(),
                });
            }
            if let Some(frame) = self
                .subscriber
                .wait_next(left.min(Duration::from_millis(200)))?
                && frame.header().timestamp_ns >= after_ns
            {
                return self.live_frame(frame);
            }
        }
    }

    fn newest_after(&mut self, after_ns: u64, timeout: Duration) -> Result<LiveFrame> {
        if let Some(frame) = self.subscriber.latest()?
            && frame.header().timestamp_ns >= after_ns
        {
            return self.live_frame(frame);
        }
        self.frame_after(after_ns, timeout)
    }

    fn dropped(&self) -> u64 {
        self.subscriber.stats().dropped + self.depth.as_ref().map_or(0, |d| d.stats().dropped)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Auto searches every frame while the target is in view, and one frame
    /// in five once it has been gone for five; the other modes always or never.
    #[test]
    fn the_watch_looks_for_a_gone_target_once_in_five_frames() {
        let looked: Vec<usize> = (0..20)
            .filter(|&m| looks_for_target(WatchObserve::Auto, m))
            .collect();
        assert_eq!(looked, [0, 1, 2, 3, 4, 5, 10, 15]);
        assert!((0..20).all(|m| looks_for_target(WatchObserve::Target, m)));
        assert!((0..20).all(|m| !looks_for_target(WatchObserve::Features, m)));
    }
}
