//! Motion checks that every hand-eye and robot-world solver runs before it solves.
//!
//! A closed-form hand-eye solver always returns *some* transform. When the robot's
//! motions do not excite every direction, that transform is partly arbitrary, and
//! the solvers give no sign of it. So the solvers in [`crate::handeye`] refuse such
//! input up front and name the reason, instead of handing back a wrong number.
//!
//! # What is checked
//!
//! The checks look at the **relative motions** of the flange, one per pair of
//! captures `i < j`: `flange_j_from_flange_i = base_from_flange[j]⁻¹ · base_from_flange[i]`.
//! These are exactly the `A` matrices of `A X = X B` the pair-based solvers use (the
//! camera motions `B` are conjugate to them, so they have the same angles). In order:
//!
//! 1. lengths agree and every number is finite ([`CalibError::MismatchedLengths`],
//!    [`CalibError::NonFinite`]);
//! 2. at least [`MotionThresholds::min_captures`] captures ([`CalibError::TooFewCaptures`]);
//! 3. the largest relative rotation is at least
//!    [`MotionThresholds::pure_translation_deg`], otherwise the robot only translated
//!    and the hand-eye rotation is unobservable ([`CalibError::PureTranslation`]);
//! 4. at least [`MotionThresholds::min_useful_motions`] relative rotations reach
//!    [`MotionThresholds::min_rotation_deg`] ([`CalibError::RotationsTooSmall`]);
//! 5. the rotation axes of those useful motions are not all (nearly) parallel: the
//!    largest angle between two of them must reach
//!    [`MotionThresholds::min_axis_angle_deg`] ([`CalibError::ParallelRotationAxes`]).
//!    Motions about one axis leave the hand-eye translation along that axis
//!    unobservable (Tsai & Lenz 1989, Chen 1991). Axes are lines, so `a` and `-a` are
//!    the same axis: the angle between axes is `acos(|a·b|)`, in `[0°, 90°]`.
//!
//! # How the largest axis angle is found
//!
//! With `n` captures there are `n(n-1)/2` motions, and the exact largest pairwise
//! axis angle would cost `O(n⁴)`. The check instead runs a two-sweep farthest-point
//! search (start at the axis of the largest rotation, go to the axis farthest from
//! it, then to the axis farthest from that), which is `O(n²)` like the solvers. The
//! angle found is a real angle between two motion axes, and because the
//! sign-insensitive axis angle is a metric, the true largest angle is at most twice
//! the first sweep's result. So a [`CalibError::ParallelRotationAxes`] from this check
//! means every axis lies within `min_axis_angle_deg` of one axis: a genuinely narrow
//! cone.

use crate::{CalibError, Iso3};

/// Thresholds for [`check_motions`]. The defaults suit a camera on a robot flange
/// calibrated against a board: real data sets rotate by tens of degrees about
/// axes tens of degrees apart, so the defaults only reject input that cannot give
/// a trustworthy closed form.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionThresholds {
    /// Fewest captures accepted. Default 3: two independent relative motions are
    /// the minimum that determines `X` in `A X = X B`.
    pub min_captures: usize,
    /// Below this largest relative rotation (degrees) the motion counts as pure
    /// translation. Default 0.5°: at the usual 0.01–0.1° pose noise, smaller
    /// rotations have axes dominated by noise.
    pub pure_translation_deg: f64,
    /// A relative rotation of at least this many degrees is a useful motion.
    /// Default 5°: the hand-eye rotation error of the pair-based solvers scales like
    /// noise / angle, so smaller motions contribute little but noise.
    pub min_rotation_deg: f64,
    /// How many useful motions are needed. Default 2 (two non-parallel axes).
    pub min_useful_motions: usize,
    /// The largest angle between the axes of useful motions must reach this
    /// (degrees). Default 5°: below it the translation along the common axis is
    /// amplified by roughly `1 / sin(angle)` (more than 11x at 5°).
    pub min_axis_angle_deg: f64,
}

