//! Joint and workspace limits, and the guard every outgoing command passes.
//!
//! # Why the guard sits below the motion planner
//! The trajectory generator already respects the limits, but a planner bug, a NaN, a stale
//! start pose or a packet-loss corner case must not reach the arm. [`SafetyGuard::check`] is
//! therefore applied by the session core to *every* joint-position command immediately
//! before it is encoded, independent of where the command came from. It checks:
//! 1. all values finite;
//! 2. joint position limits (optionally shrunk by a margin);
//! 3. joint velocity implied by the step from the previously sent command over the
//!    controller time between the two (sequence-counter difference × send period);
//! 4. the flange position, from a caller-supplied forward-kinematics function, inside a
//!    Cartesian box in the robot base frame.
//!
//! Kinematics are deliberately not implemented here: the caller passes anything that
//! implements [`ForwardKinematics`] (a closure `Fn(&[f64; 7]) -> [f64; 3]` does).
//!
//! Limits come from shared/facts.md §2.3: positions ±170/120/170/120/170/120/175° for both
//! models; velocities 98/98/100/130/140/180/180 °/s (iiwa 7 R800) and
//! 85/85/100/75/130/135/135 °/s (iiwa 14 R820). KUKA publishes no acceleration limits in
//! those sources; [`JointLimits::acceleration`] is this crate's conservative default.

use std::fmt;
use std::sync::Arc;

use crate::error::{FriError, Result};
use crate::messages::NUM_JOINTS;

/// A joint vector.
pub type Joints = [f64; NUM_JOINTS];

fn deg(v: [f64; NUM_JOINTS]) -> Joints {
    v.map(f64::to_radians)
}

/// Position, velocity and acceleration limits of the seven joints (rad, rad/s, rad/s²).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointLimits {
    /// Lower position limits (rad).
    pub position_min: Joints,
    /// Upper position limits (rad).
    pub position_max: Joints,
    /// Velocity limit magnitudes (rad/s).
    pub velocity: Joints,
    /// Acceleration limit magnitudes (rad/s²) used for planning and by the simulator.
    pub acceleration: Joints,
}

const POSITION_DEG: [f64; NUM_JOINTS] = [170.0, 120.0, 170.0, 120.0, 170.0, 120.0, 175.0];
/// Default planning acceleration (rad/s²): gentle, as for moving a camera around a patient.
const DEFAULT_ACCELERATION: f64 = 2.0;

impl JointLimits {
    fn with_velocity_deg(v: [f64; NUM_JOINTS]) -> Self {
        let max = deg(POSITION_DEG);
        Self {
            position_min: max.map(|m| -m),
            position_max: max,
            velocity: deg(v),
            acceleration: [DEFAULT_ACCELERATION; NUM_JOINTS],
        }
    }

    /// LBR iiwa 7 R800.
    pub fn iiwa7() -> Self {
        Self::with_velocity_deg([98.0, 98.0, 100.0, 130.0, 140.0, 180.0, 180.0])
    }

    /// LBR iiwa 14 R820.
    pub fn iiwa14() -> Self {
        Self::with_velocity_deg([85.0, 85.0, 100.0, 75.0, 130.0, 135.0, 135.0])
    }

    /// The same limits with velocities and accelerations multiplied by `factor` (0, 1].
    pub fn scaled(mut self, factor: f64) -> Result<Self> {
        if !(factor.is_finite() && factor > 0.0 && factor <= 1.0) {
            return Err(FriError::InvalidValue {
                what: "limit scale factor",
                value: factor.to_string(),
            });
        }
        self.velocity = self.velocity.map(|v| v * factor);
        self.acceleration = self.acceleration.map(|a| a * factor);
        Ok(self)
    }

    /// Checks that every limit is finite, positive and ordered.
    pub fn validate(&self) -> Result<()> {
        for j in 0..NUM_JOINTS {
            let (lo, hi) = (self.position_min[j], self.position_max[j]);
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return Err(FriError::InvalidValue {
                    what: "joint position limits",
                    value: format!("A{}: [{lo}, {hi}]", j + 1),
                });
            }
            for (what, v) in [
                ("joint velocity limit", self.velocity[j]),
                ("joint acceleration limit", self.acceleration[j]),
            ] {
                if !(v.is_finite() && v > 0.0) {
                    return Err(FriError::InvalidValue {
                        what,
                        value: format!("A{}: {v}", j + 1),
                    });
                }
            }
        }
        Ok(())
    }

    /// Checks position limits shrunk by `margin` rad on each side.
    pub fn check_position(&self, q: &Joints, margin: f64) -> Result<()> {
        for (j, &v) in q.iter().enumerate() {
            if !v.is_finite() {
                return Err(FriError::NonFinite {
                    what: "joint command",
                    joint: j,
                });
            }
            let (min, max) = (self.position_min[j] + margin, self.position_max[j] - margin);
            if v < min || v > max {
                return Err(FriError::JointLimit {
                    joint: j,
                    value: v,
                    min,
                    max,
                });
            }
        }
        Ok(())
    }
}

/// An axis-aligned box in the robot base frame (m) that the flange must stay in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorkspaceBox {
    /// Lower corner (m).
    pub min: [f64; 3],
    /// Upper corner (m).
    pub max: [f64; 3],
}

impl WorkspaceBox {
    /// A box from two corners; rejects non-finite or empty boxes.
    pub fn new(min: [f64; 3], max: [f64; 3]) -> Result<Self> {
        for k in 0..3 {
            if !(min[k].is_finite() && max[k].is_finite() && min[k] < max[k]) {
                return Err(FriError::InvalidValue {
                    what: "workspace box",
                    value: format!("axis {k}: [{}, {}]", min[k], max[k]),
                });
            }
        }
        Ok(Self { min, max })
    }

