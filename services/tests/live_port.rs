//! The live source's decisions on a fake arm, fake frames and a virtual clock
//! (issue 38): the arm never at rest, a frame that never comes, the session not
//! commanding, a motion aborted, the arm moving during the exposure. Virtual time
//! passes only through the source's sleeps and the fakes' waits, so a 10 s settle
//! timeout is waited out at once; no wall-clock duration is asserted.

use std::cell::{Cell, RefCell};
use std::path::Path;
use std::rc::Rc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use b2b_calib::camera::CameraModel;
use b2b_live::{
    ArmPort, Clock, FrameSource, LiveConfig, LiveError, LiveFrame, LiveSource, WatchObserve,
};
use b2b_live::{CaptureSource, Progress};
use b2b_robot::{Arm, Joints};
use b2b_routine::Mode;
use b2b_routine::plan::PlanConfig;
use b2b_services::setup::CellSetup;
use kuka_fri::{ControllerTime, FriError, JointState, SessionState};

#[path = "common/virtual_clock.rs"]
mod virtual_clock;
use virtual_clock::{EPOCH_NS, VirtualClock};

/// When the fake arm is at rest: from a virtual time on, or never.
type RestFrom = Rc<Cell<Option<Duration>>>;

/// An arm standing at a comfortable pose, its session, its motions and its
/// stillness as the test says.
#[derive(Debug)]
struct FakeArm {
    clock: VirtualClock,
    q: Cell<Joints>,
    /// Measured joints arrive.
    joints: bool,
    rest_from: RestFrom,
    /// The session state now; it never changes by itself.
    state: SessionState,
    /// Motions are aborted with this reason.
    abort: Option<String>,
    moves: RefCell<Vec<Joints>>,
    stillness_asked: Cell<usize>,
}

impl FakeArm {
    fn new(clock: &VirtualClock) -> Self {
        FakeArm {
            clock: clock.clone(),
            q: Cell::new(Arm::comfortable()),
            joints: true,
            rest_from: Rc::new(Cell::new(Some(Duration::ZERO))),
            state: SessionState::CommandingActive,
            abort: None,
            moves: RefCell::default(),
            stillness_asked: Cell::new(0),
        }
    }
}

impl ArmPort for FakeArm {
    fn wait_for_joints(&self, timeout: Duration) -> Result<JointState, FriError> {
        match self.latest() {
            Some(js) => Ok(js),
            None => {
                self.clock.sleep(timeout);
                Err(FriError::Timeout {
                    what: "measured joints",
                    waited: timeout,
                })
            }
        }
    }

    fn latest(&self) -> Option<JointState> {
        self.joints.then(|| JointState {
            q: self.q.get(),
            timestamp: ControllerTime::from_duration(Duration::from_nanos(self.clock.now_ns())),
            received_at: self.clock.now(),
        })
    }

    fn is_still(&self, _window: Duration, _tol: f64) -> bool {
        self.stillness_asked.set(self.stillness_asked.get() + 1);
        self.rest_from
            .get()
            .is_some_and(|t| self.clock.elapsed() >= t)
    }

    fn state(&self) -> SessionState {
        self.state
    }

    fn wait_for_state(&self, state: SessionState, timeout: Duration) -> Result<(), FriError> {
        if self.state == state {
            return Ok(());
        }
        self.clock.sleep(timeout);
        Err(FriError::Timeout {
            what: "session state",
            waited: timeout,
        })
    }

    fn move_to(&self, q: Joints) -> Result<(), FriError> {
        if self.state != SessionState::CommandingActive {
            return Err(FriError::NotCommanding { state: self.state });
        }
        self.moves.borrow_mut().push(q);
        if let Some(reason) = &self.abort {
            return Err(FriError::MotionAborted {
                reason: reason.clone(),
            });
        }
        self.clock.sleep(Duration::from_secs(2));
        self.q.set(q);
        Ok(())
    }
}

/// A camera whose frames come at once, exposed when asked for, or never.
#[derive(Debug)]
struct FakeFrames {
    clock: VirtualClock,
    /// Frames come.
    comes: bool,
    /// The arm is pushed during each exposure: never at rest again.
    push: Option<RestFrom>,
    /// The `after_ns` of every request.
    asked: Rc<RefCell<Vec<u64>>>,
    number: u64,
}