impl Default for MotionThresholds {
    fn default() -> Self {
        MotionThresholds {
            min_captures: 3,
            pure_translation_deg: 0.5,
            min_rotation_deg: 5.0,
            min_useful_motions: 2,
            min_axis_angle_deg: 5.0,
        }
    }
}

/// What [`check_motions`] found about an accepted set of captures.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionReport {
    /// Number of captures.
    pub captures: usize,
    /// Number of relative motions examined (`captures * (captures - 1) / 2`).
    pub motions: usize,
    /// Relative motions whose rotation reaches `min_rotation_deg`.
    pub useful_motions: usize,
    /// The largest relative rotation (degrees).
    pub max_rotation_deg: f64,
    /// The largest angle (degrees, in `[0, 90]`) between the rotation axes of two
    /// useful motions, found by the two-sweep search described in the module docs
    /// (a lower bound on the exact maximum, and at least half of it).
    pub max_axis_angle_deg: f64,
}

/// Checks that a list of poses has no NaN or infinity; `what` names it in the error.
pub fn check_finite(poses: &[Iso3], what: &str) -> Result<(), CalibError> {
    for (i, p) in poses.iter().enumerate() {
        let finite = p.translation.vector.iter().all(|v| v.is_finite())
            && p.rotation.coords.iter().all(|v| v.is_finite());
        if !finite {
            return Err(CalibError::NonFinite(format!("{what}[{i}]")));
        }
    }
    Ok(())
}

/// Checks that two per-capture lists have the same length.
pub fn check_same_length(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
) -> Result<(), CalibError> {
    if base_from_flange.len() != camera_from_target.len() {
        return Err(CalibError::MismatchedLengths {
            len_a: base_from_flange.len(),
            what_a: "flange poses (base_from_flange)",
            len_b: camera_from_target.len(),
            what_b: "board poses (camera_from_target)",
        });
    }
    Ok(())
}

