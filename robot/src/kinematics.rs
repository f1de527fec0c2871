//! Standard-DH chains: forward kinematics, the geometric Jacobian, and inverse
//! kinematics for a 7-DOF arm. The iiwa's tables are in [`crate::catalogue`].
//!
//! **Own DH chain, not the `k` crate.** `k` 0.32 is built on nalgebra 0.30 (a second
//! nalgebra in the build, converted through arrays at every call) and pulls in a URDF
//! parser; what the project needs is small and specific: a standard-DH chain whose
//! parameters can be *perturbed* (the simulator's robot error model gives the true robot
//! slightly different DH parameters from the nominal ones the controller believes), a
//! geometric Jacobian, and an IK that resolves the redundancy of a 7-DOF arm towards a
//! chosen posture inside the joint limits. That is ~200 lines here.
//!
//! **Parameters** (shared/facts.md §2, verified against the `lbr_description` URDF):
//! standard DH with `a = 0`, `α = [-π/2, π/2, π/2, -π/2, -π/2, π/2, 0]`,
//! `d = [0.34, 0, 0.40, 0, 0.40, 0, 0.126]` (iiwa 7) or `[0.36, 0, 0.42, 0, 0.40, 0, 0.126]`
//! (iiwa 14); frame 7 is the flange. Each link transform is
//! `Rz(θ_i + q_i) · Tz(d_i) · Tx(a_i) · Rx(α_i)`.
//!
//! **IK** is damped least squares on the 6-D pose error (position, and the rotation
//! vector of `R_target · R^T`), with the redundancy resolved in the Jacobian's null
//! space: a pull towards a preferred posture (by default the "comfortable" elbow-up
//! posture of [`Arm::comfortable`]), so the same target always gives the same,
//! natural-looking configuration. Joint limits are enforced by projecting every iterate
//! into the limits shrunk by a small margin; a solve that cannot reach the target from
//! one seed is restarted from deterministic alternative seeds.

use nalgebra::{
    Isometry3, Matrix3, Matrix6, Point3, SMatrix, Translation3, UnitQuaternion, Vector3, Vector6,
};
use serde::{Deserialize, Serialize};

use crate::{IiwaModel, JointLimits, Joints, N_JOINTS, RobotError};

/// The geometric Jacobian of a 7-joint chain: rows are the linear then the angular
/// velocity of the flange in the base frame, columns the joints.
pub type Jacobian = SMatrix<f64, 6, N_JOINTS>;

/// One link's standard DH parameters: `Rz(theta + q) Tz(d) Tx(a) Rx(alpha)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Dh {
    /// Offset along the previous z axis, m.
    pub d: f64,
    /// Length along the new x axis, m.
    pub a: f64,
    /// Twist about the new x axis, rad.
    pub alpha: f64,
    /// Joint zero offset, added to the joint value.
    pub theta: f64,
}

impl Dh {
    /// `frame_{i-1} from frame_i` at joint value `q`. A non-finite joint value
    /// (or table entry) gives a pose that is NaN throughout, at once: the
    /// rotation-matrix-to-quaternion step iterates until it converges, which it
    /// never does on NaN.
    pub fn transform(&self, q: f64) -> Isometry3<f64> {
        if ![q, self.theta, self.alpha, self.a, self.d]
            .iter()
            .all(|v| v.is_finite())
        {
            return Isometry3::from_parts(
                Translation3::new(f64::NAN, f64::NAN, f64::NAN),
                UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(
                    f64::NAN,
                    f64::NAN,
                    f64::NAN,
                    f64::NAN,
                )),
            );
        }
        let (st, ct) = (self.theta + q).sin_cos();
        let (sa, ca) = self.alpha.sin_cos();
        let r = Matrix3::new(ct, -st * ca, st * sa, st, ct * ca, -ct * sa, 0.0, sa, ca);
        Isometry3::from_parts(
            Translation3::new(self.a * ct, self.a * st, self.d),
            UnitQuaternion::from_matrix(&r),
        )
    }
}

/// A 7-DOF serial arm in standard DH. [`Arm::new`] gives a model's nominal arm; the
/// fields are public so that an error model can perturb the table of a "true" arm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Arm {
    /// Which arm this is (the catalogue entry its table started from).
    pub model: IiwaModel,
    /// The standard-DH table, base to flange.
    pub dh: [Dh; N_JOINTS],
    /// The joint limits.
    pub limits: JointLimits,
}

