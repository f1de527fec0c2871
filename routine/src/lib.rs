//! The automatic pre-operative routine's decisions, without I/O.
//!
//! The agent's live source does the I/O: it moves the arm through FRI, waits
//! until it is still, takes a frame, detects the target and plans viewpoints.
//! This crate decides, from what those steps observed, what happens next, so
//! that every policy branch is a unit test rather than a whole-process run:
//!
//! - [`Routine::next_step`]: plan, re-plan, visit the next viewpoint, or stop
//!   (the stop rule, the board found elsewhere than planned for, the plan
//!   exhausted before enough good captures, the visit budget).
//! - [`Routine::step_visit`]: one viewpoint's attempts. Observations go in
//!   ([`VisitEvent`]: moved, motion refused, no still frame, what the camera
//!   saw, a re-centred pose); actions come out ([`VisitAction`]: move to q,
//!   capture, re-centre on a point, deliver the capture, reject it with a
//!   reason, give up with a reason).
//!
//! Every threshold is a named constant below; [`RoutineConfig`] carries the
//! ones an operator may change.

use b2b_robot::Joints;
use nalgebra::{Isometry3, Point2, Point3};

pub mod plan;

type Iso3 = Isometry3<f64>;

/// Tries per viewpoint, the first included (so at most three re-centrings).
pub const MAX_TRIES: usize = 4;
/// A board whose detected centre is further than this fraction of the image
/// size (per axis) from the principal point is re-centred.
pub const OFF_CENTRE_FRACTION: f64 = 0.12;
/// The stop rule: the hand-eye's largest 1-sigma translation, m ...
pub const STOP_SIGMA_T_M: f64 = 0.1e-3;
/// ... and rotation, degrees ...
pub const STOP_SIGMA_R_DEG: f64 = 0.01;
/// ... with at least this many good captures.
pub const MIN_GOOD: usize = 20;
/// A capture closer than this to an earlier good one (translation, m) ...
pub const SIMILAR_T_M: f64 = 5e-3;
/// ... and rotation (degrees) adds little and is rejected as too similar.
pub const SIMILAR_R_DEG: f64 = 2.0;
/// A capture whose sharpness (variance of the Laplacian) is below this
/// fraction of the median so far is rejected as blurred ...
pub const BLUR_FRACTION: f64 = 0.3;
/// ... once this many sharp captures give a median.
pub const BLUR_MIN_HISTORY: usize = 3;
/// Re-plan when the board is seen further than this from where the plan
/// assumed it (m).
pub const REPLAN_SHIFT_M: f64 = 0.01;
/// Each new plan starts its ring of viewpoints this much further round (rad),
/// so a top-up plan does not repeat the first.
pub const REPLAN_PHASE_STEP_RAD: f64 = 0.7;
/// Viewpoints visited in all, at most this many times the planned count.
pub const VISIT_BUDGET_FACTOR: usize = 2;
/// A plan has at least this many viewpoints.
pub const MIN_PLAN_COUNT: usize = 3;

/// Good captures (their motions passing the degeneracy checks) before an
/// agent's status says it has enough data: a first hand-eye from ten is good to
/// a few tenths of a millimetre, enough for the operator to go on; the
/// automatic routine itself stops only by its own rule ([`MIN_GOOD`] and the
/// hand-eye's sigmas).
pub const ENOUGH_CAPTURES: usize = 10;

/// Whether the agent fits its camera's intrinsics again to every good
/// capture's corners after a capture: for a camera that gave none
/// (`estimated`), once `good` captures (this one included) reach the fewest
/// views the intrinsics are fitted to, and only when this capture added one
/// (`observed`).
pub fn refit_intrinsics(estimated: bool, observed: bool, good: usize, min_views: usize) -> bool {
    estimated && observed && good >= min_views
}

/// Whether the agent fits the hand-eye after a capture: as soon as the good
/// captures' motions pass the degeneracy checks (two rotations with
/// non-parallel axes, not a pure translation), and never from a guessed camera
/// (intrinsics neither given by the camera nor estimated yet: it would put the
/// board centimetres off).
pub fn fit_hand_eye(motions_ok: bool, intrinsics_known: bool) -> bool {
    motions_ok && intrinsics_known
}