/// Checks the flange motions of a hand-eye data set (see the module docs for the
/// order of the checks and what each error means).
pub fn check_motions(
    base_from_flange: &[Iso3],
    t: &MotionThresholds,
) -> Result<MotionReport, CalibError> {
    check_finite(base_from_flange, "base_from_flange")?;
    let n = base_from_flange.len();
    let need = t.min_captures.max(2);
    if n < need {
        return Err(CalibError::TooFewCaptures { got: n, need });
    }

    // Relative rotations of all pairs: angle and unit axis.
    let min_rot = t.min_rotation_deg.to_radians();
    let mut max_rotation = 0.0_f64;
    let mut useful: Vec<(f64, nalgebra::Vector3<f64>)> = Vec::new();
    for i in 0..n {
        for j in (i + 1)..n {
            let rel = base_from_flange[j].rotation.inverse() * base_from_flange[i].rotation;
            let angle = rel.angle();
            max_rotation = max_rotation.max(angle);
            if angle >= min_rot
                && let Some(axis) = rel.axis()
            {
                useful.push((angle, axis.into_inner()));
            }
        }
    }
    let max_rotation_deg = max_rotation.to_degrees();
    if max_rotation_deg < t.pure_translation_deg {
        return Err(CalibError::PureTranslation {
            max_rotation_deg,
            min_rotation_deg: t.pure_translation_deg,
        });
    }
    if useful.len() < t.min_useful_motions.max(1) {
        return Err(CalibError::RotationsTooSmall {
            count: useful.len(),
            need: t.min_useful_motions.max(1),
            min_rotation_deg: t.min_rotation_deg,
        });
    }

    // Two-sweep farthest-point search over the axes (sign-insensitive).
    let axis_angle =
        |a: &nalgebra::Vector3<f64>, b: &nalgebra::Vector3<f64>| a.dot(b).abs().min(1.0).acos();
    let farthest =
        |from: &nalgebra::Vector3<f64>| {
            useful.iter().map(|(_, a)| (axis_angle(from, a), *a)).fold(
                (0.0_f64, *from),
                |best, cur| if cur.0 > best.0 { cur } else { best },
            )
        };
    let start = useful
        .iter()
        .fold(
            &useful[0],
            |best, cur| if cur.0 > best.0 { cur } else { best },
        )
        .1;
    let (first, far) = farthest(&start);
    let (second, _) = farthest(&far);
    let max_axis_angle_deg = first.max(second).to_degrees();
    if max_axis_angle_deg < t.min_axis_angle_deg {
        return Err(CalibError::ParallelRotationAxes {
            max_angle_deg: max_axis_angle_deg,
            min_angle_deg: t.min_axis_angle_deg,
        });
    }

    Ok(MotionReport {
        captures: n,
        motions: n * (n - 1) / 2,
        useful_motions: useful.len(),
        max_rotation_deg,
        max_axis_angle_deg,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn pose(t: [f64; 3], axis: Vector3<f64>, angle_deg: f64) -> Iso3 {
        Iso3::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_scaled_axis(axis.normalize() * angle_deg.to_radians()),
        )
    }

    fn good_poses() -> Vec<Iso3> {
        vec![
            pose([0.5, 0.0, 0.3], Vector3::x(), 0.0),
            pose([0.6, 0.1, 0.3], Vector3::x(), 30.0),
            pose([0.5, -0.1, 0.4], Vector3::y(), 25.0),
            pose([0.4, 0.0, 0.35], Vector3::new(1.0, 1.0, 1.0), 40.0),
        ]
    }

    #[test]
    fn accepts_well_spread_motions() {
        let report = check_motions(&good_poses(), &MotionThresholds::default()).unwrap();
        assert_eq!(report.captures, 4);
        assert_eq!(report.motions, 6);
        assert_eq!(report.useful_motions, 6);
        assert!(report.max_rotation_deg > 40.0, "{report:?}");
        // x and y axes are 90 degrees apart.
        assert!(report.max_axis_angle_deg > 60.0, "{report:?}");
    }

    #[test]
    fn two_captures_are_too_few() {
        let err = check_motions(&good_poses()[..2], &MotionThresholds::default()).unwrap_err();
        assert_eq!(err, CalibError::TooFewCaptures { got: 2, need: 3 });
    }

    #[test]
    fn empty_input_is_too_few() {
        let err = check_motions(&[], &MotionThresholds::default()).unwrap_err();
        assert!(matches!(err, CalibError::TooFewCaptures { got: 0, .. }));
    }

    #[test]
    fn pure_translation_is_named() {
        let poses: Vec<Iso3> = (0..6)
            .map(|k| {
                pose(
                    [0.5 + 0.05 * k as f64, 0.02 * k as f64, 0.3],
                    Vector3::z(),
                    10.0,
                )
            })
            .collect();
        let err = check_motions(&poses, &MotionThresholds::default()).unwrap_err();
        assert!(matches!(err, CalibError::PureTranslation { .. }), "{err}");
    }

    #[test]
    fn tiny_rotations_are_too_small() {
        let axes = [
            Vector3::x(),
            Vector3::y(),
            Vector3::z(),
            Vector3::new(1.0, -1.0, 0.0),
        ];
        let poses: Vec<Iso3> = axes
            .iter()
            .enumerate()
            .map(|(k, a)| pose([0.5, 0.1 * k as f64, 0.3], *a, 1.5))
            .collect();
        let err = check_motions(&poses, &MotionThresholds::default()).unwrap_err();
        assert!(
            matches!(
                err,
                CalibError::RotationsTooSmall {
                    count: 0,
                    need: 2,
                    ..
                }
            ),
            "{err}"
        );
    }

    #[test]
    fn rotations_about_one_axis_are_parallel() {
        // Large rotations, all about the same (tilted) axis, with translations:
        // the classic planar-motion degeneracy.
        let axis = Vector3::new(0.2, -0.3, 1.0);
        let poses: Vec<Iso3> = (0..8)
            .map(|k| {
                pose(
                    [0.4 + 0.03 * k as f64, -0.02 * k as f64, 0.3],
                    axis,
                    25.0 * k as f64,
                )
            })
            .collect();
        let err = check_motions(&poses, &MotionThresholds::default()).unwrap_err();
        match err {
            CalibError::ParallelRotationAxes { max_angle_deg, .. } => {
                assert!(max_angle_deg < 1e-6, "{max_angle_deg}")
            }
            other => panic!("expected ParallelRotationAxes, got {other}"),
        }
    }

    #[test]
    fn opposite_axes_are_parallel() {
        // +z and -z are the same axis: the comparison must ignore the sign.
        let poses = vec![
            pose([0.5, 0.0, 0.3], Vector3::z(), 0.0),
            pose([0.5, 0.1, 0.3], Vector3::z(), 40.0),
            pose([0.5, 0.2, 0.3], -Vector3::z(), 70.0),
        ];
        let err = check_motions(&poses, &MotionThresholds::default()).unwrap_err();
        assert!(
            matches!(err, CalibError::ParallelRotationAxes { .. }),
            "{err}"
        );
    }

    #[test]
    fn nan_is_non_finite() {
        let mut poses = good_poses();
        poses[2].translation.vector.y = f64::NAN;
        let err = check_motions(&poses, &MotionThresholds::default()).unwrap_err();
        assert_eq!(err, CalibError::NonFinite("base_from_flange[2]".into()));
    }

    #[test]
    fn nan_rotation_is_non_finite() {
        let mut poses = good_poses();
        poses[1] = Iso3::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(f64::NAN, 0.0, 0.0, 0.0)),
        );
        let err = check_motions(&poses, &MotionThresholds::default()).unwrap_err();
        assert!(matches!(err, CalibError::NonFinite(_)), "{err}");
    }

    #[test]
    fn stricter_thresholds_reject_what_defaults_accept() {
        let strict = MotionThresholds {
            min_axis_angle_deg: 89.9,
            ..MotionThresholds::default()
        };
        let poses = vec![
            pose([0.5, 0.0, 0.3], Vector3::x(), 0.0),
            pose([0.5, 0.1, 0.3], Vector3::x(), 30.0),
            pose([0.5, 0.2, 0.3], Vector3::new(1.0, 0.3, 0.0), 30.0),
        ];
        assert!(check_motions(&poses, &MotionThresholds::default()).is_ok());
        let err = check_motions(&poses, &strict).unwrap_err();
        assert!(
            matches!(err, CalibError::ParallelRotationAxes { .. }),
            "{err}"
        );
    }

    #[test]
    fn axis_angle_search_is_within_factor_two_of_exact() {
        // Axes fanned out in a plane: the exact maximum is the fan's width.
        let poses: Vec<Iso3> = std::iter::once(pose([0.0; 3], Vector3::x(), 0.0))
            .chain((0..7).map(|k| {
                let phi = (10.0 * k as f64).to_radians();
                pose(
                    [0.1 * k as f64, 0.0, 0.0],
                    Vector3::new(phi.cos(), phi.sin(), 0.0),
                    60.0,
                )
            }))
            .collect();
        let report = check_motions(&poses, &MotionThresholds::default()).unwrap();
        let mut axes = vec![];
        for i in 0..poses.len() {
            for j in (i + 1)..poses.len() {
                let rel = poses[j].rotation.inverse() * poses[i].rotation;
                if rel.angle() >= 5f64.to_radians() {
                    axes.push(rel.axis().unwrap().into_inner());
                }
            }
        }
        let mut exact = 0.0_f64;
        for a in &axes {
            for b in &axes {
                exact = exact.max(a.dot(b).abs().min(1.0).acos().to_degrees());
            }
        }
        assert!(report.max_axis_angle_deg <= exact + 1e-9);
        assert!(
            2.0 * report.max_axis_angle_deg >= exact - 1e-9,
            "{report:?} vs {exact}"
        );
    }
}
