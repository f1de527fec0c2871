//! The ports the live source ([`crate::live::LiveSource`]) drives besides its
//! frames ([`crate::live::FrameSource`]): the arm and the clock.
//!
//! In production the arm is the KUKA FRI client ([`kuka_fri::FriClient`]) and the
//! clock the host's ([`SystemClock`]); tests put a fake arm and a virtual clock
//! behind them, so the live source's decisions (the arm never at rest, a frame
//! that never comes, the session not commanding, the arm moving during the
//! exposure) run in-process without waiting out the real timeouts.
//!
//! The port speaks kuka-fri's types (joint states, session states, its errors):
//! the services are where the FRI client is wired, and the robot model below it
//! knows nothing of FRI.

use std::time::{Duration, Instant};

use b2b_robot::Joints;
use kuka_fri::{FriClient, FriError, JointState, SessionState};

/// What the live source needs of an arm: its measured joints, whether it is
/// still, its session state, and motions (every command checked by the
/// port's safety guard).
pub trait ArmPort {
    /// Waits until the first measured joint state arrives.
    fn wait_for_joints(&self, timeout: Duration) -> Result<JointState, FriError>;
    /// The newest measured joint state.
    fn latest(&self) -> Option<JointState>;
    /// Whether every joint stayed within `tol` rad over the last `window` of
    /// controller time.
    fn is_still(&self, window: Duration, tol: f64) -> bool;
    /// The session state now.
    fn state(&self) -> SessionState;
    /// Waits until the session reports `state`.
    fn wait_for_state(&self, state: SessionState, timeout: Duration) -> Result<(), FriError>;
    /// Moves to `q` and waits until it is reached (or the motion failed).
    fn move_to(&self, q: Joints) -> Result<(), FriError>;
}

impl ArmPort for FriClient {
    fn wait_for_joints(&self, timeout: Duration) -> Result<JointState, FriError> {
        FriClient::wait_for_joints(self, timeout)
    }

    fn latest(&self) -> Option<JointState> {
        FriClient::latest(self)
    }

    fn is_still(&self, window: Duration, tol: f64) -> bool {
        FriClient::is_still(self, window, tol)
    }

    fn state(&self) -> SessionState {
        FriClient::state(self)
    }

    fn wait_for_state(&self, state: SessionState, timeout: Duration) -> Result<(), FriError> {
        FriClient::wait_for_state(self, state, timeout)
    }

    fn move_to(&self, q: Joints) -> Result<(), FriError> {
        FriClient::move_to(self, q)
    }
}

/// The time the live source's waits and timings go through.
pub trait Clock {
    /// Monotonic time (deadlines, durations).
    fn now(&self) -> Instant;
    /// Host time, ns since the Unix epoch (the clock the camera stamps its
    /// exposures with).
    fn now_ns(&self) -> u64;
    /// Lets `d` pass.
    fn sleep(&self, d: Duration);
}

/// The host's clock.
#[derive(Debug, Clone, Copy, Default)]
pub struct SystemClock;

impl Clock for SystemClock {
    fn now(&self) -> Instant {
        Instant::now()
    }

    fn now_ns(&self) -> u64 {
        // The frames' own timebase, so "exposed after" compares like with like.
        b2b_frames::now_ns()
    }

    fn sleep(&self, d: Duration) {
        std::thread::sleep(d);
    }
}