/// Whether the agent's status says "enough data" ([`ENOUGH_CAPTURES`]).
pub fn enough_data(motions_ok: bool, good: usize) -> bool {
    motions_ok && good >= ENOUGH_CAPTURES
}

/// Viewpoints of a top-up plan when the plan ran out `missing` good captures
/// short: half as many again (some will be rejected), and two more.
pub fn top_up(missing: usize) -> usize {
    missing * 3 / 2 + 2
}

/// A setting that cannot work.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RoutineError {
    #[error("{what} must be a number > 0, not {value}")]
    NotPositive { what: &'static str, value: f64 },
    #[error("{what} must be at least {min}, not {value}")]
    TooSmall {
        what: &'static str,
        min: usize,
        value: usize,
    },
    #[error("{what} must be in {range}, not {value}")]
    OutOfRange {
        what: &'static str,
        value: f64,
        range: &'static str,
    },
    #[error("plan: the distance range [{near}, {far}] m is not a range of distances above 0.05 m")]
    PlanDistances { near: f64, far: f64 },
    #[error("plan: the target has no points")]
    NoTargetPoints,
    #[error("plan: the target's view axis is zero")]
    ZeroViewAxis,
}

/// The automatic routine's settings (defaults: the constants above).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoutineConfig {
    pub max_tries: usize,
    pub off_centre: f64,
    pub stop_sigma_t_m: f64,
    pub stop_sigma_r_rad: f64,
    pub min_good: usize,
    pub similar_t_m: f64,
    pub similar_r_rad: f64,
    pub blur_fraction: f64,
}

impl Default for RoutineConfig {
    fn default() -> Self {
        RoutineConfig {
            max_tries: MAX_TRIES,
            off_centre: OFF_CENTRE_FRACTION,
            stop_sigma_t_m: STOP_SIGMA_T_M,
            stop_sigma_r_rad: STOP_SIGMA_R_DEG.to_radians(),
            min_good: MIN_GOOD,
            similar_t_m: SIMILAR_T_M,
            similar_r_rad: SIMILAR_R_DEG.to_radians(),
            blur_fraction: BLUR_FRACTION,
        }
    }
}

impl RoutineConfig {
    /// Refuses settings that cannot work (a stop bound of zero is never met).
    pub fn validate(&self) -> Result<(), RoutineError> {
        let positive = [
            ("the stop rule's translation sigma", self.stop_sigma_t_m),
            ("the stop rule's rotation sigma", self.stop_sigma_r_rad),
            ("the off-centre fraction", self.off_centre),
            ("the similarity distance", self.similar_t_m),
            ("the similarity angle", self.similar_r_rad),
            ("the blur fraction", self.blur_fraction),
        ];
        for (what, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return Err(RoutineError::NotPositive { what, value });
            }
        }
        if self.max_tries == 0 {
            return Err(RoutineError::TooSmall {
                what: "tries per viewpoint",
                min: 1,
                value: 0,
            });
        }
        Ok(())
    }
}

/// What the live source does.
#[derive(Debug, Clone, PartialEq)]
pub enum Mode {
    /// `agent run`: visit the planned viewpoints once; no re-centring, no checks,
    /// no early stop.
    Program,
    /// `agent auto`: the automatic pre-operative routine.
    Auto(RoutineConfig),
}

/// What the agent's fit knows so far.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Status<'a> {
    pub good: usize,
    /// The newest hand-eye covariance (`[r; t]`, left perturbation).
    pub hand_eye_covariance: Option<&'a [[f64; 6]; 6]>,
    /// Flange poses of the good captures so far.
    pub good_poses: &'a [Iso3],
}

