//! Checks that name the likely cause of input that would give a confident,
//! wrong result, from one robot's flange poses and board poses alone (before
//! any fit), each with the numbers that show it.
//!
//! [`crate::sanity`] checks invariants of `A X = X B` that hold whatever `X` is.
//! These checks fit the parts of `X` that the poses determine linearly and ask
//! what a *single* `X` cannot explain:
//!
//! - [`fit_rotation_axes`]: the rotation of the hand-eye from the screw axes of
//!   the motions alone (`axis_A = R_X axis_B` for every pair). With the flange
//!   poses written inverted (`T_flange_base` instead of `T_base_flange`) every
//!   motion keeps its angle and pitch (so the sanity check passes), but no
//!   single rotation maps the camera's axes onto the robot's: the axes fit
//!   badly as given and well inverted ([`inverted_poses`]).
//! - [`fit_positions`]: with that rotation, the target's position in the base
//!   is linear in the unknowns (target position, hand-eye translation and a
//!   scale of the board poses' translations): `p = t_i + R_i t_X + R_i R_X
//!   (s · c_i)`. The scale `s` is the board's printed size over its declared
//!   size (from the robot's metric motions), with its standard error; a shift
//!   of every capture after one row ([`ChangePoint`]: a mount, tool or base
//!   that moved mid-run) is the step that best explains the residuals.
//!
//! Every check is linear in the number of captures: pairs are formed with a
//! few strides, never all of them.

use nalgebra::{DMatrix, DVector, Matrix3, UnitQuaternion, Vector3};

use crate::Iso3;
use crate::metrics::median;

/// Relative motions with a rotation below this (or within it of a half turn)
/// have screw axes too noisy to compare.
pub const MIN_AXIS_ANGLE_RAD: f64 = 0.2; // about 11°

/// The strides of the capture pairs compared: `(i, i + s)` for each `s`, plus
/// half the number of captures.
const STRIDES: [usize; 5] = [1, 2, 3, 5, 8];

/// The rotation of the hand-eye fitted to the motions' screw axes, and how
/// well it fits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisFit {
    /// `R_X`: the camera's orientation in the flange frame.
    pub flange_from_camera: UnitQuaternion<f64>,
    /// Median over the pairs of the angle between the robot's screw axis and
    /// the camera's mapped by `R_X` (radians).
    pub median_residual_rad: f64,
    /// Pairs compared.
    pub pairs: usize,
}

/// The capture pairs compared, `(i, j)` with `i < j`: a few strides, so the
/// count is linear in `n`.
fn pairs(n: usize) -> Vec<(usize, usize)> {
    let mut strides: Vec<usize> = STRIDES.to_vec();
    strides.push(n / 2);
    strides.sort_unstable();
    strides.dedup();
    strides
        .into_iter()
        .filter(|s| *s > 0)
        .flat_map(|s| (0..n.saturating_sub(s)).map(move |i| (i, i + s)))
        .collect()
}

/// The unit screw axis and angle of a rotation.
fn axis_angle(q: &UnitQuaternion<f64>) -> Option<(Vector3<f64>, f64)> {
    q.axis_angle().map(|(a, angle)| (a.into_inner(), angle))
}

/// `R_X` from the screw axes of the motions `A = base_from_flange[i]⁻¹
/// base_from_flange[j]` and `B = camera_from_target[i] camera_from_target[j]⁻¹`
/// (`axis_A = R_X axis_B`), by the weighted orthogonal Procrustes solution.
/// `None` with fewer than three pairs whose rotations are far enough from
/// zero and from a half turn, or axes that span no plane.
pub fn fit_rotation_axes(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
) -> Option<AxisFit> {
    let n = base_from_flange.len().min(camera_from_target.len());
    let mut axes: Vec<(Vector3<f64>, Vector3<f64>)> = Vec::new();
    for (i, j) in pairs(n) {
        let a = base_from_flange[i].rotation.inverse() * base_from_flange[j].rotation;
        let b = camera_from_target[i].rotation * camera_from_target[j].rotation.inverse();
        let (Some((axis_a, angle_a)), Some((axis_b, angle_b))) = (axis_angle(&a), axis_angle(&b))
        else {
            continue;
        };
        let usable = |angle: f64| {
            angle > MIN_AXIS_ANGLE_RAD && angle < std::f64::consts::PI - MIN_AXIS_ANGLE_RAD
        };
        if usable(angle_a) && usable(angle_b) {
            axes.push((axis_a, axis_b));
        }
    }
    if axes.len() < 3 {
        return None;
    }
    let m: Matrix3<f64> = axes.iter().map(|(a, b)| a * b.transpose()).sum();
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut sorted = svd.singular_values;
    sorted
        .as_mut_slice()
        .sort_unstable_by(|a, b| b.total_cmp(a));
    // The axes must span at least a plane for R_X to be defined.
    if sorted[1] < 1e-3 * sorted[0] {
        return None;
    }
    let d = (u * v_t).determinant().signum();
    let r = u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * v_t;
    let rotation = UnitQuaternion::from_matrix(&r);
    let mut residuals: Vec<f64> = axes.iter().map(|(a, b)| a.angle(&(rotation * b))).collect();
    Some(AxisFit {
        flange_from_camera: rotation,
        median_residual_rad: median(&mut residuals),
        pairs: axes.len(),
    })
}

