//! Joint limits: one type for the planner, the IK, the FRI guard, the trajectory
//! generator and the simulated controller.
//!
//! The values of the two arms live in [`crate::catalogue`] (shared/facts.md §2.3):
//! positions ±170/120/170/120/170/120/175° for both models; velocities
//! 98/98/100/130/140/180/180 °/s (iiwa 7 R800) and 85/85/100/75/130/135/135 °/s
//! (iiwa 14 R820). KUKA publishes no acceleration limits in those sources;
//! [`JointLimits::acceleration`] holds a conservative planning default instead
//! ([`crate::catalogue::PLANNING_ACCELERATION`]).

use serde::{Deserialize, Serialize};

use crate::{IiwaModel, Joints, N_JOINTS, RobotError};

/// Position, velocity and acceleration limits of the seven joints (rad, rad/s, rad/s²).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointLimits {
    /// Lower position limits (rad).
    pub position_min: Joints,
    /// Upper position limits (rad).
    pub position_max: Joints,
    /// Velocity limit magnitudes (rad/s).
    pub velocity: Joints,
    /// Acceleration limit magnitudes (rad/s²) used for planning and by the simulated
    /// controller (not a KUKA figure: see the module documentation).
    pub acceleration: Joints,
}

impl JointLimits {
    /// LBR iiwa 7 R800.
    pub fn iiwa7() -> Self {
        IiwaModel::Iiwa7R800.limits()
    }

    /// LBR iiwa 14 R820.
    pub fn iiwa14() -> Self {
        IiwaModel::Iiwa14R820.limits()
    }

    /// The same limits with velocities and accelerations multiplied by `factor` (0, 1].
    pub fn scaled(mut self, factor: f64) -> Result<Self, RobotError> {
        if !(factor.is_finite() && factor > 0.0 && factor <= 1.0) {
            return Err(RobotError::InvalidValue {
                what: "limit scale factor",
                value: factor.to_string(),
            });
        }
        self.velocity = self.velocity.map(|v| v * factor);
        self.acceleration = self.acceleration.map(|a| a * factor);
        Ok(self)
    }

    /// Checks that every limit is finite, positive and ordered.
    pub fn validate(&self) -> Result<(), RobotError> {
        for j in 0..N_JOINTS {
            let (lo, hi) = (self.position_min[j], self.position_max[j]);
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return Err(RobotError::InvalidValue {
                    what: "joint position limits",
                    value: format!("A{}: [{lo}, {hi}]", j + 1),
                });
            }
            for (what, v) in [
                ("joint velocity limit", self.velocity[j]),
                ("joint acceleration limit", self.acceleration[j]),
            ] {
                if !(v.is_finite() && v > 0.0) {
                    return Err(RobotError::InvalidValue {
                        what,
                        value: format!("A{}: {v}", j + 1),
                    });
                }
            }
        }
        Ok(())
    }

    /// Whether `q` lies inside the position limits (boundary included; NaN never does).
    pub fn contains(&self, q: &Joints) -> bool {
        (0..N_JOINTS).all(|i| q[i] >= self.position_min[i] && q[i] <= self.position_max[i])
    }

    /// `q` clamped into the position limits shrunk by `margin` on each side.
    pub fn clamp(&self, q: &Joints, margin: f64) -> Joints {
        std::array::from_fn(|i| {
            q[i].clamp(self.position_min[i] + margin, self.position_max[i] - margin)
        })
    }

    /// Checks position limits shrunk by `margin` rad on each side; a NaN or infinite
    /// value is an error of its own.
    pub fn check_position(&self, q: &Joints, margin: f64) -> Result<(), RobotError> {
        for (j, &v) in q.iter().enumerate() {
            if !v.is_finite() {
                return Err(RobotError::NonFinite {
                    what: "joint command",
                    joint: j,
                });
            }
            let (min, max) = (self.position_min[j] + margin, self.position_max[j] - margin);
            if v < min || v > max {
                return Err(RobotError::JointLimit {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_match_facts() {
        let l = JointLimits::iiwa14();
        assert!((l.position_max[6] - 175f64.to_radians()).abs() < 1e-12);
        assert!((l.position_min[1] + 120f64.to_radians()).abs() < 1e-12);
        assert!((l.velocity[3] - 75f64.to_radians()).abs() < 1e-12);
        assert!((JointLimits::iiwa7().velocity[6] - std::f64::consts::PI).abs() < 1e-12);
    }

    #[test]
    fn both_models_validate_and_scaling_keeps_positions() {
        for l in [JointLimits::iiwa7(), JointLimits::iiwa14()] {
            l.validate().unwrap();
            let half = l.scaled(0.5).unwrap();
            assert_eq!(half.position_min, l.position_min);
            assert_eq!(half.position_max, l.position_max);
            assert!((half.velocity[0] - 0.5 * l.velocity[0]).abs() < 1e-15);
        }
        assert!(JointLimits::iiwa7().scaled(0.0).is_err());
        assert!(JointLimits::iiwa7().scaled(1.5).is_err());
        assert!(JointLimits::iiwa7().scaled(f64::NAN).is_err());
    }

    #[test]
    fn check_position_names_the_joint_and_the_margin() {
        let l = JointLimits::iiwa7();
        let mut q = [0.0; N_JOINTS];
        q[1] = 119f64.to_radians();
        assert!(l.check_position(&q, 0.0).is_ok());
        assert!(matches!(
            l.check_position(&q, 2f64.to_radians()),
            Err(RobotError::JointLimit { joint: 1, .. })
        ));
        q[4] = f64::INFINITY;
        assert!(matches!(
            l.check_position(&q, 0.0),
            Err(RobotError::NonFinite { joint: 4, .. })
        ));
        assert!(!l.contains(&[f64::NAN; N_JOINTS]));
    }
}