/// The next thing the routine wants.
#[derive(Debug, Clone, PartialEq)]
pub enum Step {
    /// Plan `count` viewpoints around the board estimate, starting the ring at
    /// `phase`. With `first_view`, first look for the board from where the arm
    /// stands. Report the plan with [`Routine::planned`].
    Plan {
        count: usize,
        first_view: bool,
        phase: f64,
    },
    /// Visit this viewpoint of the current plan.
    Visit(usize),
    /// Done, and why.
    Stop(String),
}

/// One viewpoint's attempts ([`Routine::visit`], [`Routine::step_visit`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Visit {
    target: Joints,
    attempt: usize,
    last_reason: String,
    /// The last frame showed the board.
    found: bool,
}

impl Visit {
    /// Attempts so far (1 for the first).
    pub fn attempt(&self) -> usize {
        self.attempt
    }
}

/// Where the board was detected in an image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardInImage {
    /// Mean of the detected corners, px.
    pub centre_px: Point2<f64>,
    pub width: u32,
    pub height: u32,
    /// The principal point, px.
    pub principal_px: Point2<f64>,
    /// The target's centre in the camera frame (from its pose).
    pub centre_in_camera: Point3<f64>,
}

/// What one still frame showed.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    pub base_from_flange: Iso3,
    /// The board, or why it was not found.
    pub board: Result<BoardInImage, String>,
    /// Where the board should be in the camera (from the board estimate), for
    /// re-centring on a board that was not found.
    pub predicted_centre_in_camera: Option<Point3<f64>>,
    /// Variance of the Laplacian, when it could be measured.
    pub sharpness: Option<f64>,
}

/// An observation during a visit.
#[derive(Debug, Clone, PartialEq)]
pub enum VisitEvent {
    /// The arm reached the commanded joints.
    Moved,
    /// The motion was refused (safety guard) or aborted.
    MoveFailed(String),
    /// No still frame (the arm did not settle, moved during the exposure, or
    /// no frame came).
    NoFrame(String),
    /// A still frame and what it showed.
    Seen(View),
    /// The pose that re-centres the board, or why there is none.
    Recentred(Result<Joints, String>),
}

/// What to do next in a visit.
#[derive(Debug, Clone, PartialEq)]
pub enum VisitAction {
    MoveTo(Joints),
    /// Wait until still, take the first frame exposed after that, detect.
    Capture,
    /// Find a safe pose from the current one that puts this point (in the
    /// camera frame) at the image centre; answer with [`VisitEvent::Recentred`].
    Recentre {
        centre_in_camera: Point3<f64>,
    },
    /// Deliver the last frame's observation as it is (a detection, or the
    /// detector's reason for none).
    Deliver,
    /// Deliver the last frame as rejected, with the reason.
    Reject(String),
    /// No frame to deliver: the viewpoint failed, with the reason.
    GiveUp(String),
}

/// The routine's state.
#[derive(Debug, Clone)]
pub struct Routine {
    mode: Mode,
    /// Viewpoints the operator asked for.
    count: usize,
    plan_len: Option<usize>,
    next_viewpoint: usize,
    visited: usize,
    plans: usize,
    board_estimate: Option<Iso3>,
    planned_for: Option<Iso3>,
    sharpness: Vec<f64>,
    stopped_because: Option<String>,
    retries: usize,
}

/// The largest 1-sigma translation (m) and rotation (rad) of a `[r; t]` covariance.
pub fn sigmas(cov: &[[f64; 6]; 6]) -> (f64, f64) {
    let max = |range: std::ops::Range<usize>| {
        range.map(|i| cov[i][i]).fold(0.0, f64::max).max(0.0).sqrt()
    };
    (max(3..6), max(0..3))
}

/// Translation distance (m) and rotation angle (rad) between two poses.
fn pose_distance(a: &Iso3, b: &Iso3) -> (f64, f64) {
    let d = a.inverse() * b;
    (d.translation.vector.norm(), d.rotation.angle())
}

impl Routine {
    /// A routine for `count` planned viewpoints.
    pub fn new(mode: Mode, count: usize) -> Self {
        Routine {
            mode,
            count,
            plan_len: None,
            next_viewpoint: 0,
            visited: 0,
            plans: 0,
            board_estimate: None,
            planned_for: None,
            sharpness: vec![],
            stopped_because: None,
            retries: 0,
        }
    }

