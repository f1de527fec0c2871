//! The robot error model: the flange pose the controller reports is not the true one.
//!
//! A real controller computes `base_from_flange` by forward kinematics of its *nominal*
//! model at its *measured* joint angles. Three things make that differ from where the
//! flange really is, and each is a separate, configurable term here:
//!
//! 1. **Kinematic parameter errors** (systematic). Machining and assembly make the true
//!    DH parameters differ slightly from the nominal ones. They are drawn once per robot
//!    ([`RobotErrorModel::realise`]) and stay fixed, so the same joint configuration
//!    always has the same error — exactly what a hand-eye calibration cannot average out.
//! 2. **Encoder noise** (random, per capture): the measured joint angles differ from the
//!    true ones by a small Gaussian error per joint.
//! 3. **Repeatability** (random, per capture): gear backlash, elasticity and settling
//!    leave the flange a little off the pose the joint angles imply. Configured as the
//!    ISO 9283 pose repeatability `RP = l̄ + 3·S_l`; for an isotropic 3-D Gaussian of
//!    per-axis σ the distance `l` is Maxwell-distributed with `l̄ = 1.596 σ` and
//!    `S_l = 0.673 σ`, so `σ = RP / 3.615`. KUKA specifies ±0.1 mm for the iiwa 7 and
//!    ±0.15 mm for the iiwa 14; measured values are often 0.05–0.1 mm.
//!
//! So the true flange is `exp(repeatability) · FK_true(q)` and the reported flange is
//! `FK_nominal(q + encoder noise)`; the images are rendered from the former and the
//! dataset's `captures.csv` gets the latter.

use b2b_robot::{Arm, Joints};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::{Iso3, Rng, SimError};

/// `RP / σ` for an isotropic 3-D Gaussian (Maxwell distance: mean + 3 std).
pub const RP_PER_SIGMA: f64 = 1.595_769 + 3.0 * 0.673_353;

/// Standard deviations of the DH parameter errors, drawn once per robot.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DhSigma {
    /// Link offsets `d` and lengths `a`, m.
    #[serde(default)]
    pub length_m: f64,
    /// Twists `α` and joint zero offsets `θ`, rad.
    #[serde(default)]
    pub angle_rad: f64,
}

/// How far the reported flange pose is from the truth. All zero means a perfect robot.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotErrorModel {
    /// Standard deviation of each joint's encoder reading, rad.
    #[serde(default)]
    pub encoder_sigma_rad: f64,
    /// ISO 9283 position repeatability RP, m.
    #[serde(default)]
    pub repeatability_m: f64,
    /// Orientation repeatability, as the per-axis standard deviation of the rotation
    /// vector, rad.
    #[serde(default)]
    pub repeatability_rad: f64,
    /// Kinematic parameter errors.
    #[serde(default)]
    pub dh: DhSigma,
}

impl RobotErrorModel {
    /// A typical iiwa: 0.08 mm repeatability, 0.001° encoders, DH errors of 0.1 mm and
    /// 0.005° (what remains after a factory calibration).
    pub fn typical() -> Self {
        RobotErrorModel {
            encoder_sigma_rad: 0.001f64.to_radians(),
            repeatability_m: 0.08e-3,
            repeatability_rad: 0.002f64.to_radians(),
            dh: DhSigma {
                length_m: 0.1e-3,
                angle_rad: 0.005f64.to_radians(),
            },
        }
    }

    /// Checks that every value is finite and not negative.
    pub fn validate(&self) -> Result<(), SimError> {
        let values = [
            ("encoder_sigma_rad", self.encoder_sigma_rad),
            ("repeatability_m", self.repeatability_m),
            ("repeatability_rad", self.repeatability_rad),
            ("dh.length_m", self.dh.length_m),
            ("dh.angle_rad", self.dh.angle_rad),
        ];
        for (name, v) in values {
            if !v.is_finite() || v < 0.0 {
                return Err(SimError::invalid(
                    "robot error model",
                    format!("{name} must be finite and >= 0, got {v}"),
                ));
            }
        }
        Ok(())
    }

    /// Draws one robot: its true kinematics, fixed from now on.
    pub fn realise(&self, nominal: &Arm, rng: &mut Rng) -> Result<RobotInstance, SimError> {
        self.validate()?;
        let mut true_arm = nominal.clone();
        for dh in &mut true_arm.dh {
            dh.d += self.dh.length_m * gauss(rng);
            dh.a += self.dh.length_m * gauss(rng);
            dh.alpha += self.dh.angle_rad * gauss(rng);
            dh.theta += self.dh.angle_rad * gauss(rng);
        }
        Ok(RobotInstance {
            nominal: nominal.clone(),
            true_arm,
            model: *self,
        })
    }
}

fn gauss(rng: &mut Rng) -> f64 {
    StandardNormal.sample(rng)
}

/// One physical robot: the nominal model the controller uses and the true one.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotInstance {
    pub nominal: Arm,
    pub true_arm: Arm,
    pub model: RobotErrorModel,
}

