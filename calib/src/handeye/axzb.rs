//! The two AX = ZB solvers, in OpenCV's naming: per capture
//! `A = camera_from_target`, `B = flange_from_base`, unknowns
//! `X = target_from_base` and `Z = camera_from_flange`. Both return `(X, Z)`.

use nalgebra::{Matrix3, SMatrix, SVector, Translation3, Vector3};

use super::axxb::kron;
use super::{normalize_rotation, solve_normal};
use crate::{CalibError, Iso3};

struct Capture {
    ra: Matrix3<f64>,
    ta: Vector3<f64>,
    rb: Matrix3<f64>,
    tb: Vector3<f64>,
}

fn captures(base_from_flange: &[Iso3], camera_from_target: &[Iso3]) -> Vec<Capture> {
    base_from_flange
        .iter()
        .zip(camera_from_target)
        .map(|(bf, ct)| {
            let flange_from_base = bf.inverse();
            Capture {
                ra: *ct.rotation.to_rotation_matrix().matrix(),
                ta: ct.translation.vector,
                rb: *flange_from_base.rotation.to_rotation_matrix().matrix(),
                tb: flange_from_base.translation.vector,
            }
        })
        .collect()
}

/// Shah: `RZ = RA RX RBᵀ` is `vec(RZ) = (RB ⊗ RA) vec(RX)` (column-major `vec`),
/// so `Σ RB ⊗ RA` has `vec(RX)`, `vec(RZ)` as its top right / left singular
/// vectors (singular value `n`). Both are scaled to `det = +1` and projected onto
/// SO(3); then `-RA tX + tZ = tA - RZ tB` is a 6-unknown least squares.
pub(super) fn shah(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
) -> Result<(Iso3, Iso3), CalibError> {
    let caps = captures(base_from_flange, camera_from_target);
    let mut t = SMatrix::<f64, 9, 9>::zeros();
    for c in &caps {
        t += kron(&c.rb, &c.ra);
    }
    let svd = t.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(CalibError::SolverBreakdown {
            method: "Shah",
            reason: "SVD did not converge",
        });
    };
    // `svd` sorts singular values in descending order.
    let vx: Vec<f64> = v_t.row(0).iter().copied().collect();
    let vz: Vec<f64> = u.column(0).iter().copied().collect();
    let rx = normalize_rotation(&Matrix3::from_column_slice(&vx), "Shah X")?;
    let rz = normalize_rotation(&Matrix3::from_column_slice(&vz), "Shah Z")?;
    let rz_m = rz.to_rotation_matrix();

    let mut ata = SMatrix::<f64, 6, 6>::zeros();
    let mut atb = SVector::<f64, 6>::zeros();
    for c in &caps {
        let mut j = SMatrix::<f64, 3, 6>::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-c.ra));
        j.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&Matrix3::identity());
        let d = c.ta - rz_m * c.tb;
        ata += j.transpose() * j;
        atb += j.transpose() * d;
    }
    let x = solve_normal(&ata, &atb, "Shah translation")?;
    Ok((
        Iso3::from_parts(Translation3::new(x[0], x[1], x[2]), rx),
        Iso3::from_parts(Translation3::new(x[3], x[4], x[5]), rz),
    ))
}

/// Li, Wang & Wu: with row-major `vec`, `RA RX = RZ RB` is
/// `(RA ⊗ I) vec(RX) - (I ⊗ RBᵀ) vec(RZ) = 0` and `RA tX + tA = RZ tB + tZ` is
/// `(I ⊗ tBᵀ) vec(RZ) - RA tX + tZ = tA`. One linear least squares in the 24
/// unknowns; both rotation blocks are then scaled to `det = +1` and projected onto
/// SO(3), and the translations are taken from the same solution.
pub(super) fn li(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
) -> Result<(Iso3, Iso3), CalibError> {
    let caps = captures(base_from_flange, camera_from_target);
    let eye = Matrix3::identity();
    let mut ata = SMatrix::<f64, 24, 24>::zeros();
    let mut atb = SVector::<f64, 24>::zeros();
    for c in &caps {
        let mut j = SMatrix::<f64, 12, 24>::zeros();
        j.fixed_view_mut::<9, 9>(0, 0).copy_from(&kron(&c.ra, &eye));
        j.fixed_view_mut::<9, 9>(0, 9)
            .copy_from(&(-kron(&eye, &c.rb.transpose())));
        for r in 0..3 {
            for k in 0..3 {
                j[(9 + r, 9 + 3 * r + k)] = c.tb[k];
            }
        }
        j.fixed_view_mut::<3, 3>(9, 18).copy_from(&(-c.ra));
        j.fixed_view_mut::<3, 3>(9, 21).copy_from(&eye);
        let mut rhs = SVector::<f64, 12>::zeros();
        rhs.fixed_rows_mut::<3>(9).copy_from(&c.ta);
        ata += j.transpose() * j;
        atb += j.transpose() * rhs;
    }
    let x = solve_normal(&ata, &atb, "Li")?;
    let row_major = |o: usize| {
        Matrix3::new(
            x[o],
            x[o + 1],
            x[o + 2],
            x[o + 3],
            x[o + 4],
            x[o + 5],
            x[o + 6],
            x[o + 7],
            x[o + 8],
        )
    };
    let rx = normalize_rotation(&row_major(0), "Li X")?;
    let rz = normalize_rotation(&row_major(9), "Li Z")?;
    Ok((
        Iso3::from_parts(Translation3::new(x[18], x[19], x[20]), rx),
        Iso3::from_parts(Translation3::new(x[21], x[22], x[23]), rz),
    ))
}