    pub fn mode(&self) -> &Mode {
        &self.mode
    }

    fn auto(&self) -> Option<&RoutineConfig> {
        match &self.mode {
            Mode::Auto(a) => Some(a),
            Mode::Program => None,
        }
    }

    /// The first plan: in the automatic routine, look for the board first.
    pub fn first_plan(&self) -> Step {
        Step::Plan {
            count: self.count.max(MIN_PLAN_COUNT),
            first_view: self.auto().is_some(),
            phase: 0.0,
        }
    }

    /// The next step, given what the fit knows.
    pub fn next_step(&mut self, status: &Status<'_>) -> Step {
        if self.plan_len.is_none() {
            return self.first_plan();
        }
        if let Some(a) = self.auto().copied() {
            if let Some(cov) = status.hand_eye_covariance {
                let (t, r) = sigmas(cov);
                if status.good >= a.min_good && t <= a.stop_sigma_t_m && r <= a.stop_sigma_r_rad {
                    return self.stop(format!(
                        "data sufficient after {} good captures: hand-eye sigma {:.3} mm, {:.4} deg",
                        status.good,
                        t * 1e3,
                        r.to_degrees()
                    ));
                }
            }
            let exhausted = self.plan_len.is_none_or(|n| self.next_viewpoint >= n);
            let planned_off = match (self.board_estimate, self.planned_for) {
                (Some(b), Some(p)) => {
                    (b.translation.vector - p.translation.vector).norm() > REPLAN_SHIFT_M
                }
                _ => false,
            };
            let budget = VISIT_BUDGET_FACTOR * self.count;
            if planned_off || (exhausted && status.good < a.min_good && self.visited < budget) {
                // Re-plan around the board where the camera actually sees it (or,
                // when the plan ran out before enough good captures, new viewpoints).
                let left = if planned_off {
                    self.count.saturating_sub(self.visited)
                } else {
                    top_up(a.min_good - status.good)
                };
                let left = left.min(budget.saturating_sub(self.visited));
                if left > 0 {
                    return Step::Plan {
                        count: left.max(MIN_PLAN_COUNT),
                        first_view: false,
                        phase: self.plans as f64 * REPLAN_PHASE_STEP_RAD,
                    };
                }
            }
        }
        match self.plan_len {
            Some(n) if self.next_viewpoint < n => {
                self.next_viewpoint += 1;
                Step::Visit(self.next_viewpoint - 1)
            }
            _ => self.stop("plan exhausted".into()),
        }
    }

    fn stop(&mut self, reason: String) -> Step {
        self.stopped_because = Some(reason.clone());
        Step::Stop(reason)
    }

    /// A plan of `len` viewpoints was made around `board` (answering [`Step::Plan`]).
    pub fn planned(&mut self, len: usize, board: Iso3) {
        self.plans += 1;
        self.plan_len = Some(len);
        self.planned_for = Some(board);
        self.next_viewpoint = 0;
    }

    /// The board's pose in the base as a first view or a good capture showed it
    /// (approximate mount): the first one replaces the configured position for
    /// planning; later ones only while the first plan runs.
    pub fn board_seen(&mut self, base_from_target: Iso3) {
        if self.board_estimate.is_none() || self.plans <= 1 {
            self.board_estimate = Some(base_from_target);
        }
    }

    /// Where the routine believes the board is, if it has seen it.
    pub fn board_estimate(&self) -> Option<Iso3> {
        self.board_estimate
    }

    pub fn plans(&self) -> usize {
        self.plans
    }

    /// Re-centring retries so far.
    pub fn retries(&self) -> usize {
        self.retries
    }

    pub fn stopped_because(&self) -> Option<&str> {
        self.stopped_because.as_deref()
    }

    /// Starts a visit of the viewpoint at `q`: its first action is the move.
    pub fn visit(&mut self, q: Joints) -> (Visit, VisitAction) {
        self.visited += 1;
        (
            Visit {
                target: q,
                attempt: 1,
                last_reason: String::new(),
                found: false,
            },
            VisitAction::MoveTo(q),
        )
    }