/// The state of the robot at one capture.
#[derive(Debug, Clone, PartialEq)]
pub struct FlangeState {
    /// Where the joints really are.
    pub true_joints: Joints,
    /// What the encoders read.
    pub measured_joints: Joints,
    /// Where the flange really is: render from this.
    pub true_base_from_flange: Iso3,
    /// What the controller reports: write this to the dataset.
    pub reported_base_from_flange: Iso3,
}

impl RobotInstance {
    /// The robot at rest at joint configuration `q` (the commanded one), with fresh
    /// encoder and repeatability noise.
    pub fn settle(&self, q: &Joints, rng: &mut Rng) -> FlangeState {
        let measured: Joints =
            std::array::from_fn(|i| q[i] + self.model.encoder_sigma_rad * gauss(rng));
        let sigma_t = self.model.repeatability_m / RP_PER_SIGMA;
        let sigma_r = self.model.repeatability_rad;
        let dt = Vector3::new(gauss(rng), gauss(rng), gauss(rng)) * sigma_t;
        let dr = Vector3::new(gauss(rng), gauss(rng), gauss(rng)) * sigma_r;
        // The disturbance acts at the flange (backlash and elasticity move the tool
        // about its own position), so it is applied in the flange frame.
        let wobble = Iso3::from_parts(Translation3::from(dt), UnitQuaternion::from_scaled_axis(dr));
        FlangeState {
            true_joints: *q,
            measured_joints: measured,
            true_base_from_flange: self.true_arm.fk(q) * wobble,
            reported_base_from_flange: self.nominal.fk(&measured),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use b2b_robot::IiwaModel;
    use rand::SeedableRng;

    const Q: Joints = [0.2, 0.6, -0.3, -1.4, 0.2, 0.8, 0.1];

    #[test]
    fn a_perfect_robot_reports_the_truth() {
        let arm = Arm::new(IiwaModel::Iiwa7R800);
        let mut rng = Rng::seed_from_u64(1);
        let robot = RobotErrorModel::default().realise(&arm, &mut rng).unwrap();
        let s = robot.settle(&Q, &mut rng);
        assert_eq!(s.true_base_from_flange, s.reported_base_from_flange);
    }

    #[test]
    fn repeatability_matches_the_iso_9283_figure() {
        let arm = Arm::new(IiwaModel::Iiwa14R820);
        let mut rng = Rng::seed_from_u64(2);
        let model = RobotErrorModel {
            repeatability_m: 0.1e-3,
            ..RobotErrorModel::default()
        };
        let robot = model.realise(&arm, &mut rng).unwrap();
        let points: Vec<Vector3<f64>> = (0..4000)
            .map(|_| {
                robot
                    .settle(&Q, &mut rng)
                    .true_base_from_flange
                    .translation
                    .vector
            })
            .collect();
        let mean = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
        let l: Vec<f64> = points.iter().map(|p| (p - mean).norm()).collect();
        let lbar = l.iter().sum::<f64>() / l.len() as f64;
        let s = (l.iter().map(|x| (x - lbar).powi(2)).sum::<f64>() / (l.len() - 1) as f64).sqrt();
        let rp = lbar + 3.0 * s;
        assert!((rp - 0.1e-3).abs() < 0.004e-3, "RP = {rp}");
    }

    #[test]
    fn kinematic_errors_are_systematic() {
        let arm = Arm::new(IiwaModel::Iiwa7R800);
        let mut rng = Rng::seed_from_u64(3);
        let model = RobotErrorModel {
            dh: DhSigma {
                length_m: 0.1e-3,
                angle_rad: 0.01f64.to_radians(),
            },
            ..RobotErrorModel::default()
        };
        let robot = model.realise(&arm, &mut rng).unwrap();
        let a = robot.settle(&Q, &mut rng);
        let b = robot.settle(&Q, &mut rng);
        let err = |s: &FlangeState| {
            (s.true_base_from_flange.translation.vector
                - s.reported_base_from_flange.translation.vector)
                .norm()
        };
        // Same configuration, same error; of the size the parameters imply.
        assert_eq!(a, b);
        assert!(err(&a) > 0.02e-3 && err(&a) < 2e-3, "{}", err(&a));
    }

    #[test]
    fn the_same_seed_gives_the_same_robot() {
        let arm = Arm::new(IiwaModel::Iiwa7R800);
        let make = || {
            let mut rng = Rng::seed_from_u64(4);
            let robot = RobotErrorModel::typical().realise(&arm, &mut rng).unwrap();
            robot.settle(&Q, &mut rng)
        };
        assert_eq!(make(), make());
    }

    #[test]
    fn negative_sigmas_are_rejected() {
        let model = RobotErrorModel {
            encoder_sigma_rad: -1.0,
            ..RobotErrorModel::default()
        };
        assert!(model.validate().is_err());
    }
}