impl FakeFrames {
    fn new(clock: &VirtualClock) -> Self {
        FakeFrames {
            clock: clock.clone(),
            comes: true,
            push: None,
            asked: Rc::default(),
            number: 0,
        }
    }
}

impl FrameSource for FakeFrames {
    fn frame_after(&mut self, after_ns: u64, timeout: Duration) -> b2b_live::Result<LiveFrame> {
        self.asked.borrow_mut().push(after_ns);
        if !self.comes {
            self.clock.sleep(timeout);
            return Err(LiveError::NoFrameInTime {
                waited: timeout,
                service: "fake/robot1/colour".into(),
            });
        }
        self.clock.sleep(Duration::from_millis(33));
        if let Some(rest_from) = &self.push {
            rest_from.set(None);
        }
        self.number += 1;
        let camera = CameraModel::new(640, 480, [615.2, 614.8, 321.4, 238.7], &[]).unwrap();
        Ok(LiveFrame {
            number: self.number,
            timestamp_ns: after_ns.max(self.clock.now_ns()),
            grey: vec![0; (camera.width * camera.height) as usize],
            camera,
            intrinsics_given: true,
            depth: None,
        })
    }

    fn newest_after(&mut self, after_ns: u64, timeout: Duration) -> b2b_live::Result<LiveFrame> {
        self.frame_after(after_ns, timeout)
    }

    fn dropped(&self) -> u64 {
        0
    }
}

/// The settle timeout of the agent's live sources (`setup::live_source`).
const SETTLE: Duration = Duration::from_secs(10);

/// A live source of the committed checkerboard scene's robot1 (its setup as the
/// simulated cart derives it) on `arm`, `frames` and `clock`, visiting the
/// planned viewpoints (`agent run`).
fn source(
    arm: FakeArm,
    frames: FakeFrames,
    clock: &VirtualClock,
) -> b2b_live::Result<LiveSource<FakeArm, VirtualClock>> {
    let setup = CellSetup::load(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/fixtures/setup-robot1.json"),
    )
    .unwrap();
    let cfg = LiveConfig {
        robot: "robot1".into(),
        mode: Mode::Program,
        plan: PlanConfig {
            count: 4,
            ..PlanConfig::default()
        },
        board_approx: setup
            .base_from_target_approx
            .to_isometry("T_base_target_approx")
            .unwrap(),
        mount_approx: setup
            .flange_from_camera_approx
            .to_isometry("T_flange_camera_approx")
            .unwrap(),
        still_window: Duration::from_millis(250),
        still_tol_rad: 2e-4,
        settle_timeout: SETTLE,
        frame_timeout: Duration::from_secs(20),
        features: None,
    };
    LiveSource::connect_with_clock(
        cfg,
        arm,
        clock.clone(),
        Box::new(frames),
        Arm::new(setup.model),
        setup.guard().unwrap(),
        setup.read_target().unwrap(),
    )
}

fn next(
    source: &mut LiveSource<FakeArm, VirtualClock>,
) -> b2b_live::Result<Option<b2b_live::SourceCapture>> {
    source.next(&Progress::default(), &AtomicBool::new(false))
}

fn watch(source: &mut LiveSource<FakeArm, VirtualClock>) -> b2b_live::Result<()> {
    source.watch(
        Duration::from_millis(200),
        WatchObserve::Target,
        &AtomicBool::new(false),
        &mut |_| panic!("no frame is delivered"),
    )
}

#[test]
fn an_arm_without_joint_states_is_not_connected() {
    let clock = VirtualClock::new();
    let arm = FakeArm {
        joints: false,
        ..FakeArm::new(&clock)
    };
    let r = source(arm, FakeFrames::new(&clock), &clock);
    assert!(
        matches!(r, Err(LiveError::NoJointState { source: Some(_) })),
        "{r:?}"
    );
}

