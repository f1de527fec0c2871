//! The arms this project knows: LBR iiwa 7 R800 and LBR iiwa 14 R820.
//!
//! Every number here is from shared/facts.md §2 and is written once:
//!
//! - **Standard DH** (verified against the `lbr_description` URDF to 1e-15 on 200 random
//!   configurations per model, and again by this crate's tests): `a = 0`,
//!   `α = [-π/2, π/2, π/2, -π/2, -π/2, π/2, 0]`, `θ = 0`,
//!   `d = [0.34, 0, 0.40, 0, 0.40, 0, 0.126]` m (iiwa 7) or
//!   `[0.36, 0, 0.42, 0, 0.40, 0, 0.126]` m (iiwa 14); frame 7 is the bare flange
//!   (`d7 = 0.126` m; KUKA's 0.28 m is a media-flange variant, not modelled).
//! - **Position limits** (both models): ±170, ±120, ±170, ±120, ±170, ±120, ±175°.
//! - **Velocity limits**: 98, 98, 100, 130, 140, 180, 180 °/s (iiwa 7) and
//!   85, 85, 100, 75, 130, 135, 135 °/s (iiwa 14).
//!
//! **Wrist geometry.** With `a = 0` and `d2 = d4 = d6 = 0`, axes 1 and 2 meet in the
//! shoulder, `d1` above the base, and axes 5, 6 and 7 meet in the wrist centre, `d7`
//! behind the flange along its z axis; the shoulder-to-wrist distance is at most
//! `d3 + d5` (arm stretched). [`crate::Arm::shoulder_in_base`],
//! [`crate::Arm::wrist_centre_in_base`] and [`crate::Arm::max_shoulder_to_wrist_m`] give
//! these from an arm's DH table, so the planner's quick reach test needs no numbers of
//! its own.

use std::f64::consts::FRAC_PI_2;

use serde::{Deserialize, Serialize};

use crate::{Dh, JointLimits, Joints, N_JOINTS};

/// The two arm models. The serde names (`"iiwa7"`, `"iiwa14"`) are those of the scene
/// and setup files.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum IiwaModel {
    /// LBR iiwa 7 R800.
    #[serde(rename = "iiwa7")]
    Iiwa7R800,
    /// LBR iiwa 14 R820.
    #[serde(rename = "iiwa14")]
    Iiwa14R820,
}

/// Position limits of both models, degrees (symmetric about zero).
const POSITION_DEG: [f64; N_JOINTS] = [170.0, 120.0, 170.0, 120.0, 170.0, 120.0, 175.0];

/// Planning acceleration of every joint, rad/s²: gentle, as for moving a camera around
/// a patient. Not a KUKA figure (none is published in the sources of facts.md §2.3).
pub const PLANNING_ACCELERATION: f64 = 2.0;

/// Link twists α of the standard-DH table, shared by both models.
const ALPHA: [f64; N_JOINTS] = [
    -FRAC_PI_2, FRAC_PI_2, FRAC_PI_2, -FRAC_PI_2, -FRAC_PI_2, FRAC_PI_2, 0.0,
];

fn deg(v: [f64; N_JOINTS]) -> Joints {
    v.map(f64::to_radians)
}

impl IiwaModel {
    /// Both models.
    pub const ALL: [IiwaModel; 2] = [IiwaModel::Iiwa7R800, IiwaModel::Iiwa14R820];

    /// The link offsets `d` of the standard-DH table, m.
    pub fn dh_d(self) -> Joints {
        match self {
            IiwaModel::Iiwa7R800 => [0.34, 0.0, 0.40, 0.0, 0.40, 0.0, 0.126],
            IiwaModel::Iiwa14R820 => [0.36, 0.0, 0.42, 0.0, 0.40, 0.0, 0.126],
        }
    }

    /// The nominal standard-DH table (frame 7 = the flange).
    pub fn dh(self) -> [Dh; N_JOINTS] {
        let d = self.dh_d();
        std::array::from_fn(|i| Dh {
            d: d[i],
            a: 0.0,
            alpha: ALPHA[i],
            theta: 0.0,
        })
    }

    /// The flange's distance from the wrist centre along the flange z axis (`d7`), m.
    pub fn flange_offset_m(self) -> f64 {
        self.dh_d()[6]
    }

    /// Rated velocity of each joint, rad/s.
    pub fn velocity_limits(self) -> Joints {
        match self {
            IiwaModel::Iiwa7R800 => deg([98.0, 98.0, 100.0, 130.0, 140.0, 180.0, 180.0]),
            IiwaModel::Iiwa14R820 => deg([85.0, 85.0, 100.0, 75.0, 130.0, 135.0, 135.0]),
        }
    }

    /// The joint limits: positions, rated velocities and the planning acceleration.
    pub fn limits(self) -> JointLimits {
        let max = deg(POSITION_DEG);
        JointLimits {
            position_min: max.map(|m| -m),
            position_max: max,
            velocity: self.velocity_limits(),
            acceleration: [PLANNING_ACCELERATION; N_JOINTS],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_flange_is_d7_from_the_wrist_for_both_models() {
        for model in IiwaModel::ALL {
            assert_eq!(model.flange_offset_m(), 0.126);
            let d = model.dh_d();
            assert_eq!([d[1], d[3], d[5]], [0.0; 3], "{model:?}: d2 = d4 = d6 = 0");
        }
    }
}
