//! The safety predicate: which joint commands may be sent to the arm.
//!
//! A command `q` is safe when
//! 1. all its values are finite;
//! 2. it lies inside the joint position limits, shrunk by a margin;
//! 3. the step from the previously sent command, over the controller time between the
//!    two, implies no joint velocity above its limit;
//! 4. the flange position, by forward kinematics, lies inside a Cartesian box in the
//!    robot base frame ([`WorkspaceBox`]).
//!
//! [`SafetyEnvelope`] is that predicate, with no state and no clock: the FRI session
//! applies it (through kuka-fri's `SafetyGuard`) to *every* command immediately before
//! it is encoded, and the planner uses the same one to keep viewpoints and legs inside
//! it. The kinematics are a parameter ([`ForwardKinematics`]): an [`Arm`] in service,
//! anything smooth in tests that want to probe the box's edges.

use crate::{Arm, JointLimits, Joints, N_JOINTS, RobotError};

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
    pub fn new(min: [f64; 3], max: [f64; 3]) -> Result<Self, RobotError> {
        for k in 0..3 {
            if !(min[k].is_finite() && max[k].is_finite() && min[k] < max[k]) {
                return Err(RobotError::InvalidValue {
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

/// Forward kinematics to the flange origin (m, robot base frame). An [`Arm`] is one; so
/// is a closure `Fn(&Joints) -> [f64; 3]`.
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

/// Non-finite joints give a NaN position, outside every box (as [`Arm::fk`] does
/// too, without computing the chain).
impl ForwardKinematics for Arm {
    fn flange_position(&self, q: &Joints) -> [f64; 3] {
        if !q.iter().all(|v| v.is_finite()) {
            return [f64::NAN; 3];
        }
        let t = self.fk(q).translation.vector;
        [t.x, t.y, t.z]
    }
}

/// Relative tolerance on velocity checks, to absorb rounding in sampled trajectories.
const VELOCITY_TOLERANCE: f64 = 1e-9;

/// The set of safe commands: joint limits (positions with a margin, velocities) and the
/// flange's workspace box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SafetyEnvelope {
    limits: JointLimits,
    workspace: WorkspaceBox,
    position_margin: f64,
}

impl SafetyEnvelope {
    /// An envelope for `limits` (validated) and the flange box `workspace`, no margin.
    pub fn new(limits: JointLimits, workspace: WorkspaceBox) -> Result<Self, RobotError> {
        limits.validate()?;
        Ok(Self {
            limits,
            workspace,
            position_margin: 0.0,
        })
    }

    /// Keeps commands `margin` rad inside each position limit (default 0).
    pub fn with_position_margin(mut self, margin: f64) -> Result<Self, RobotError> {
        if !(margin.is_finite() && margin >= 0.0) {
            return Err(RobotError::InvalidValue {
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

    /// Checks a pose on its own: finite, within the position limits (with the margin),
    /// flange in the box.
    pub fn check_pose<K>(&self, q: &Joints, fk: &K) -> Result<(), RobotError>
    where
        K: ForwardKinematics + ?Sized,
    {
        self.limits.check_position(q, self.position_margin)?;
        self.check_flange(q, fk)
    }

    /// Checks command `q` that follows `previous` after `dt` seconds of controller time.
    ///
    /// With `previous = None` (first command of a commanding phase) only the pose is
    /// checked.
    pub fn check_step<K>(
        &self,
        previous: Option<&Joints>,
        q: &Joints,
        dt: f64,
        fk: &K,
    ) -> Result<(), RobotError>
    where
        K: ForwardKinematics + ?Sized,
    {
        self.limits.check_position(q, self.position_margin)?;
        if let Some(prev) = previous {
            if !(dt.is_finite() && dt > 0.0) {
                return Err(RobotError::InvalidValue {
                    what: "command interval",
                    value: format!("{dt} s"),
                });
            }
            for j in 0..N_JOINTS {
                let velocity = (q[j] - prev[j]).abs() / dt;
                let limit = self.limits.velocity[j];
                // Written so that a NaN velocity fails too.
                if velocity.is_nan() || velocity > limit * (1.0 + VELOCITY_TOLERANCE) {
                    return Err(RobotError::VelocityLimit {
                        joint: j,
                        velocity,
                        limit,
                    });
                }
            }
        }
        self.check_flange(q, fk)
    }

    fn check_flange<K>(&self, q: &Joints, fk: &K) -> Result<(), RobotError>
    where
        K: ForwardKinematics + ?Sized,
    {
        let p = fk.flange_position(q);
        if !self.workspace.contains(&p) {
            return Err(RobotError::Workspace { position: p });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;
    use crate::IiwaModel;

    fn toy_fk(q: &Joints) -> [f64; 3] {
        [q[0], q[1], 1.0]
    }

    fn envelope() -> SafetyEnvelope {
        SafetyEnvelope::new(
            JointLimits::iiwa7(),
            WorkspaceBox::new([-0.5, -0.5, 0.0], [0.5, 0.5, 2.0]).unwrap(),
        )
        .unwrap()
    }

    #[test]
    fn envelope_rejects_each_kind_of_violation() {
        let e = envelope();
        let fk = toy_fk;
        let zero = [0.0; 7];
        assert!(e.check_step(None, &zero, 0.005, &fk).is_ok());
        let mut q = zero;
        q[3] = 2.2;
        assert!(matches!(
            e.check_step(None, &q, 0.005, &fk),
            Err(RobotError::JointLimit { joint: 3, .. })
        ));
        let mut q = zero;
        q[2] = 0.1; // 20 rad/s over 5 ms
        assert!(matches!(
            e.check_step(Some(&zero), &q, 0.005, &fk),
            Err(RobotError::VelocityLimit { joint: 2, .. })
        ));
        let mut q = zero;
        q[0] = 0.6;
        assert!(matches!(
            e.check_step(None, &q, 0.005, &fk),
            Err(RobotError::Workspace { .. })
        ));
        let mut q = zero;
        q[5] = f64::NAN;
        assert!(matches!(
            e.check_step(None, &q, 0.005, &fk),
            Err(RobotError::NonFinite { joint: 5, .. })
        ));
    }

    #[test]
    fn nan_kinematics_is_outside() {
        let e = SafetyEnvelope::new(JointLimits::iiwa7(), WorkspaceBox::unbounded()).unwrap();
        let fk = |_: &Joints| [f64::NAN; 3];
        assert!(matches!(
            e.check_pose(&[0.0; 7], &fk),
            Err(RobotError::Workspace { .. })
        ));
    }

    #[test]
    fn the_margin_shrinks_the_position_limits() {
        let e = envelope().with_position_margin(0.1).unwrap();
        let mut q = [0.0; 7];
        q[6] = 175f64.to_radians() - 0.05;
        assert!(envelope().check_pose(&q, &toy_fk).is_ok());
        assert!(matches!(
            e.check_pose(&q, &toy_fk),
            Err(RobotError::JointLimit { joint: 6, .. })
        ));
        assert!(envelope().with_position_margin(-0.1).is_err());
        assert!(envelope().with_position_margin(f64::NAN).is_err());
    }

    #[test]
    fn an_arm_is_its_own_forward_kinematics() {
        let arm = Arm::new(IiwaModel::Iiwa14R820);
        let q = Arm::comfortable();
        let t = arm.fk(&q).translation.vector;
        assert_eq!(arm.flange_position(&q), [t.x, t.y, t.z]);
        let mut nan = q;
        nan[3] = f64::NAN;
        assert!(arm.flange_position(&nan).iter().all(|v| v.is_nan()));
        let e = SafetyEnvelope::new(
            arm.limits,
            WorkspaceBox::new([t.x - 0.01, -1.0, 0.0], [t.x + 0.01, 1.0, 2.0]).unwrap(),
        )
        .unwrap();
        assert!(e.check_pose(&q, &arm).is_ok());
        let mut moved = q;
        moved[0] += 0.5; // swings the flange sideways, out of the thin box in x
        assert!(matches!(
            e.check_pose(&moved, &arm),
            Err(RobotError::Workspace { .. })
        ));
    }

    /// Joint values around the limits of `model`: each joint a fraction in [-1.15, 1.15]
    /// of its limit (about half the vectors inside all seven), sometimes NaN or infinite.
    fn joints_around_limits(model: IiwaModel) -> impl Strategy<Value = Joints> {
        let max = model.limits().position_max;
        proptest::array::uniform7(prop_oneof![
            30 => -1.15f64..1.15,
            1 => Just(f64::NAN),
            1 => Just(f64::INFINITY),
        ])
        .prop_map(move |u| std::array::from_fn(|j| u[j] * max[j]))
    }

    proptest! {
        #![proptest_config(ProptestConfig {
            cases: 2000,
            max_shrink_iters: 1024,
            ..ProptestConfig::default()
        })]

        /// The predicate is exactly its four conditions, computed here independently of
        /// the envelope's code: a check that is dropped, loosened or tightened fails.
        #[test]
        fn check_step_is_exactly_finite_limits_velocity_and_box(
            fourteen in any::<bool>(),
            q in joints_around_limits(IiwaModel::Iiwa7R800),
            step in proptest::array::uniform7(-0.03f64..0.03),
            with_previous in any::<bool>(),
            dt in 0.001f64..0.02,
            margin in prop_oneof![Just(0.0), 0.0f64..0.3],
            centre in proptest::array::uniform3(-0.8f64..0.8),
            half in proptest::array::uniform3(0.1f64..1.2),
        ) {
            let model = if fourteen { IiwaModel::Iiwa14R820 } else { IiwaModel::Iiwa7R800 };
            let arm = Arm::new(model);
            let (min, max) = (
                std::array::from_fn(|k| centre[k] - half[k]),
                std::array::from_fn(|k| centre[k] + half[k] + 0.5),
            );
            let workspace = WorkspaceBox::new(min, max).unwrap();
            let envelope = SafetyEnvelope::new(arm.limits, workspace)
                .unwrap()
                .with_position_margin(margin)
                .unwrap();
            let previous: Option<Joints> =
                with_previous.then(|| std::array::from_fn(|j| q[j] - step[j]));

            let limits = model.limits();
            let finite = q.iter().all(|v| v.is_finite());
            let inside_limits = (0..N_JOINTS).all(|j| {
                limits.position_min[j] + margin <= q[j] && q[j] <= limits.position_max[j] - margin
            });
            let slow = previous.is_none_or(|p| {
                (0..N_JOINTS).all(|j| (q[j] - p[j]).abs() <= limits.velocity[j] * dt * (1.0 + 1e-9))
            });
            // (FK only of finite joints: nalgebra's rotation-matrix-to-quaternion
            // iteration does not end on NaN.)
            let in_box = finite && {
                let flange = arm.fk(&q).translation.vector;
                (0..3).all(|k| min[k] <= flange[k] && flange[k] <= max[k])
            };
            let expected = finite && inside_limits && slow && in_box;

            let got = envelope.check_step(previous.as_ref(), &q, dt, &arm);
            prop_assert_eq!(got.is_ok(), expected, "{:?}", got);
            if previous.is_none() {
                prop_assert_eq!(envelope.check_pose(&q, &arm).is_ok(), expected);
            }
        }
    }
}
