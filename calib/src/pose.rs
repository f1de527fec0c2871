//! Pose conversions, the left perturbation, rotation averaging and distances.
//!
//! One perturbation convention serves the whole project, because covariances are
//! exchanged between crates and written to files: a 6-vector
//! `delta = [rx, ry, rz, tx, ty, tz]` acts on the **left** of a pose,
//! `perturbed = Translation(t) * Rotation(exp(r)) * pose`, so a point `p` expressed
//! in the pose's output frame moves by `r × p + t` to first order. That is exactly
//! the error model needed to predict touch-point errors in `base1`.

use nalgebra::{
    Matrix3, Matrix4, Point3, Rotation3, SymmetricEigen, Translation3, UnitQuaternion, Vector3,
    Vector6,
};

use crate::{CalibError, Iso3};

/// Builds an isometry from a translation and a quaternion written x, y, z, w.
/// The quaternion is normalised; callers validate its norm beforehand.
pub fn iso_from_xyzw(t: [f64; 3], q: [f64; 4]) -> Iso3 {
    let [x, y, z, w] = q;
    Iso3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z)),
    )
}

/// The quaternion of a pose as x, y, z, w with w >= 0.
pub fn xyzw(a_from_b: &Iso3) -> [f64; 4] {
    let q = a_from_b.rotation.quaternion();
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    [s * q.i, s * q.j, s * q.k, s * q.w]
}

/// Builds an isometry from a translation and a rotation vector (axis * angle,
/// OpenCV's Rodrigues vector, ViSP's theta-u).
pub fn iso_from_rotation_vector(t: [f64; 3], r: [f64; 3]) -> Iso3 {
    Iso3::new(Vector3::from(t), Vector3::from(r))
}

/// The rotation vector (axis * angle, angle in [0, pi]) of a rotation.
pub fn rotation_vector(r: &UnitQuaternion<f64>) -> Vector3<f64> {
    r.scaled_axis()
}

/// The homogeneous 4x4 matrix of a pose.
pub fn to_matrix4(a_from_b: &Iso3) -> Matrix4<f64> {
    a_from_b.to_homogeneous()
}

/// Reads a homogeneous 4x4 matrix. The rotation block must be orthonormal with
/// determinant +1 to within `tol` (Frobenius norm of `R^T R - I`), and the last
/// row must be `0 0 0 1`.
pub fn from_matrix4(m: &Matrix4<f64>, tol: f64) -> Result<Iso3, CalibError> {
    if m.iter().any(|v| !v.is_finite()) {
        return Err(CalibError::NonFinite("4x4 matrix".into()));
    }
    let last = m.row(3);
    if (last[0].abs() + last[1].abs() + last[2].abs() + (last[3] - 1.0).abs()) > tol {
        return Err(CalibError::NotHomogeneous {
            last_row: [last[0], last[1], last[2], last[3]],
        });
    }
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into();
    rotation_from_matrix(&r, tol)
        .map(|rot| Iso3::from_parts(Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]), rot))
}

/// Reads a rotation matrix, checking orthonormality and handedness to within `tol`.
pub fn rotation_from_matrix(r: &Matrix3<f64>, tol: f64) -> Result<UnitQuaternion<f64>, CalibError> {
    let ortho = (r.transpose() * r - Matrix3::identity()).norm();
    if ortho > tol {
        return Err(CalibError::NotOrthonormal { deviation: ortho });
    }
    if r.determinant() < 0.0 {
        return Err(CalibError::Reflection);
    }
    Ok(nearest_rotation(r))
}

/// The rotation nearest to a 3x3 matrix in the Frobenius sense (SVD projection).
pub fn nearest_rotation(m: &Matrix3<f64>) -> UnitQuaternion<f64> {
    let svd = m.svd(true, true);
    nearest_rotation_from_svd(&svd.u, &svd.v_t)
}

/// [`nearest_rotation`] from the matrix's SVD factors `U` and `Vᵀ`, for callers
/// that need the SVD anyway (identity when either is missing).
pub fn nearest_rotation_from_svd(
    u: &Option<Matrix3<f64>>,
    v_t: &Option<Matrix3<f64>>,
) -> UnitQuaternion<f64> {
    let (Some(u), Some(v_t)) = (u, v_t) else {
        return UnitQuaternion::identity();
    };
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(u * d * v_t))
}

/// KUKA's A, B, C angles (radians): `R = Rz(A) * Ry(B) * Rx(C)`.
pub fn rotation_from_kuka_abc(a: f64, b: f64, c: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), a)
        * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), b)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), c)
}

