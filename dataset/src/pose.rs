//! Numbers and poses: the checks every coordinate in the format goes through.
//!
//! Two policies live here and nowhere else:
//!
//! * **Quaternions.** A quaternion whose norm is more than
//!   [`b2b_protocol::QUATERNION_NORM_TOLERANCE`] away from 1 is an error: it is not a
//!   rotation that lost some digits, it is a wrong column or a wrong convention. Inside
//!   the tolerance it is normalised, except when it is already unit to machine precision
//!   ([`UNIT_EXACT_TOLERANCE`]): then it is taken exactly as written. Normalising an
//!   already normalised quaternion can move its last bit, and that alone would break the
//!   promise that whatever this crate writes, it reads back bit for bit.
//! * **Units.** The format is in metres. A coordinate larger than
//!   [`crate::MAX_COORDINATE_M`] is far outside any robot cell and almost certainly
//!   millimetres (the unit most controllers print), so it is rejected with that hint
//!   instead of silently producing a calibration a thousand times off.
//!
//! Numbers are written with Rust's shortest round-trip formatting (`{:?}` of `f64`), never
//! with a fixed number of decimals, for the same bit-for-bit reason.

use b2b_protocol::{Pose, QUATERNION_NORM_TOLERANCE};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::MAX_COORDINATE_M;
use crate::error::{DatasetError, Location};

/// A quaternion whose norm is this close to 1 is used exactly as written.
pub const UNIT_EXACT_TOLERANCE: f64 = 8.0 * f64::EPSILON;

/// Names of the seven numbers of a pose in a file, in `t` then `q` (x, y, z, w) order.
pub(crate) type PoseFields<'a> = [&'a str; 7];

/// Builds a rotation from `[x, y, z, w]`, applying the quaternion policy.
pub(crate) fn unit_quaternion(
    xyzw: [f64; 4],
    at: impl FnOnce() -> Location,
) -> Result<UnitQuaternion<f64>, DatasetError> {
    let [x, y, z, w] = xyzw;
    let q = Quaternion::new(w, x, y, z);
    let norm = q.norm();
    let off = (norm - 1.0).abs();
    if off.is_nan() || off > QUATERNION_NORM_TOLERANCE {
        return Err(DatasetError::NotUnitQuaternion { at: at(), norm });
    }
    if off <= UNIT_EXACT_TOLERANCE {
        Ok(UnitQuaternion::new_unchecked(q))
    } else {
        Ok(UnitQuaternion::new_normalize(q))
    }
}

/// Checks that a coordinate is finite and metre-sized.
pub(crate) fn check_coordinate(
    value: f64,
    at: impl FnOnce() -> Location,
) -> Result<(), DatasetError> {
    if !value.is_finite() {
        return Err(DatasetError::NonFinite { at: at(), value });
    }
    if value.abs() > MAX_COORDINATE_M {
        return Err(DatasetError::LooksLikeMillimetres { at: at(), value });
    }
    Ok(())
}

/// Builds an isometry from the seven numbers of a pose (already parsed, finite).
pub(crate) fn isometry_from_numbers(
    v: [f64; 7],
    fields: &PoseFields<'_>,
    at: impl Fn(String) -> Location,
) -> Result<Isometry3<f64>, DatasetError> {
    for (value, field) in v.iter().zip(fields.iter()) {
        if !value.is_finite() {
            return Err(DatasetError::NonFinite {
                at: at((*field).to_owned()),
                value: *value,
            });
        }
    }
    let rotation = unit_quaternion([v[3], v[4], v[5], v[6]], || at(quaternion_field(fields)))?;
    for i in 0..3 {
        check_coordinate(v[i], || at(fields[i].to_owned()))?;
    }
    Ok(Isometry3::from_parts(
        Translation3::new(v[0], v[1], v[2]),
        rotation,
    ))
}

