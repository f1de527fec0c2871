//! The guard every outgoing command passes.
//!
//! # Why the guard sits below the motion planner
//! The trajectory generator already respects the limits, but a planner bug, a NaN, a stale
//! start pose or a packet-loss corner case must not reach the arm. [`SafetyGuard::check`] is
//! therefore applied by the session core to *every* joint-position command immediately
//! before it is encoded, independent of where the command came from.
//!
//! What "safe" means is `b2b_robot`'s [`SafetyEnvelope`]: all values finite; joint
//! positions inside the limits (optionally shrunk by a margin); joint velocities implied by
//! the step from the previously sent command over the controller time between the two
//! (sequence-counter difference × send period) within their limits; the flange position
//! inside a Cartesian box in the robot base frame. The limits, the box and the
//! [`ForwardKinematics`] (an [`b2b_robot::Arm`] in service, any closure
//! `Fn(&[f64; 7]) -> [f64; 3]` in tests) all come from `b2b_robot`; this module adds only
//! what the session needs: one value that owns the predicate and the kinematics, shared
//! with the driver thread.

use std::fmt;
use std::sync::Arc;

use b2b_robot::{ForwardKinematics, JointLimits, Joints, SafetyEnvelope, WorkspaceBox};

use crate::error::Result;

/// Checks each command against joint position and velocity limits and the workspace box.
#[derive(Clone)]
pub struct SafetyGuard {
    envelope: SafetyEnvelope,
    fk: Arc<dyn ForwardKinematics>,
}

impl fmt::Debug for SafetyGuard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SafetyGuard")
            .field("envelope", &self.envelope)
            .finish_non_exhaustive()
    }
}

impl SafetyGuard {
    /// A guard for `limits`, the flange box `workspace` and the kinematics `fk`.
    pub fn new(
        limits: JointLimits,
        workspace: WorkspaceBox,
        fk: impl ForwardKinematics + 'static,
    ) -> Result<Self> {
        Ok(Self {
            envelope: SafetyEnvelope::new(limits, workspace)?,
            fk: Arc::new(fk),
        })
    }

    /// Keeps commands `margin` rad inside each position limit (default 0).
    pub fn with_position_margin(mut self, margin: f64) -> Result<Self> {
        self.envelope = self.envelope.with_position_margin(margin)?;
        Ok(self)
    }

    /// Whether `other` applies the same envelope with the same kinematics (a clone of this
    /// guard, or this guard itself).
    pub fn is_same(&self, other: &SafetyGuard) -> bool {
        self.envelope == other.envelope && Arc::ptr_eq(&self.fk, &other.fk)
    }

    /// The predicate this guard applies.
    pub fn envelope(&self) -> &SafetyEnvelope {
        &self.envelope
    }

    /// The joint limits.
    pub fn limits(&self) -> &JointLimits {
        self.envelope.limits()
    }

    /// The workspace box.
    pub fn workspace(&self) -> &WorkspaceBox {
        self.envelope.workspace()
    }

    /// The position margin (rad).
    pub fn position_margin(&self) -> f64 {
        self.envelope.position_margin()
    }

    /// Flange position of `q` from the guard's kinematics.
    pub fn flange_position(&self, q: &Joints) -> [f64; 3] {
        self.fk.flange_position(q)
    }

    /// Checks a pose without a previous command: finite, within position limits, in the box.
    pub fn check_pose(&self, q: &Joints) -> Result<()> {
        Ok(self.envelope.check_pose(q, self.fk.as_ref())?)
    }

    /// Checks command `q` that follows `previous` after `dt` seconds of controller time.
    ///
    /// With `previous = None` (first command of a commanding phase) only the pose is checked.
    pub fn check(&self, previous: Option<&Joints>, q: &Joints, dt: f64) -> Result<()> {
        Ok(self
            .envelope
            .check_step(previous, q, dt, self.fk.as_ref())?)
    }
}

#[cfg(test)]
mod tests {
    use b2b_robot::RobotError;

    use super::*;
    use crate::FriError;

    fn guard() -> SafetyGuard {
        let fk = |q: &Joints| [q[0], q[1], 1.0];
        SafetyGuard::new(
            JointLimits::iiwa7(),
            WorkspaceBox::new([-0.5, -0.5, 0.0], [0.5, 0.5, 2.0]).unwrap(),
            fk,
        )
        .unwrap()
    }

    #[test]
    fn guard_rejects_each_kind_of_violation() {
        let g = guard();
        let zero = [0.0; 7];
        assert!(g.check(None, &zero, 0.005).is_ok());
        let mut q = zero;
        q[3] = 2.2;
        assert!(matches!(
            g.check(None, &q, 0.005),
            Err(FriError::Robot(RobotError::JointLimit { joint: 3, .. }))
        ));
        let mut q = zero;
        q[2] = 0.1; // 20 rad/s over 5 ms
        assert!(matches!(
            g.check(Some(&zero), &q, 0.005),
            Err(FriError::Robot(RobotError::VelocityLimit { joint: 2, .. }))
        ));
        let mut q = zero;
        q[0] = 0.6;
        assert!(matches!(
            g.check(None, &q, 0.005),
            Err(FriError::Robot(RobotError::Workspace { .. }))
        ));
        let mut q = zero;
        q[5] = f64::NAN;
        assert!(matches!(
            g.check(None, &q, 0.005),
            Err(FriError::Robot(RobotError::NonFinite { joint: 5, .. }))
        ));
    }

    #[test]
    fn nan_kinematics_is_outside() {
        let g = SafetyGuard::new(
            JointLimits::iiwa7(),
            WorkspaceBox::unbounded(),
            |_: &Joints| [f64::NAN; 3],
        )
        .unwrap();
        assert!(matches!(
            g.check_pose(&[0.0; 7]),
            Err(FriError::Robot(RobotError::Workspace { .. }))
        ));
    }

    #[test]
    fn guard_with_an_arm_uses_its_forward_kinematics() {
        let arm = b2b_robot::Arm::new(b2b_robot::IiwaModel::Iiwa7R800);
        let q = b2b_robot::Arm::comfortable();
        let t = arm.fk(&q).translation.vector;
        let g = SafetyGuard::new(arm.limits, WorkspaceBox::unbounded(), arm).unwrap();
        assert_eq!(g.flange_position(&q), [t.x, t.y, t.z]);
    }
}