    fn tries(&self) -> usize {
        self.auto().map_or(1, |a| a.max_tries.max(1))
    }

    /// The next try of the same viewpoint, or the end of the visit.
    fn retry(&mut self, visit: &mut Visit) -> VisitAction {
        if visit.attempt < self.tries() {
            visit.attempt += 1;
            self.retries += 1;
            VisitAction::MoveTo(visit.target)
        } else {
            VisitAction::GiveUp(visit.last_reason.clone())
        }
    }

    /// Advances a visit by one observation.
    pub fn step_visit(
        &mut self,
        visit: &mut Visit,
        event: VisitEvent,
        status: &Status<'_>,
    ) -> VisitAction {
        match event {
            VisitEvent::Moved => VisitAction::Capture,
            VisitEvent::MoveFailed(e) => {
                visit.last_reason = format!("motion refused or aborted: {e}");
                VisitAction::GiveUp(visit.last_reason.clone())
            }
            VisitEvent::NoFrame(e) => {
                visit.last_reason = e;
                self.retry(visit)
            }
            VisitEvent::Recentred(Ok(q)) => {
                visit.target = q;
                self.retry(visit)
            }
            VisitEvent::Recentred(Err(why)) => {
                visit.last_reason = format!("{}; {why}", visit.last_reason);
                // The last frame stands: a found (if off-centre) board is a capture.
                if visit.found {
                    VisitAction::Deliver
                } else {
                    VisitAction::Reject(format!(
                        "{} after {} tries",
                        visit.last_reason, visit.attempt
                    ))
                }
            }
            VisitEvent::Seen(view) => self.judge(visit, view, status),
        }
    }

    /// The automatic routine's checks of a still frame, in order: placement
    /// (re-centre), similarity, blur.
    fn judge(&mut self, visit: &mut Visit, view: View, status: &Status<'_>) -> VisitAction {
        let Some(a) = self.auto().copied() else {
            return VisitAction::Deliver;
        };
        let (centre, badly_placed) = match &view.board {
            Ok(b) => {
                let off = ((b.centre_px.x - b.principal_px.x) / f64::from(b.width))
                    .abs()
                    .max(((b.centre_px.y - b.principal_px.y) / f64::from(b.height)).abs());
                (
                    Some(b.centre_in_camera),
                    (off > a.off_centre)
                        .then(|| format!("board off-centre by {:.0}% of the image", off * 100.0)),
                )
            }
            Err(reason) => (
                view.predicted_centre_in_camera,
                Some(format!("board not found ({reason})")),
            ),
        };
        visit.found = view.board.is_ok();
        if let Some(why) = badly_placed {
            visit.last_reason = why;
            if visit.attempt < self.tries()
                && let Some(c) = centre
            {
                return VisitAction::Recentre {
                    centre_in_camera: c,
                };
            }
            return if view.board.is_ok() {
                VisitAction::Deliver
            } else {
                VisitAction::Reject(format!(
                    "{} after {} tries",
                    visit.last_reason, visit.attempt
                ))
            };
        }
        if let Some(k) = status.good_poses.iter().position(|p| {
            let (t, r) = pose_distance(p, &view.base_from_flange);
            t < a.similar_t_m && r < a.similar_r_rad
        }) {
            return VisitAction::Reject(format!("too similar to good capture {}", k + 1));
        }
        if let Some(s) = view.sharpness {
            if self.sharpness.len() >= BLUR_MIN_HISTORY {
                let mut sorted = self.sharpness.clone();
                sorted.sort_by(f64::total_cmp);
                let median = sorted[sorted.len() / 2];
                if s < a.blur_fraction * median {
                    return VisitAction::Reject(format!(
                        "blurred: sharpness {s:.0} < {:.0}% of the median {median:.0}",
                        a.blur_fraction * 100.0
                    ));
                }
            }
            if view.board.is_ok() {
                self.sharpness.push(s);
            }
        }
        VisitAction::Deliver
    }
}