/// The seven numbers of an isometry, exactly as stored (no hemisphere flip).
pub(crate) fn numbers_from_isometry(iso: &Isometry3<f64>) -> [f64; 7] {
    let t = iso.translation.vector;
    let q = iso.rotation.quaternion();
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

/// Checks an isometry that is about to be written: what the reader would check.
pub(crate) fn check_isometry(
    iso: &Isometry3<f64>,
    fields: &PoseFields<'_>,
    at: impl Fn(String) -> Location,
) -> Result<(), DatasetError> {
    isometry_from_numbers(numbers_from_isometry(iso), fields, at).map(|_| ())
}

/// `qx..qw` for the quaternion of a pose.
pub(crate) fn quaternion_field(fields: &PoseFields<'_>) -> String {
    format!("{}..{}", fields[3], fields[6])
}

/// Field names of a JSON pose called `name`.
pub(crate) fn json_fields(name: &str) -> [String; 7] {
    ["t[0]", "t[1]", "t[2]", "q[0]", "q[1]", "q[2]", "q[3]"].map(|s| format!("{name}.{s}"))
}

/// A JSON pose to an isometry, with the format's checks. The quaternion field is reported
/// as `<name>.q`.
pub(crate) fn isometry_from_pose(
    pose: &Pose,
    name: &str,
    at: impl Fn(String) -> Location,
) -> Result<Isometry3<f64>, DatasetError> {
    let names = json_fields(name);
    let fields: PoseFields<'_> = [
        &names[0], &names[1], &names[2], &names[3], &names[4], &names[5], &names[6],
    ];
    let [x, y, z] = pose.t;
    let [qx, qy, qz, qw] = pose.q;
    isometry_from_numbers([x, y, z, qx, qy, qz, qw], &fields, |f| {
        if f.contains("..") {
            at(format!("{name}.q"))
        } else {
            at(f)
        }
    })
}

/// An isometry as a JSON pose, exactly as stored. Unlike
/// [`b2b_protocol::Pose::from_isometry`] this does not flip the quaternion into `w >= 0`:
/// a dataset writer must give back what it was given.
pub(crate) fn pose_from_isometry(iso: &Isometry3<f64>) -> Pose {
    let v = numbers_from_isometry(iso);
    Pose {
        t: [v[0], v[1], v[2]],
        q: [v[3], v[4], v[5], v[6]],
    }
}

/// Shortest text that parses back to exactly `v`.
pub(crate) fn format_number(v: f64) -> String {
    format!("{v:?}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    const F: PoseFields<'static> = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"];

    fn at(field: String) -> Location {
        Location::cell("c.csv", 1, Some(2), field)
    }

    #[test]
    fn unit_quaternion_is_kept_bit_for_bit() {
        for k in 0..200 {
            let r = UnitQuaternion::from_scaled_axis(Vector3::new(
                0.1 * k as f64,
                -0.37 * k as f64,
                2.0 - 0.05 * k as f64,
            ));
            let q = r.quaternion();
            let back = unit_quaternion([q.i, q.j, q.k, q.w], || at("q".into())).unwrap();
            assert_eq!(back.quaternion().coords, q.coords);
        }
    }

    #[test]
    fn slightly_off_quaternion_is_normalised() {
        let r = unit_quaternion([0.0, 0.0, 0.0, 1.0005], || at("q".into())).unwrap();
        assert_eq!(r.quaternion().w, 1.0);
    }

    #[test]
    fn far_off_or_zero_quaternion_is_rejected() {
        for q in [[0.0, 0.0, 0.0, 1.002], [0.0; 4], [1.0, 1.0, 0.0, 0.0]] {
            let e = unit_quaternion(q, || at("qx..qw".into())).unwrap_err();
            assert!(matches!(e, DatasetError::NotUnitQuaternion { .. }), "{e}");
        }
    }

    #[test]
    fn millimetres_and_non_finite_are_rejected() {
        let mut v = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        v[1] = 512.0;
        let e = isometry_from_numbers(v, &F, at).unwrap_err();
        assert!(matches!(e, DatasetError::LooksLikeMillimetres { .. }));
        assert!(e.to_string().contains("field `ty`"), "{e}");
        v[1] = f64::INFINITY;
        let e = isometry_from_numbers(v, &F, at).unwrap_err();
        assert!(matches!(e, DatasetError::NonFinite { .. }));
    }

    #[test]
    fn numbers_print_shortest_and_parse_back_exactly() {
        for v in [
            0.1,
            -0.0,
            1e-300,
            5e-324,
            0.30857,
            1.0 / 3.0,
            -9.999_999_999_999_999,
        ] {
            let s = format_number(v);
            assert_eq!(s.parse::<f64>().unwrap().to_bits(), v.to_bits(), "{s}");
        }
        assert_eq!(format_number(0.512), "0.512");
    }

    #[test]
    fn json_pose_error_names_the_quaternion() {
        let p = Pose {
            t: [0.0; 3],
            q: [0.0, 0.0, 0.0, 3.0],
        };
        let e =
            isometry_from_pose(&p, "T_base1_base2", |f| Location::field("g.json", f)).unwrap_err();
        assert!(e.to_string().contains("field `T_base1_base2.q`"), "{e}");
    }
}