/// The KUKA A, B, C angles (radians) of a rotation, with B in [-pi/2, pi/2].
/// At B = ±pi/2 (gimbal lock) C is set to 0 and A takes the whole yaw.
pub fn kuka_abc(r: &UnitQuaternion<f64>) -> [f64; 3] {
    let m = r.to_rotation_matrix();
    let m = m.matrix();
    let sb = (-m[(2, 0)]).clamp(-1.0, 1.0);
    let b = sb.asin();
    if (1.0 - sb.abs()) < 1e-12 {
        let a = (-m[(0, 1)]).atan2(m[(1, 1)]);
        [a, b, 0.0]
    } else {
        let a = m[(1, 0)].atan2(m[(0, 0)]);
        let c = m[(2, 1)].atan2(m[(2, 2)]);
        [a, b, c]
    }
}

/// A KUKA frame (X, Y, Z in metres, A, B, C in radians) as an isometry.
pub fn iso_from_kuka_frame(xyz: [f64; 3], abc: [f64; 3]) -> Iso3 {
    Iso3::from_parts(
        Translation3::from(Vector3::from(xyz)),
        rotation_from_kuka_abc(abc[0], abc[1], abc[2]),
    )
}

/// Applies a left perturbation `[rx, ry, rz, tx, ty, tz]` (see the module docs).
pub fn perturb_left(delta: &Vector6<f64>, a_from_b: &Iso3) -> Iso3 {
    let r = Vector3::new(delta[0], delta[1], delta[2]);
    let t = Vector3::new(delta[3], delta[4], delta[5]);
    Iso3::from_parts(Translation3::from(t), UnitQuaternion::from_scaled_axis(r)) * a_from_b
}

/// The left perturbation that takes `reference` to `perturbed`
/// (the inverse of [`perturb_left`]).
pub fn left_difference(perturbed: &Iso3, reference: &Iso3) -> Vector6<f64> {
    let d = perturbed * reference.inverse();
    let r = d.rotation.scaled_axis();
    let t = d.translation.vector;
    Vector6::new(r.x, r.y, r.z, t.x, t.y, t.z)
}

/// The geodesic angle between two rotations, radians in [0, pi].
pub fn geodesic_angle(a: &UnitQuaternion<f64>, b: &UnitQuaternion<f64>) -> f64 {
    a.angle_to(b)
}

/// Translation distance (metres) and rotation angle (radians) between two poses.
pub fn pose_distance(a: &Iso3, b: &Iso3) -> (f64, f64) {
    (
        (a.translation.vector - b.translation.vector).norm(),
        geodesic_angle(&a.rotation, &b.rotation),
    )
}

/// The weighted chordal-L2 mean of rotations (Markley's quaternion average: the
/// principal eigenvector of `sum w_i q_i q_i^T`). Sign-invariant in each `q_i`.
pub fn average_rotations(
    rotations: &[UnitQuaternion<f64>],
    weights: Option<&[f64]>,
) -> Result<UnitQuaternion<f64>, CalibError> {
    if rotations.is_empty() {
        return Err(CalibError::TooFewCaptures { got: 0, need: 1 });
    }
    if let Some(w) = weights
        && w.len() != rotations.len()
    {
        return Err(CalibError::MismatchedLengths {
            len_a: rotations.len(),
            what_a: "rotations",
            len_b: w.len(),
            what_b: "weights",
        });
    }
    let mut m = Matrix4::<f64>::zeros();
    for (i, q) in rotations.iter().enumerate() {
        let w = weights.map_or(1.0, |w| w[i]);
        if !w.is_finite() || w < 0.0 {
            return Err(CalibError::BadWeight { index: i, value: w });
        }
        let v = q.quaternion().coords;
        m += w * v * v.transpose();
    }
    let eig = SymmetricEigen::new(m);
    let (imax, _) =
        eig.eigenvalues
            .iter()
            .enumerate()
            .fold((0, f64::NEG_INFINITY), |(bi, bv), (i, &v)| {
                if v > bv { (i, v) } else { (bi, bv) }
            });
    let v = eig.eigenvectors.column(imax);
    Ok(UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        v[3], v[0], v[1], v[2],
    )))
}

/// The adjoint of a pose for left perturbations ordered `[ω, v]`: perturbing by
/// `δ` on the left of `m * T` equals perturbing `T`'s image under `m` by
/// `adjoint(m) * δ`, i.e. `m · E(δ) · m⁻¹ = E(adjoint(m) δ)` to first order.
pub fn adjoint(m: &Iso3) -> nalgebra::Matrix6<f64> {
    let r = m.rotation.to_rotation_matrix().into_inner();
    let mut a = nalgebra::Matrix6::zeros();
    a.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    a.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    a.fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&(skew(&m.translation.vector) * r));
    a
}

