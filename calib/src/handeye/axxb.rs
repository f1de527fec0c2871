//! The five AX = XB solvers. Each takes the relative motions of all capture pairs
//! (see the parent module for conventions and the sign rule) and returns
//! `flange_from_camera`.

use nalgebra::{
    Matrix3, Matrix4, Quaternion, SMatrix, SVector, SymmetricEigen, Translation3, UnitQuaternion,
    Vector3, Vector4,
};

use super::{
    Motion, normalize_rotation, quaternion_wxyz, solve_normal, translation_given_rotation,
};
use crate::pose::skew;
use crate::{CalibError, Iso3};

fn vector_part(q: &Vector4<f64>) -> Vector3<f64> {
    Vector3::new(q[1], q[2], q[3])
}

/// Tsai & Lenz: with `P = 2 sin(θ/2) axis` of each motion and the unknown
/// `u = tan(φ/2) axis` of `X`, every pair gives `skew(Pa + Pb) u = Pb - Pa`.
/// Least squares over the pairs, then `q = (1, u) / |(1, u)|`.
pub(super) fn tsai(pairs: &[Motion]) -> Result<Iso3, CalibError> {
    let mut ata = Matrix3::zeros();
    let mut atb = Vector3::zeros();
    for p in pairs.iter().filter(|p| p.sign_safe()) {
        let pa = 2.0 * vector_part(&p.qa);
        let pb = 2.0 * vector_part(&p.qb);
        let s = skew(&(pa + pb));
        let d = pb - pa;
        ata += s.transpose() * s;
        atb += s.transpose() * d;
    }
    let u = solve_normal(&ata, &atb, "Tsai rotation")?;
    let rotation = UnitQuaternion::from_quaternion(Quaternion::new(1.0, u.x, u.y, u.z));
    let t = translation_given_rotation(pairs, &rotation)?;
    Ok(Iso3::from_parts(Translation3::from(t), rotation))
}

/// Park & Martin: rotation vectors satisfy `log(Ra) = R log(Rb)`, so with
/// `M = Σ log(Rb) log(Ra)ᵀ` the rotation is the orthogonal polar factor of `Mᵀ`
/// (OpenCV writes it `(MᵀM)^(-1/2) Mᵀ`; the SVD form also guards against a
/// reflection).
pub(super) fn park(pairs: &[Motion]) -> Result<Iso3, CalibError> {
    let mut m = Matrix3::zeros();
    for p in pairs.iter().filter(|p| p.sign_safe()) {
        let a = quaternion_wxyz(&p.qa).scaled_axis();
        let b = quaternion_wxyz(&p.qb).scaled_axis();
        m += b * a.transpose();
    }
    let rotation = crate::pose::nearest_rotation(&m.transpose());
    let t = translation_given_rotation(pairs, &rotation)?;
    Ok(Iso3::from_parts(Translation3::from(t), rotation))
}

/// Left multiplication by `r` (w, x, y, z): `r ⊗ q = Q(r) q`.
fn quat_left(r: &Vector4<f64>) -> Matrix4<f64> {
    let (w, x, y, z) = (r[0], r[1], r[2], r[3]);
    Matrix4::new(w, -x, -y, -z, x, w, -z, y, y, z, w, -x, z, -y, x, w)
}

/// Right multiplication by `r` (w, x, y, z): `q ⊗ r = W(r) q`.
fn quat_right(r: &Vector4<f64>) -> Matrix4<f64> {
    let (w, x, y, z) = (r[0], r[1], r[2], r[3]);
    Matrix4::new(w, -x, -y, -z, x, w, z, -y, y, -z, w, x, z, y, -x, w)
}

/// Indices of eigenvalues in increasing order.
fn ascending(eigenvalues: &[f64]) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..eigenvalues.len()).collect();
    idx.sort_by(|&i, &j| eigenvalues[i].total_cmp(&eigenvalues[j]));
    idx
}