    /// A box that contains every reachable point (no Cartesian restriction).
    pub fn unbounded() -> Self {
        Self {
            min: [f64::NEG_INFINITY; 3],
            max: [f64::INFINITY; 3],
        }
    }

    /// Whether `p_in_base` lies inside (boundary included). NaN is never inside.
    pub fn contains(&self, p_in_base: &[f64; 3]) -> bool {
        (0..3).all(|k| p_in_base[k] >= self.min[k] && p_in_base[k] <= self.max[k])
    }
}

/// Forward kinematics to the flange origin, supplied by the caller (m, robot base frame).
pub trait ForwardKinematics: Send + Sync {
    /// Flange position for joint positions `q` (rad).
    fn flange_position(&self, q: &Joints) -> [f64; 3];
}

impl<F> ForwardKinematics for F
where
    F: Fn(&Joints) -> [f64; 3] + Send + Sync,
{
    fn flange_position(&self, q: &Joints) -> [f64; 3] {
        self(q)
    }
}

/// Relative tolerance on velocity checks, to absorb rounding in sampled trajectories.
const VELOCITY_TOLERANCE: f64 = 1e-9;

/// Checks each command against joint position and velocity limits and the workspace box.
#[derive(Clone)]
pub struct SafetyGuard {
    limits: JointLimits,
    workspace: WorkspaceBox,
    fk: Arc<dyn ForwardKinematics>,
    position_margin: f64,
}

impl fmt::Debug for SafetyGuard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SafetyGuard")
            .field("limits", &self.limits)
            .field("workspace", &self.workspace)
            .field("position_margin", &self.position_margin)
            .finish_non_exhaustive()
    }
}

impl SafetyGuard {
    /// A guard for `limits`, the flange box `workspace` and the caller's kinematics.
    pub fn new(
        limits: JointLimits,
        workspace: WorkspaceBox,
        fk: impl ForwardKinematics + 'static,
    ) -> Result<Self> {
        limits.validate()?;
        Ok(Self {
            limits,
            workspace,
            fk: Arc::new(fk),
            position_margin: 0.0,
        })
    }

    /// Keeps commands `margin` rad inside each position limit (default 0).
    pub fn with_position_margin(mut self, margin: f64) -> Result<Self> {
        if !(margin.is_finite() && margin >= 0.0) {
            return Err(FriError::InvalidValue {
                what: "position margin",
                value: margin.to_string(),
            });
        }
        self.position_margin = margin;
        Ok(self)
    }

    /// The joint limits.
    pub fn limits(&self) -> &JointLimits {
        &self.limits
    }

    /// The workspace box.
    pub fn workspace(&self) -> &WorkspaceBox {
        &self.workspace
    }

    /// The position margin (rad).
    pub fn position_margin(&self) -> f64 {
        self.position_margin
    }

    /// Flange position of `q` from the caller's kinematics.
    pub fn flange_position(&self, q: &Joints) -> [f64; 3] {
        self.fk.flange_position(q)
    }

    /// Checks a pose without a previous command: finite, within position limits, in the box.
    pub fn check_pose(&self, q: &Joints) -> Result<()> {
        self.limits.check_position(q, self.position_margin)?;
        let p = self.fk.flange_position(q);
        if !self.workspace.contains(&p) {
            return Err(FriError::Workspace { position: p });
        }
        Ok(())
    }

    /// Checks command `q` that follows `previous` after `dt` seconds of controller time.
    ///
    /// With `previous = None` (first command of a commanding phase) only the pose is checked.
    pub fn check(&self, previous: Option<&Joints>, q: &Joints, dt: f64) -> Result<()> {
        self.limits.check_position(q, self.position_margin)?;
        if let Some(prev) = previous {
            if !(dt.is_finite() && dt > 0.0) {
                return Err(FriError::InvalidValue {
                    what: "command interval",
                    value: format!("{dt} s"),
                });
            }
            for j in 0..NUM_JOINTS {
                let velocity = (q[j] - prev[j]).abs() / dt;
                let limit = self.limits.velocity[j];
                // Written so that a NaN velocity fails too.
                if velocity.is_nan() || velocity > limit * (1.0 + VELOCITY_TOLERANCE) {
                    return Err(FriError::VelocityLimit {
                        joint: j,
                        velocity,
                        limit,
                    });
                }
            }
        }
        let p = self.fk.flange_position(q);
        if !self.workspace.contains(&p) {
            return Err(FriError::Workspace { position: p });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn limits_match_facts() {
        let l = JointLimits::iiwa14();
        assert!((l.position_max[6] - 175f64.to_radians()).abs() < 1e-12);
        assert!((l.position_min[1] + 120f64.to_radians()).abs() < 1e-12);
        assert!((l.velocity[3] - 75f64.to_radians()).abs() < 1e-12);
        assert!((JointLimits::iiwa7().velocity[6] - std::f64::consts::PI).abs() < 1e-12);
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
            Err(FriError::JointLimit { joint: 3, .. })
        ));
        let mut q = zero;
        q[2] = 0.1; // 20 rad/s over 5 ms
        assert!(matches!(
            g.check(Some(&zero), &q, 0.005),
            Err(FriError::VelocityLimit { joint: 2, .. })
        ));
        let mut q = zero;
        q[0] = 0.6;
        assert!(matches!(
            g.check(None, &q, 0.005),
            Err(FriError::Workspace { .. })
        ));
        let mut q = zero;
        q[5] = f64::NAN;
        assert!(matches!(
            g.check(None, &q, 0.005),
            Err(FriError::NonFinite { joint: 5, .. })
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
            Err(FriError::Workspace { .. })
        ));
    }
}