/// The evidence that flange poses were written inverted: the screw axes'
/// fit as given and as inverted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Inversion {
    pub given: AxisFit,
    pub inverted: AxisFit,
}

impl Inversion {
    /// One line of evidence.
    pub fn describe(&self) -> String {
        format!(
            "no single camera orientation maps the camera's motions onto the robot's: their \
             screw axes disagree by a median {:.2}° as given, {:.2}° with every pose inverted \
             ({} motions compared)",
            self.given.median_residual_rad.to_degrees(),
            self.inverted.median_residual_rad.to_degrees(),
            self.given.pairs
        )
    }
}

/// A median axis misfit above this (as given) is not noise: real arms and
/// cameras give about 0.5° on motions of at least [`MIN_AXIS_ANGLE_RAD`]
/// (ViSP's Franka 0.48°, Tabb's Denso 0.63°; a rendered set 0.015°).
pub const INVERTED_GIVEN_MIN_RAD: f64 = 0.035; // 2°
/// The inverted poses must fit at least this many times better (a rendered
/// set written inverted: 8.0° as given, 0.015° inverted).
pub const INVERTED_RATIO: f64 = 10.0;

/// `Some` when the flange poses fit far better inverted than as given (see
/// the module docs): the given axes misfit by more than
/// [`INVERTED_GIVEN_MIN_RAD`] and the inverted ones by [`INVERTED_RATIO`]
/// times less. Eye-to-hand data (the camera fixed, the target on the flange)
/// looks the same.
pub fn inverted_poses(base_from_flange: &[Iso3], camera_from_target: &[Iso3]) -> Option<Inversion> {
    let given = fit_rotation_axes(base_from_flange, camera_from_target)?;
    if given.median_residual_rad < INVERTED_GIVEN_MIN_RAD {
        return None;
    }
    let flange_from_base: Vec<Iso3> = base_from_flange.iter().map(Iso3::inverse).collect();
    let inverted = fit_rotation_axes(&flange_from_base, camera_from_target)?;
    (inverted.median_residual_rad * INVERTED_RATIO < given.median_residual_rad)
        .then_some(Inversion { given, inverted })
}

/// A shift of the target's position in the base from one capture on: the
/// flange poses (or the base, or the camera mount) changed mid-run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChangePoint {
    /// The first capture (index into the input) after the change.
    pub index: usize,
    /// The shift, in the base frame (m).
    pub shift: Vector3<f64>,
    /// The residual RMS per axis without the step and with it (m).
    pub rms_without_m: f64,
    pub rms_with_m: f64,
    /// The F statistic of the step (3 and `3n - 10` degrees of freedom).
    pub f: f64,
}

/// The target's positions fitted linearly (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct PositionFit {
    /// Captures fitted.
    pub captures: usize,
    /// The scale of the board poses' translations that fits the robot's
    /// motions: the board's printed size over its declared size.
    pub scale: f64,
    /// Its standard error (from the residuals).
    pub scale_sigma: f64,
    /// The scales along the camera's optical axis and across it (a focal
    /// length error scales the first only; a board's size both).
    pub scale_along: f64,
    pub scale_along_sigma: f64,
    pub scale_across: f64,
    pub scale_across_sigma: f64,
    /// Residual RMS per axis (m).
    pub rms_m: f64,
    /// The step that best explains the residuals, when any could be fitted
    /// (each side at least [`MIN_SEGMENT`] captures); whether it is real is
    /// the caller's decision ([`ChangePoint::f`], its size).
    pub change: Option<ChangePoint>,
}

/// The fewest captures on either side of a change point.
pub const MIN_SEGMENT: usize = 3;

/// Weighted least squares `y ≈ J θ` from the accumulated normal equations:
/// `θ`, its covariance factor `N⁻¹` and the residual sum of squares.
fn solve_normal(
    n: &DMatrix<f64>,
    b: &DVector<f64>,
    yy: f64,
) -> Option<(DVector<f64>, DMatrix<f64>, f64)> {
    let inv = n.clone().try_inverse()?;
    let theta = &inv * b;
    let rss = (yy - b.dot(&theta)).max(0.0);
    Some((theta, inv, rss))
}