impl Arm {
    /// The nominal kinematics and limits of a model ([`crate::catalogue`]).
    pub fn new(model: IiwaModel) -> Arm {
        Arm {
            model,
            dh: model.dh(),
            limits: model.limits(),
        }
    }

    /// A relaxed elbow-up posture with the flange pointing down in front of the base:
    /// the default preference of the IK's null-space term and its first seed.
    pub fn comfortable() -> Joints {
        [0.0, 30.0, 0.0, -90.0, 0.0, 60.0, 0.0].map(f64::to_radians)
    }

    /// The shoulder centre (where axes 1 and 2 meet, `d1` above the base) in the base.
    /// Meaningful for the iiwa's layout ([`crate::catalogue`]: `a = 0`, `d2 = 0`).
    pub fn shoulder_in_base(&self) -> Point3<f64> {
        Point3::new(0.0, 0.0, self.dh[0].d)
    }

    /// The wrist centre (where axes 5, 6 and 7 meet) of a flange pose: `d7` behind the
    /// flange along its z axis.
    pub fn wrist_centre_in_base(&self, base_from_flange: &Isometry3<f64>) -> Point3<f64> {
        base_from_flange * Point3::new(0.0, 0.0, -self.dh[N_JOINTS - 1].d)
    }

    /// The longest possible shoulder-to-wrist distance, `|d3| + |d5|` (arm stretched):
    /// a flange pose whose wrist centre is further from the shoulder is out of reach
    /// whatever the joint angles.
    pub fn max_shoulder_to_wrist_m(&self) -> f64 {
        self.dh[2].d.abs() + self.dh[4].d.abs()
    }

    /// `base_from_flange` at `q`.
    pub fn fk(&self, q: &Joints) -> Isometry3<f64> {
        self.dh
            .iter()
            .zip(q)
            .fold(Isometry3::identity(), |acc, (dh, &qi)| {
                acc * dh.transform(qi)
            })
    }

    /// `base_from_frame_i` for i = 0 (the base) ..= 7 (the flange).
    pub fn frames(&self, q: &Joints) -> [Isometry3<f64>; N_JOINTS + 1] {
        let mut out = [Isometry3::identity(); N_JOINTS + 1];
        for i in 0..N_JOINTS {
            out[i + 1] = out[i] * self.dh[i].transform(q[i]);
        }
        out
    }

    /// The geometric Jacobian at the flange, in the base frame: rows are the linear
    /// then the angular velocity of the flange.
    pub fn jacobian(&self, q: &Joints) -> Jacobian {
        jacobian_from_frames(&self.frames(q))
    }

    /// Inverse kinematics: a configuration inside the limits whose flange is at
    /// `base_from_flange`, found by [`IkOptions`]' method. `seed` is the first start.
    pub fn ik(
        &self,
        base_from_flange: &Isometry3<f64>,
        seed: &Joints,
        opts: &IkOptions,
    ) -> Result<Joints, RobotError> {
        let mut best: Option<(f64, Joints)> = None;
        for k in 0..=opts.restarts {
            let start = if k == 0 { *seed } else { self.restart_seed(k) };
            let (q, err) = self.ik_from(base_from_flange, &start, opts);
            if err.0 < opts.tolerance_m && err.1 < opts.tolerance_rad {
                return Ok(q);
            }
            let score = err.0 + err.1;
            if best.is_none_or(|(s, _)| score < s) {
                best = Some((score, q));
            }
        }
        let (pos, rot) = best
            .map(|(_, q)| pose_error_norms(&self.fk(&q), base_from_flange))
            .unwrap_or((f64::INFINITY, f64::INFINITY));
        Err(RobotError::Unreachable {
            position_error_m: pos,
            rotation_error_rad: rot,
        })
    }

    /// Deterministic restart seeds spread over the joint space (a fixed low-discrepancy
    /// sequence, so the IK is a pure function of its inputs).
    fn restart_seed(&self, k: usize) -> Joints {
        const PRIMES: [f64; N_JOINTS] = [2.0, 3.0, 5.0, 7.0, 11.0, 13.0, 17.0];
        std::array::from_fn(|i| {
            let u = (k as f64 * PRIMES[i].sqrt()).fract();
            let (lo, hi) = (self.limits.position_min[i], self.limits.position_max[i]);
            lo + (hi - lo) * (0.15 + 0.7 * u)
        })
    }