/// Horaud & Dornaika: `qa ⊗ q = q ⊗ qb` for every pair, so the unit quaternion
/// minimising `Σ |(Q(qa) - W(qb)) q|²` is the eigenvector of the smallest
/// eigenvalue.
pub(super) fn horaud(pairs: &[Motion]) -> Result<Iso3, CalibError> {
    let mut a = Matrix4::zeros();
    for p in pairs.iter().filter(|p| p.sign_safe()) {
        let d = quat_left(&p.qa) - quat_right(&p.qb);
        a += d.transpose() * d;
    }
    let eig = SymmetricEigen::new(a);
    let q: Vector4<f64> = eig
        .eigenvectors
        .column(ascending(eig.eigenvalues.as_slice())[0])
        .into_owned();
    let rotation = quaternion_wxyz(&q);
    let t = translation_given_rotation(pairs, &rotation)?;
    Ok(Iso3::from_parts(Translation3::from(t), rotation))
}

/// Andreff, Horaud & Espiau: with `vec` the row-major vectorisation,
/// `Ra R = R Rb` is `(I₉ - Ra ⊗ Rb) vec(R) = 0` and `Ra t + ta = R tb + t` is
/// `(I₃ ⊗ tbᵀ) vec(R) + (I₃ - Ra) t = ta`. One linear least squares in the 12
/// unknowns (the translation rows fix the scale of `vec(R)`), then `R` is scaled
/// to `det = +1` and projected onto SO(3); `t` comes from the same solution.
pub(super) fn andreff(pairs: &[Motion]) -> Result<Iso3, CalibError> {
    let mut ata = SMatrix::<f64, 12, 12>::zeros();
    let mut atb = SVector::<f64, 12>::zeros();
    for p in pairs {
        // Rotation rows: (I - K)ᵀ(I - K) = 2I - K - Kᵀ because KᵀK = I for
        // K = Ra ⊗ Rb with orthonormal Ra, Rb.
        let k = kron(&p.ra, &p.rb);
        let rot_block = 2.0 * SMatrix::<f64, 9, 9>::identity() - k - k.transpose();
        let mut top = ata.fixed_view_mut::<9, 9>(0, 0);
        top += rot_block;
        // Translation rows [I₃ ⊗ tbᵀ, I₃ - Ra] x = ta.
        let mut j = SMatrix::<f64, 3, 12>::zeros();
        for r in 0..3 {
            for c in 0..3 {
                j[(r, 3 * r + c)] = p.tb[c];
            }
        }
        j.fixed_view_mut::<3, 3>(0, 9)
            .copy_from(&(Matrix3::identity() - p.ra));
        ata += j.transpose() * j;
        atb += j.transpose() * p.ta;
    }
    let x = solve_normal(&ata, &atb, "Andreff")?;
    let r = Matrix3::new(x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7], x[8]);
    let rotation = normalize_rotation(&r, "Andreff")?;
    Ok(Iso3::from_parts(
        Translation3::new(x[9], x[10], x[11]),
        rotation,
    ))
}

/// `a ⊗ b` for 3x3 matrices.
pub(super) fn kron(a: &Matrix3<f64>, b: &Matrix3<f64>) -> SMatrix<f64, 9, 9> {
    SMatrix::<f64, 9, 9>::from_fn(|r, c| a[(r / 3, c / 3)] * b[(r % 3, c % 3)])
}

/// The dual quaternion (real, dual) of a motion with the real part's sign fixed
/// (`w >= 0`): `dual = ½ (0, t) ⊗ real`.
fn dual_part(q: &Vector4<f64>, t: &Vector3<f64>) -> Vector4<f64> {
    let real = Quaternion::new(q[0], q[1], q[2], q[3]);
    let d = Quaternion::new(0.0, t.x, t.y, t.z) * real * 0.5;
    Vector4::new(d.w, d.i, d.j, d.k)
}