#[test]
fn an_arm_never_at_rest_is_not_at_rest_after_the_settle_timeout() {
    let clock = VirtualClock::new();
    let arm = FakeArm::new(&clock);
    arm.rest_from.set(None);
    let frames = FakeFrames::new(&clock);
    let asked = frames.asked.clone();
    let mut source = source(arm, frames, &clock).unwrap();
    let r = next(&mut source);
    assert!(
        matches!(r, Err(LiveError::NotAtRest { waited }) if waited == SETTLE),
        "{r:?}"
    );
    // The settle timeout passed on the virtual clock, polled every 10 ms; no
    // frame was asked for.
    assert!(clock.elapsed() >= SETTLE, "{:?}", clock.elapsed());
    assert!(clock.elapsed() < SETTLE + Duration::from_millis(20));
    assert!(asked.borrow().is_empty());
    assert!(source.into_arm().stillness_asked.get() > 900);
}

#[test]
fn the_frame_is_the_first_exposed_after_the_arm_came_to_rest() {
    let clock = VirtualClock::new();
    let arm = FakeArm::new(&clock);
    arm.rest_from.set(Some(Duration::from_secs(3)));
    let frames = FakeFrames::new(&clock);
    let asked = frames.asked.clone();
    let mut source = source(arm, frames, &clock).unwrap();
    // The plan's frame: the arm found still at 3 s (virtual), frames from then on.
    let capture = next(&mut source).unwrap().unwrap();
    assert_eq!(asked.borrow()[0], EPOCH_NS + 3_000_000_000);
    // Then the first viewpoint: moved there, still, a frame exposed after the
    // move (no board in a black frame: rejected with the reason).
    assert_eq!(source.into_arm().moves.borrow().len(), 1);
    assert!(asked.borrow()[1] > asked.borrow()[0]);
    assert!(capture.observed.is_err());
}

#[test]
fn a_frame_that_never_comes_is_the_frame_timeout() {
    let clock = VirtualClock::new();
    let frames = FakeFrames {
        comes: false,
        ..FakeFrames::new(&clock)
    };
    let asked = frames.asked.clone();
    let mut source = source(FakeArm::new(&clock), frames, &clock).unwrap();
    let r = next(&mut source);
    assert!(
        matches!(&r, Err(LiveError::NoFrameInTime { waited, .. }) if *waited == Duration::from_secs(20)),
        "{r:?}"
    );
    assert_eq!(asked.borrow().len(), 1);
}

#[test]
fn the_arm_moving_during_the_exposure_is_refused() {
    let clock = VirtualClock::new();
    let arm = FakeArm::new(&clock);
    let frames = FakeFrames {
        push: Some(arm.rest_from.clone()),
        ..FakeFrames::new(&clock)
    };
    let mut source = source(arm, frames, &clock).unwrap();
    let r = next(&mut source);
    assert!(
        matches!(r, Err(LiveError::MovedDuringExposure { frame: 1 })),
        "{r:?}"
    );
}

#[test]
fn a_session_not_commanding_stops_the_watch_with_its_error() {
    let clock = VirtualClock::new();
    let arm = FakeArm {
        state: SessionState::MonitoringReady,
        ..FakeArm::new(&clock)
    };
    let mut source = source(arm, FakeFrames::new(&clock), &clock).unwrap();
    let r = watch(&mut source);
    assert!(
        matches!(&r, Err(LiveError::NotCommanding(e)) if matches!(**e, FriError::Timeout { .. })),
        "{r:?}"
    );
    assert!(source.into_arm().moves.borrow().is_empty());
}

#[test]
fn an_aborted_motion_stops_the_watch_with_its_error() {
    let clock = VirtualClock::new();
    let arm = FakeArm {
        abort: Some("connection lost".into()),
        ..FakeArm::new(&clock)
    };
    let mut source = source(arm, FakeFrames::new(&clock), &clock).unwrap();
    let r = watch(&mut source);
    assert!(
        matches!(&r, Err(LiveError::Fri(e)) if matches!(&**e, FriError::MotionAborted { reason } if reason == "connection lost")),
        "{r:?}"
    );
    // The watch moved once, to its pose: the first planned viewpoint.
    let planned = source.plan().unwrap().viewpoints[0].q;
    assert_eq!(source.into_arm().moves.borrow().as_slice(), [planned]);
}