    fn ik_from(
        &self,
        target: &Isometry3<f64>,
        seed: &Joints,
        opts: &IkOptions,
    ) -> (Joints, (f64, f64)) {
        let preferred = opts.preferred.unwrap_or_else(Arm::comfortable);
        let mut q = self.limits.clamp(seed, opts.limit_margin);
        let mut err = (f64::INFINITY, f64::INFINITY);
        for _ in 0..opts.max_iterations {
            let frames = self.frames(&q);
            let current = frames[N_JOINTS];
            let e = pose_error(&current, target);
            err = (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm());
            let j = jacobian_from_frames(&frames);
            let jjt = j * j.transpose();
            // Damping grows only near singularities (small e => small damping), so the
            // final iterations are plain Gauss-Newton and converge quadratically.
            let lambda2 = opts.damping * opts.damping * e.norm().min(1.0);
            let Some(inv) = (jjt + Matrix6::identity() * lambda2).try_inverse() else {
                break;
            };
            let pinv = j.transpose() * inv;
            let task = pinv * e;
            // Null-space pull towards the preferred posture.
            let pull = SMatrix::<f64, N_JOINTS, 1>::from_fn(|i, _| {
                opts.posture_gain * (preferred[i] - q[i])
            });
            let null = (SMatrix::<f64, N_JOINTS, N_JOINTS>::identity() - pinv * j) * pull;
            let mut step = task + null;
            let norm = step.norm();
            if norm > opts.max_step {
                step *= opts.max_step / norm;
            }
            let next: Joints = std::array::from_fn(|i| q[i] + step[i]);
            let next = self.limits.clamp(&next, opts.limit_margin);
            let moved = (0..N_JOINTS)
                .map(|i| (next[i] - q[i]).abs())
                .fold(0.0, f64::max);
            q = next;
            // Done when the task is met and the posture has settled (or is held by a
            // limit, where the clamped step vanishes).
            if err.0 < opts.tolerance_m * 1e-3
                && err.1 < opts.tolerance_rad * 1e-3
                && moved < opts.settle_rad
            {
                break;
            }
        }
        let final_err = pose_error_norms(&self.fk(&q), target);
        if final_err.0.is_finite() {
            err = final_err;
        }
        (q, err)
    }
}

/// The geometric Jacobian from the frames of [`Arm::frames`].
fn jacobian_from_frames(frames: &[Isometry3<f64>; N_JOINTS + 1]) -> Jacobian {
    let p_end = frames[N_JOINTS].translation.vector;
    let mut j = Jacobian::zeros();
    for (i, frame) in frames.iter().take(N_JOINTS).enumerate() {
        let z = frame.rotation * Vector3::z();
        let lin = z.cross(&(p_end - frame.translation.vector));
        j.fixed_view_mut::<3, 1>(0, i).copy_from(&lin);
        j.fixed_view_mut::<3, 1>(3, i).copy_from(&z);
    }
    j
}

/// The 6-D error `[position; rotation vector]` that takes `current` to `target`, in the
/// base frame.
fn pose_error(current: &Isometry3<f64>, target: &Isometry3<f64>) -> Vector6<f64> {
    let dp = target.translation.vector - current.translation.vector;
    let dr = (target.rotation * current.rotation.inverse()).scaled_axis();
    Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
}

/// Position (m) and rotation (rad) distance between two flange poses.
pub fn pose_error_norms(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let e = pose_error(a, b);
    (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm())
}

/// How [`Arm::ik`] searches.
#[derive(Debug, Clone, PartialEq)]
pub struct IkOptions {
    /// Accepted position error, m.
    pub tolerance_m: f64,
    /// Accepted rotation error, rad.
    pub tolerance_rad: f64,
    pub max_iterations: usize,
    /// Additional deterministic starts after `seed`.
    pub restarts: usize,
    /// Damping of the least-squares step far from the solution.
    pub damping: f64,
    /// Largest joint step per iteration, rad (norm over joints).
    pub max_step: f64,
    /// Gain of the null-space pull towards `preferred`.
    pub posture_gain: f64,
    /// The posture the redundancy is resolved towards; `None` means [`Arm::comfortable`].
    pub preferred: Option<Joints>,
    /// Solutions stay this far inside every position limit, rad.
    pub limit_margin: f64,
    /// The posture counts as settled once no joint moves more than this in an
    /// iteration (the null-space pull converges geometrically, so a tight value
    /// costs iterations without moving the flange), rad.
    pub settle_rad: f64,
}