/// Daniilidis: with `a, a'` (`b, b'`) the vector parts of the real and dual parts
/// of `A` (`B`), the unknown dual quaternion `(q, q')` of `X` satisfies
/// `[a-b, [a+b]x, 0, 0; a'-b', [a'+b']x, a-b, [a+b]x] (q; q') = 0`. The stacked
/// system has a two-dimensional null space `α v₁ + β v₂`; the constraints
/// `|q| = 1` and `q·q' = 0` fix `α, β` up to a common sign.
pub(super) fn daniilidis(pairs: &[Motion]) -> Result<Iso3, CalibError> {
    let mut tt = SMatrix::<f64, 8, 8>::zeros();
    for p in pairs.iter().filter(|p| p.sign_safe()) {
        let a = vector_part(&p.qa);
        let b = vector_part(&p.qb);
        let a_d = vector_part(&dual_part(&p.qa, &p.ta));
        let b_d = vector_part(&dual_part(&p.qb, &p.tb));
        let mut s = SMatrix::<f64, 6, 8>::zeros();
        s.fixed_view_mut::<3, 1>(0, 0).copy_from(&(a - b));
        s.fixed_view_mut::<3, 3>(0, 1).copy_from(&skew(&(a + b)));
        s.fixed_view_mut::<3, 1>(3, 0).copy_from(&(a_d - b_d));
        s.fixed_view_mut::<3, 3>(3, 1)
            .copy_from(&skew(&(a_d + b_d)));
        s.fixed_view_mut::<3, 1>(3, 4).copy_from(&(a - b));
        s.fixed_view_mut::<3, 3>(3, 5).copy_from(&skew(&(a + b)));
        tt += s.transpose() * s;
    }
    let eig = SymmetricEigen::new(tt);
    let order = ascending(eig.eigenvalues.as_slice());
    let v1: SVector<f64, 8> = eig.eigenvectors.column(order[0]).into_owned();
    let v2: SVector<f64, 8> = eig.eigenvectors.column(order[1]).into_owned();
    let u1: Vector4<f64> = v1.fixed_rows::<4>(0).into_owned();
    let d1: Vector4<f64> = v1.fixed_rows::<4>(4).into_owned();
    let u2: Vector4<f64> = v2.fixed_rows::<4>(0).into_owned();
    let d2: Vector4<f64> = v2.fixed_rows::<4>(4).into_owned();

    // q·q' = 0 for q = α u1 + β u2, q' = α d1 + β d2:
    // a α² + b αβ + c β² = 0. Homogeneous roots, stable for any a, c.
    let qa = u1.dot(&d1);
    let qb = u1.dot(&d2) + u2.dot(&d1);
    let qc = u2.dot(&d2);
    let disc = (qb * qb - 4.0 * qa * qc).max(0.0);
    let h = -0.5 * (qb + qb.signum() * disc.sqrt());
    let candidates = [(h, qa), (qc, h)];
    // Of the two roots take the one whose real part carries the larger share of
    // the (unit) null-space vector: the other root is the spurious solution with
    // a (nearly) vanishing real part.
    let best = candidates
        .iter()
        .filter(|(al, be)| al.abs() + be.abs() > 0.0)
        .map(|&(al, be)| {
            let real = al * u1 + be * u2;
            (real.norm_squared() / (al * al + be * be), al, be)
        })
        .fold(None::<(f64, f64, f64)>, |acc, c| match acc {
            Some(a) if a.0 >= c.0 => Some(a),
            _ => Some(c),
        })
        .ok_or(CalibError::SolverBreakdown {
            method: "Daniilidis",
            reason: "the null space gives no dual quaternion",
        })?;
    let (_, al, be) = best;
    let real = al * u1 + be * u2;
    let dual = al * d1 + be * d2;
    let norm = real.norm();
    if norm.is_nan() || norm <= 1e-12 {
        return Err(CalibError::SolverBreakdown {
            method: "Daniilidis",
            reason: "the dual-quaternion solution has a vanishing rotation part",
        });
    }
    let (real, dual) = (real / norm, dual / norm);
    let q = Quaternion::new(real[0], real[1], real[2], real[3]);
    let qd = Quaternion::new(dual[0], dual[1], dual[2], dual[3]);
    let t = (qd * q.conjugate() * 2.0).imag();
    Ok(Iso3::from_parts(
        Translation3::from(t),
        UnitQuaternion::new_unchecked(q),
    ))
}