/// Fits the target's position in the base, the hand-eye's translation and the
/// scales of the board poses' translations, given `flange_from_camera`'s
/// rotation (see the module docs), and scans for a change point. `None` with
/// fewer than six captures or a singular problem.
pub fn fit_positions(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
    flange_from_camera: &UnitQuaternion<f64>,
) -> Option<PositionFit> {
    let n = base_from_flange.len().min(camera_from_target.len());
    if n < 6 {
        return None;
    }
    // Per capture: y_i = t_i; columns p (3), t_X (3), then the board
    // translation's part across the optical axis and along it.
    let rows = |i: usize| -> (DMatrix<f64>, Vector3<f64>) {
        let r = base_from_flange[i].rotation.to_rotation_matrix();
        let c = camera_from_target[i].translation.vector;
        let across = r * (flange_from_camera * Vector3::new(c.x, c.y, 0.0));
        let along = r * (flange_from_camera * Vector3::new(0.0, 0.0, c.z));
        let mut j = DMatrix::zeros(3, 8);
        j.view_mut((0, 0), (3, 3)).copy_from(&Matrix3::identity());
        j.view_mut((0, 3), (3, 3)).copy_from(&(-r.matrix()));
        j.view_mut((0, 6), (3, 1)).copy_from(&(-across));
        j.view_mut((0, 7), (3, 1)).copy_from(&(-along));
        (j, base_from_flange[i].translation.vector)
    };
    let per: Vec<(DMatrix<f64>, Vector3<f64>)> = (0..n).map(rows).collect();
    // The two-scale model, and the one-scale model (the last two columns summed).
    let one_scale = |j: &DMatrix<f64>| -> DMatrix<f64> {
        let mut k = j.columns(0, 7).into_owned();
        let sum = j.column(6) + j.column(7);
        k.set_column(6, &sum);
        k
    };
    let accumulate = |m: usize, f: &dyn Fn(&DMatrix<f64>) -> DMatrix<f64>| {
        let mut nn = DMatrix::zeros(m, m);
        let mut b = DVector::zeros(m);
        let mut yy = 0.0;
        for (j, y) in &per {
            let j = f(j);
            nn += j.transpose() * &j;
            b += j.transpose() * y;
            yy += y.norm_squared();
        }
        (nn, b, yy)
    };
    let (n2, b2, yy) = accumulate(8, &|j: &DMatrix<f64>| j.clone());
    let (theta2, inv2, rss2) = solve_normal(&n2, &b2, yy)?;
    let dof2 = (3 * n - 8) as f64;
    let s2 = rss2 / dof2;
    let (n1, b1, _) = accumulate(7, &one_scale);
    let (theta1, inv1, rss1) = solve_normal(&n1, &b1, yy)?;
    let dof1 = (3 * n - 7) as f64;
    let s1 = rss1 / dof1;
    // The change-point scan on the one-scale model: the step's column is the
    // identity for captures at and after k. Suffix sums of J_iᵀ and y_i give
    // every k's normal equations in O(n).
    let mut change: Option<ChangePoint> = None;
    if n >= 2 * MIN_SEGMENT + 2 {
        let mut suffix_jt = DMatrix::<f64>::zeros(7, 3);
        let mut suffix_y = Vector3::zeros();
        let mut count = 0usize;
        for k in (MIN_SEGMENT..n).rev() {
            let (j, y) = &per[k];
            suffix_jt += one_scale(j).transpose();
            suffix_y += y;
            count += 1;
            if count < MIN_SEGMENT || n - count < MIN_SEGMENT {
                continue;
            }
            let mut nn = DMatrix::zeros(10, 10);
            nn.view_mut((0, 0), (7, 7)).copy_from(&n1);
            nn.view_mut((0, 7), (7, 3)).copy_from(&suffix_jt);
            nn.view_mut((7, 0), (3, 7))
                .copy_from(&suffix_jt.transpose());
            nn.view_mut((7, 7), (3, 3))
                .copy_from(&(Matrix3::identity() * count as f64));
            let mut b = DVector::zeros(10);
            b.rows_mut(0, 7).copy_from(&b1);
            b.rows_mut(7, 3).copy_from(&suffix_y);
            let Some((theta, _, rss)) = solve_normal(&nn, &b, yy) else {
                continue;
            };
            let dof = (3 * n - 10) as f64;
            let f = ((rss1 - rss).max(0.0) / 3.0) / (rss / dof).max(1e-30);
            if change.is_none_or(|c| f > c.f) {
                change = Some(ChangePoint {
                    index: k,
                    shift: Vector3::new(theta[7], theta[8], theta[9]),
                    rms_without_m: (rss1 / (3 * n) as f64).sqrt(),
                    rms_with_m: (rss / (3 * n) as f64).sqrt(),
                    f,
                });
            }
        }
    }
    Some(PositionFit {
        captures: n,
        scale: theta1[6],
        scale_sigma: (s1 * inv1[(6, 6)]).max(0.0).sqrt(),
        scale_across: theta2[6],
        scale_across_sigma: (s2 * inv2[(6, 6)]).max(0.0).sqrt(),
        scale_along: theta2[7],
        scale_along_sigma: (s2 * inv2[(7, 7)]).max(0.0).sqrt(),
        rms_m: (rss1 / (3 * n) as f64).sqrt(),
        change,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Captures of a target seen by a flange camera from varied poses, with
    /// noise: (base_from_flange, camera_from_target).
    fn captures(n: usize, seed: u64, noise_m: f64) -> (Vec<Iso3>, Vec<Iso3>, Iso3) {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let flange_from_camera = Iso3::new(
            Vector3::new(0.03, -0.05, 0.08),
            Vector3::new(0.1, -0.2, 1.4),
        );
        let base_from_target = Iso3::new(Vector3::new(0.7, 0.1, 0.0), Vector3::new(0.0, 0.0, 0.3));
        let mut flanges = Vec::new();
        let mut boards = Vec::new();
        for _ in 0..n {
            // A camera about half a metre above the target, looking down, turned.
            let camera_from_target = Iso3::new(
                Vector3::new(
                    rng.random_range(-0.08..0.08),
                    rng.random_range(-0.06..0.06),
                    rng.random_range(0.4..0.7),
                ),
                Vector3::new(
                    rng.random_range(-0.5..0.5),
                    rng.random_range(-0.5..0.5),
                    rng.random_range(-1.5..1.5),
                ),
            );
            let base_from_flange =
                base_from_target * camera_from_target.inverse() * flange_from_camera.inverse();
            let jitter = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ) * noise_m;
            flanges.push(Iso3::from_parts(
                (base_from_flange.translation.vector + jitter).into(),
                base_from_flange.rotation,
            ));
            boards.push(camera_from_target);
        }
        (flanges, boards, flange_from_camera)
    }

    #[test]
    fn the_axes_give_the_hand_eyes_rotation_and_inverted_poses_are_named() {
        let (flanges, boards, x) = captures(15, 1, 5e-4);
        let fit = fit_rotation_axes(&flanges, &boards).unwrap();
        assert!(fit.flange_from_camera.angle_to(&x.rotation) < 1e-6);
        assert!(fit.median_residual_rad < 1e-6);
        assert_eq!(inverted_poses(&flanges, &boards), None);
        let inverted: Vec<Iso3> = flanges.iter().map(Iso3::inverse).collect();
        let found = inverted_poses(&inverted, &boards).expect("named");
        assert!(found.given.median_residual_rad > 0.3, "{found:?}");
        assert!(found.inverted.median_residual_rad < 1e-6, "{found:?}");
    }

    #[test]
    fn the_board_scale_and_a_change_point_are_found() {
        let (flanges, boards, x) = captures(20, 2, 5e-4);
        let fit = fit_positions(&flanges, &boards, &x.rotation).unwrap();
        assert!(
            (fit.scale - 1.0).abs() < 5.0 * fit.scale_sigma + 1e-3,
            "{fit:?}"
        );
        assert!(fit.scale_sigma < 5e-3, "{fit:?}");
        // A board printed 4% large: PnP with the declared size sees every
        // translation 4% short.
        let small: Vec<Iso3> = boards
            .iter()
            .map(|b| Iso3::from_parts((b.translation.vector / 1.04).into(), b.rotation))
            .collect();
        let fit = fit_positions(&flanges, &small, &x.rotation).unwrap();
        assert!((fit.scale - 1.04).abs() < 4.0 * fit.scale_sigma, "{fit:?}");
        assert!(
            (fit.scale_along - 1.04).abs() < 4.0 * fit.scale_along_sigma,
            "{fit:?}"
        );
        // The last 8 rows 5 cm off in x.
        let mut moved = flanges.clone();
        for f in &mut moved[12..] {
            f.translation.vector.x += 0.05;
        }
        let fit = fit_positions(&moved, &boards, &x.rotation).unwrap();
        let c = fit.change.unwrap();
        assert_eq!(c.index, 12, "{c:?}");
        assert!((c.shift.x - 0.05).abs() < 2e-3, "{c:?}");
        assert!(c.f > 100.0, "{c:?}");
    }
}