impl Default for IkOptions {
    fn default() -> Self {
        IkOptions {
            tolerance_m: 1e-9,
            tolerance_rad: 1e-9,
            max_iterations: 400,
            restarts: 8,
            damping: 0.05,
            max_step: 0.3,
            posture_gain: 0.5,
            preferred: None,
            limit_margin: 2f64.to_radians(),
            settle_rad: 1e-8,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Forward kinematics of a non-finite joint vector returns (a NaN pose)
    /// instead of iterating forever; finite joints are untouched.
    #[test]
    fn non_finite_joints_give_a_nan_pose_at_once() {
        let arm = Arm::new(IiwaModel::Iiwa14R820);
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let mut q = Arm::comfortable();
            q[3] = bad;
            let pose = arm.fk(&q);
            assert!(pose.translation.vector.iter().all(|v| v.is_nan()));
            assert!(pose.rotation.coords.iter().all(|v| v.is_nan()));
            assert!(arm.frames(&q)[7].translation.vector.x.is_nan());
        }
        let q = Arm::comfortable();
        assert!(arm.fk(&q).translation.vector.iter().all(|v| v.is_finite()));
    }

    /// The `lbr_description` URDF chain (shared/facts.md §2.1), written independently of
    /// the DH table: joint origins (rpy = 0) and axes, then the fixed flange joint.
    fn urdf_fk(model: IiwaModel, q: &Joints) -> Isometry3<f64> {
        let origins: [[f64; 3]; 7] = match model {
            IiwaModel::Iiwa7R800 => [
                [0.0, 0.0, 0.1475],
                [0.0, -0.0105, 0.1925],
                [0.0, 0.0105, 0.2075],
                [0.0, 0.0105, 0.1925],
                [0.0, -0.0105, 0.2075],
                [0.0, -0.0707, 0.1925],
                [0.0, 0.0707, 0.091],
            ],
            IiwaModel::Iiwa14R820 => [
                [0.0, 0.0, 0.1475],
                [0.0, -0.01, 0.2125],
                [0.0, 0.01, 0.228],
                [0.0, 0.0105, 0.192],
                [0.0, -0.0105, 0.2075],
                [0.0, -0.0707, 0.1925],
                [0.0, 0.0707, 0.091],
            ],
        };
        let axes = [
            Vector3::z(),
            Vector3::y(),
            Vector3::z(),
            -Vector3::y(),
            Vector3::z(),
            Vector3::y(),
            Vector3::z(),
        ];
        let mut t = Isometry3::identity();
        for i in 0..7 {
            t = t
                * Translation3::from(Vector3::from(origins[i]))
                * UnitQuaternion::from_scaled_axis(axes[i] * q[i]);
        }
        t * Translation3::new(0.0, 0.0, 0.035)
    }

    fn joints_in(arm: &Arm, shrink: f64) -> impl Strategy<Value = Joints> {
        let lo = arm.limits.position_min;
        let hi = arm.limits.position_max;
        proptest::array::uniform7(0.0..1.0f64).prop_map(move |u| {
            std::array::from_fn(|i| lo[i] * shrink + (hi[i] - lo[i]) * shrink * u[i])
        })
    }

    #[test]
    fn zero_pose_flange_heights_match_the_datasheet() {
        let z7 = Arm::new(IiwaModel::Iiwa7R800).fk(&[0.0; 7]).translation.z;
        let z14 = Arm::new(IiwaModel::Iiwa14R820).fk(&[0.0; 7]).translation.z;
        assert!((z7 - 1.266).abs() < 1e-12, "{z7}");
        assert!((z14 - 1.306).abs() < 1e-12, "{z14}");
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let arm = Arm::new(IiwaModel::Iiwa14R820);
        let q = [0.3, -0.5, 0.7, -1.2, 0.4, 0.9, -0.6];
        let j = arm.jacobian(&q);
        let t0 = arm.fk(&q);
        for i in 0..7 {
            let h = 1e-7;
            let mut qh = q;
            qh[i] += h;
            let d = pose_error(&t0, &arm.fk(&qh)) / h;
            assert!(
                (d - j.column(i)).norm() < 1e-6,
                "joint {i}: {d} vs {}",
                j.column(i)
            );
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

        #[test]
        fn fk_matches_the_urdf_chain(q in joints_in(&Arm::new(IiwaModel::Iiwa7R800), 1.0),
                                     fourteen in any::<bool>()) {
            let model = if fourteen { IiwaModel::Iiwa14R820 } else { IiwaModel::Iiwa7R800 };
            let dh = Arm::new(model).fk(&q);
            let urdf = urdf_fk(model, &q);
            let (dp, dr) = pose_error_norms(&dh, &urdf);
            prop_assert!(dp < 1e-12 && dr < 1e-12, "{dp} m, {dr} rad");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 100, ..ProptestConfig::default() })]

        #[test]
        fn wrist_and_shoulder_centres_are_where_the_axes_meet(
            q in joints_in(&Arm::new(IiwaModel::Iiwa7R800), 1.0),
            fourteen in any::<bool>(),
        ) {
            let model = if fourteen { IiwaModel::Iiwa14R820 } else { IiwaModel::Iiwa7R800 };
            let arm = Arm::new(model);
            let frames = arm.frames(&q);
            // Axes 1 and 2 meet at the origins of frames 1 and 2; axes 5, 6 and 7 at
            // those of frames 5 and 6.
            for f in [1, 2] {
                let d = (frames[f].translation.vector - arm.shoulder_in_base().coords).norm();
                prop_assert!(d < 1e-12, "frame {f}: {d}");
            }
            let wrist = arm.wrist_centre_in_base(&arm.fk(&q));
            for f in [5, 6] {
                let d = (frames[f].translation.vector - wrist.coords).norm();
                prop_assert!(d < 1e-12, "frame {f}: {d}");
            }
            let reach = (wrist - arm.shoulder_in_base()).norm();
            prop_assert!(reach <= arm.max_shoulder_to_wrist_m() + 1e-12, "{reach}");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

        #[test]
        fn ik_round_trips_inside_the_limits(q in joints_in(&Arm::new(IiwaModel::Iiwa7R800), 0.8),
                                            fourteen in any::<bool>()) {
            // Away from the wrist and elbow singularities (A4 or A6 straight), where
            // the damped least-squares IK does not reach 1e-6 from every start: a
            // known limit of this IK (viewpoints are planned away from them).
            prop_assume!(q[3].abs() > 0.2 && q[5].abs() > 0.2);
            let model = if fourteen { IiwaModel::Iiwa14R820 } else { IiwaModel::Iiwa7R800 };
            let arm = Arm::new(model);
            let target = arm.fk(&q);
            let sol = arm.ik(&target, &Arm::comfortable(), &IkOptions::default())
                .map_err(|e| TestCaseError::fail(format!("{e} for {q:?}")))?;
            prop_assert!(arm.limits.contains(&sol));
            let (dp, dr) = pose_error_norms(&arm.fk(&sol), &target);
            prop_assert!(dp < 1e-6 && dr < 1e-6, "{dp} m, {dr} rad");
        }
    }

    #[test]
    fn ik_resolves_redundancy_towards_the_preferred_posture() {
        let arm = Arm::new(IiwaModel::Iiwa7R800);
        let target = arm.fk(&Arm::comfortable());
        // Start far away: the null-space pull must bring the elbow back.
        let seed = [0.8, 0.2, -0.9, -1.2, 0.7, 0.5, 0.3];
        let sol = arm.ik(&target, &seed, &IkOptions::default()).unwrap();
        let dist: f64 = sol
            .iter()
            .zip(Arm::comfortable())
            .map(|(a, b)| (a - b).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(dist < 1e-3, "{sol:?}");
    }

    #[test]
    fn unreachable_targets_are_an_error_not_a_panic() {
        let arm = Arm::new(IiwaModel::Iiwa7R800);
        let far = Isometry3::translation(3.0, 0.0, 0.5);
        let opts = IkOptions {
            restarts: 1,
            ..IkOptions::default()
        };
        assert!(matches!(
            arm.ik(&far, &Arm::comfortable(), &opts),
            Err(RobotError::Unreachable { .. })
        ));
    }
}