/// The skew-symmetric matrix of `v`, so that `skew(v) * u = v × u`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// A camera at `eye` looking at `centre`, rolled about its view axis.
pub fn look_at(eye: &Point3<f64>, centre: &Point3<f64>, up_hint: &Vector3<f64>, roll: f64) -> Iso3 {
    let z = (centre - eye).normalize();
    // Image "down" (y) roughly along -up_hint projected on the image plane.
    let mut y = -(up_hint - z * z.dot(up_hint));
    if y.norm() < 1e-6 {
        y = z.cross(&Vector3::x());
    }
    let y = y.normalize();
    let x = y.cross(&z);
    let r = UnitQuaternion::from_matrix(&Matrix3::from_columns(&[x, y, z]))
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll);
    Iso3::from_parts(Translation3::from(eye.coords), r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn iso_strategy() -> impl Strategy<Value = Iso3> {
        (
            prop::array::uniform3(-2.0..2.0f64),
            prop::array::uniform3(-3.0..3.0f64),
        )
            .prop_map(|(t, r)| Iso3::new(Vector3::from(t), Vector3::from(r)))
    }

    proptest! {
        #[test]
        fn perturbation_round_trips(pose in iso_strategy(), d in prop::array::uniform6(-0.5..0.5f64)) {
            let delta = Vector6::from_row_slice(&d);
            let back = left_difference(&perturb_left(&delta, &pose), &pose);
            prop_assert!((back - delta).norm() < 1e-9, "{back} vs {delta}");
        }

        #[test]
        fn matrix4_round_trips(pose in iso_strategy()) {
            let back = from_matrix4(&to_matrix4(&pose), 1e-9).unwrap();
            let (dt, da) = pose_distance(&pose, &back);
            prop_assert!(dt < 1e-12 && da < 1e-9);
        }

        #[test]
        fn kuka_abc_round_trips(a in -3.1..3.1f64, b in -1.5..1.5f64, c in -3.1..3.1f64) {
            let q = rotation_from_kuka_abc(a, b, c);
            let [a2, b2, c2] = kuka_abc(&q);
            let q2 = rotation_from_kuka_abc(a2, b2, c2);
            prop_assert!(q.angle_to(&q2) < 1e-9);
        }

        #[test]
        fn xyzw_round_trips(pose in iso_strategy()) {
            let t = pose.translation.vector;
            let back = iso_from_xyzw([t.x, t.y, t.z], xyzw(&pose));
            prop_assert!(pose.rotation.angle_to(&back.rotation) < 1e-9);
        }
    }

    #[test]
    fn first_order_point_motion_matches_cross_product() {
        let pose = Iso3::new(Vector3::new(0.3, 0.1, -0.2), Vector3::new(0.2, -0.4, 1.0));
        let delta = Vector6::new(1e-6, -2e-6, 3e-6, 1e-5, 0.0, -1e-5);
        let p_in_b = nalgebra::Point3::new(0.5, -0.2, 0.7);
        let p = pose * p_in_b;
        let moved = perturb_left(&delta, &pose) * p_in_b;
        let r = Vector3::new(delta[0], delta[1], delta[2]);
        let t = Vector3::new(delta[3], delta[4], delta[5]);
        let predicted = r.cross(&p.coords) + t;
        assert!(((moved - p) - predicted).norm() < 1e-11);
    }

    #[test]
    fn adjoint_moves_a_perturbation_through_a_pose() {
        let m = Iso3::new(Vector3::new(0.2, -0.4, 0.7), Vector3::new(-0.3, 0.9, 0.4));
        let t = Iso3::new(Vector3::new(-0.1, 0.3, 0.2), Vector3::new(0.5, 0.1, -0.2));
        let delta = Vector6::new(1e-6, -2e-6, 1.5e-6, 3e-6, -1e-6, 2e-6);
        // m * E(delta) * t  ==  E(Ad(m) delta) * m * t
        let lhs = m * perturb_left(&delta, &t);
        let rhs = perturb_left(&(adjoint(&m) * delta), &(m * t));
        let (dt, da) = pose_distance(&lhs, &rhs);
        assert!(dt < 1e-11 && da < 1e-11, "{dt} {da}");
    }

    #[test]
    fn kuka_abc_matches_known_rotation() {
        // A = 90 deg about z only: x goes to y.
        let q = rotation_from_kuka_abc(std::f64::consts::FRAC_PI_2, 0.0, 0.0);
        let x = q * Vector3::x();
        assert!((x - Vector3::y()).norm() < 1e-12);
    }

    #[test]
    fn average_of_symmetric_rotations_is_the_middle() {
        let mid = UnitQuaternion::from_scaled_axis(Vector3::new(0.3, 0.2, -0.1));
        let e = Vector3::new(0.0, 0.05, 0.0);
        let a = UnitQuaternion::from_scaled_axis(e) * mid;
        // Sign flips must not matter.
        let b = UnitQuaternion::new_unchecked(
            -(UnitQuaternion::from_scaled_axis(-e) * mid).into_inner(),
        );
        let avg = average_rotations(&[a, b], None).unwrap();
        assert!(avg.angle_to(&mid) < 1e-9);
    }

    #[test]
    fn reflection_is_rejected() {
        let m = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert!(rotation_from_matrix(&m, 1e-6).is_err());
    }
}
