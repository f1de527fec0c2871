//! Closed-form hand-eye (`A X = X B`) and robot-world hand-eye (`A X = Z B`) solvers.
//!
//! # Conventions
//!
//! Inputs are one pair of poses per capture, named by the frames they connect:
//!
//! - `base_from_flange[i]`: the flange pose the controller reports (forward
//!   kinematics), mapping flange points into the robot base. OpenCV calls it
//!   `gripper2base`.
//! - `camera_from_target[i]`: the board pose from PnP, mapping board points into the
//!   camera. OpenCV: `target2cam`.
//!
//! The unknowns are `flange_from_camera` (the hand-eye; OpenCV `cam2gripper`) and
//! `base_from_target` (where the board lies). For every capture the chain
//! `base_from_target = base_from_flange[i] · flange_from_camera · camera_from_target[i]`
//! closes.
//!
//! # AX = XB: which motions
//!
//! Eliminating `base_from_target` between captures `i` and `j` gives
//! `A X = X B` with `A = base_from_flange[j]⁻¹ · base_from_flange[i]`
//! (flange_j_from_flange_i), `B = camera_from_target[j] · camera_from_target[i]⁻¹`
//! (camera_j_from_camera_i) and `X = flange_from_camera`.
//!
//! All five AX = XB solvers use **every pair `i < j`**, `n(n-1)/2` motions. This
//! is what OpenCV's `calibrateHandEye` does. Consecutive pairs alone would throw
//! away most of the rotational diversity of a data set. The pairs are correlated, so
//! the unweighted least squares over them is not a maximum-likelihood estimate. For
//! that, seed [`crate::refine`] with the result.
//!
//! # The solvers
//!
//! All are our own nalgebra implementations of the papers' equations. Where the
//! papers leave a choice open, we chose OpenCV 4.6's formulation, so the
//! agreement test in `tests/tests/opencv_agreement.rs` can hold both to a tight
//! tolerance. The least-squares problems are solved through their (small) normal
//! equations. OpenCV solves them with an SVD of the stacked system. For full-rank
//! systems both give the same minimiser.
//!
//! | method | rotation | translation |
//! |---|---|---|
//! | [`HandEyeMethod::Tsai`] (Tsai & Lenz 1989) | least squares on `skew(Pa + Pb) x = Pb - Pa`, `P = 2 sin(θ/2) axis` | least squares `(Ra - I) t = R tb - ta` |
//! | [`HandEyeMethod::Park`] (Park & Martin 1994) | `R = polar(Σ log(Ra) log(Rb)ᵀ)` | as Tsai |
//! | [`HandEyeMethod::Horaud`] (Horaud & Dornaika 1995) | unit quaternion: smallest eigenvector of `Σ (Q(qa) - W(qb))ᵀ(Q(qa) - W(qb))` | as Tsai |
//! | [`HandEyeMethod::Andreff`] (Andreff et al. 1999) | one linear least squares in `vec(R)` and `t`: `(I₉ - Ra ⊗ Rb) vec(R) = 0` and `(I₃ ⊗ tbᵀ) vec(R) + (I₃ - Ra) t = ta`; then `R` is scaled to `det = +1` and projected onto SO(3) | from the same linear solution |
//! | [`HandEyeMethod::Daniilidis`] (Daniilidis 1999) | dual quaternion: two-dimensional null space of the stacked 6x8 equations, then the two unit / orthogonality constraints | from the dual quaternion |
//!
//! # Quaternion signs and motions near 180°
//!
//! Tsai, Horaud and Daniilidis use unit quaternions of `A` and `B`, and Park uses
//! their rotation vectors. Their equations hold only if `qa` and `qb` have matching
//! signs. We take both with `w ≥ 0` (angle in `[0, π]`). The two rotations have the
//! same angle, so this matches the signs except near 180°, where `w ≈ 0` and noise
//! decides the sign. So these four solvers leave out of their quaternion (or
//! rotation-vector) equations the pairs whose relative rotation exceeds
//! [`MAX_SIGN_SAFE_ANGLE_DEG`] (178°): about 1% of the pairs of a well-spread data
//! set. Tsai, Park and Horaud still use those pairs for the translation step, which
//! has no sign issue. Daniilidis solves both together and leaves them out entirely.
//!
//! OpenCV 4.6 differs here. Its `rot2quat`/`rot2quatMinimal` choose the sign by the
//! largest diagonal element whenever the trace is ≤ 0, which means a rotation above
//! 120°. `A` and `B` are different matrices, so for such pairs OpenCV's Tsai, Horaud
//! and Daniilidis can pair `qa` with `-qb` (opencv/opencv#24871, fixed upstream by
//! #24897 after 4.6). With a camera looking out sideways from the flange, noise-free
//! data then gives rotations tens of degrees off, while ours stay exact
//! (`tests/tests/opencv_agreement.rs`). The agreement tests therefore compare
//! Tsai, Park, Horaud and Daniilidis tightly on data whose relative rotations
//! stay below 120°. On full-range data they differ from OpenCV only by the effect
//! of the skipped pairs above 178°, about 1e-5 (m, rad), which is far below the noise.
//!
//! # AX = ZB
//!
//! [`robot_world`] follows OpenCV's `calibrateRobotWorldHandEye`. It solves, per
//! capture, `A X = Z B` with `A = camera_from_target`,
//! `B = flange_from_base = base_from_flange⁻¹`, `X = target_from_base` and
//! `Z = camera_from_flange`. It returns the inverses in this crate's naming:
//! [`RobotWorld::flange_from_camera`] and [`RobotWorld::base_from_target`].
//! - [`RobotWorldMethod::Shah`] (Shah 2013): the rotations come from the top singular
//!   pair of `Σ RB ⊗ RA`. Each is projected onto SO(3). The translations are a 6-unknown
//!   least squares.
//! - [`RobotWorldMethod::Li`] (Li, Wang & Wu 2010): one linear least squares in
//!   `vec(RX), vec(RZ), tX, tZ` (24 unknowns). Both rotations are then projected
//!   onto SO(3), and the translations are taken from the same solution.
//!
//! # Accuracy (measured by this module's tests)
//!
//! Without noise every solver recovers the truth to rounding error: at most
//! 2e-15 m (1.5e-13 m for Andreff and Li) and 2e-14 rad. With the default
//! synthetic noise (0.2 px corners, 0.05 mm and 0.01° flange error) and 30
//! captures, the hand-eye errors over 20 problems are (`noise_study`):
//!
//! | method | translation mean / max | rotation mean / max |
//! |---|---|---|
//! | tsai | 0.22 / 0.47 mm | 0.029 / 0.070° |
//! | park | 0.22 / 0.47 mm | 0.028 / 0.059° |
//! | horaud | 0.22 / 0.47 mm | 0.029 / 0.063° |
//! | andreff | 0.65 / 1.63 mm | 0.029 / 0.062° |
//! | daniilidis | 0.23 / 0.48 mm | 0.029 / 0.063° |
//! | shah | 0.17 / 0.42 mm | 0.029 / 0.062° |
//! | li | 0.76 / 1.76 mm | 0.029 / 0.061° |
//!
//! Andreff and Li take the translation from the same linear solution as the
//! not-yet-orthonormal rotation block, as OpenCV does. Rotation noise in that block
//! leaks into the translation through the camera-to-board distance, which makes
//! their translations 3-4x worse. All of these are seeds for [`crate::refine`],
//! not final answers.
//!
//! # Degeneracy
//!
//! Every solver first runs [`crate::degeneracy::check_motions`] on the flange
//! poses (and checks lengths and finiteness of the camera poses). On degenerate
//! input it returns the named error, never a number. The `*_with` variants take
//! custom [`MotionThresholds`].
//!
//! # Not robust
//!
//! These are closed-form least squares, and they do not detect outliers. In the
//! tests, 3 of 30 flange poses off by 5–15° and 2–6 cm move the hand-eye by about
//! 10 mm and 2° (Tsai, Park, Horaud, Daniilidis) or 6 mm (Shah). Andreff and Li
//! move by about 240 mm, because their translation leans on the unnormalised
//! rotation block. The answer stays a finite rigid transform. Use
//! [`base_from_target_given`] (robust) and [`crate::refine`] (robust loss, MAD
//! rejection) downstream.

mod axxb;
mod axzb;
#[cfg(test)]
mod tests;

use std::fmt;
use std::str::FromStr;

use nalgebra::{
    Matrix3, Quaternion, SMatrix, SVector, Translation3, UnitQuaternion, Vector3, Vector4,
};

use crate::degeneracy::{
    MotionReport, MotionThresholds, check_finite, check_motions, check_same_length,
};
use crate::{CalibError, Iso3};

/// Pairs whose relative rotation exceeds this angle (degrees) are left out of the
/// rotation step of the sign-sensitive solvers (Tsai, Park, Horaud, Daniilidis).
/// See the module docs.
pub const MAX_SIGN_SAFE_ANGLE_DEG: f64 = 178.0;

/// An AX = XB hand-eye method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum HandEyeMethod {
    /// Tsai & Lenz 1989: modified Rodrigues parameters, rotation then translation.
    Tsai,
    /// Park & Martin 1994: rotation vectors (Lie algebra), rotation then translation.
    Park,
    /// Horaud & Dornaika 1995: unit quaternion eigenproblem, rotation then translation.
    Horaud,
    /// Andreff, Horaud & Espiau 1999: linear (Kronecker) in rotation and translation.
    Andreff,
    /// Daniilidis 1999: dual quaternions, rotation and translation together.
    Daniilidis,
}

impl HandEyeMethod {
    /// All methods, in OpenCV's enum order.
    pub const ALL: [HandEyeMethod; 5] = [
        HandEyeMethod::Tsai,
        HandEyeMethod::Park,
        HandEyeMethod::Horaud,
        HandEyeMethod::Andreff,
        HandEyeMethod::Daniilidis,
    ];

    /// The lowercase name, as accepted by [`FromStr`].
    pub fn name(self) -> &'static str {
        match self {
            HandEyeMethod::Tsai => "tsai",
            HandEyeMethod::Park => "park",
            HandEyeMethod::Horaud => "horaud",
            HandEyeMethod::Andreff => "andreff",
            HandEyeMethod::Daniilidis => "daniilidis",
        }
    }
}

impl fmt::Display for HandEyeMethod {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.pad(self.name())
    }
}

impl FromStr for HandEyeMethod {
    type Err = CalibError;

    /// Parses a method name (ASCII case-insensitive).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        HandEyeMethod::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| {
                let names: Vec<&str> = HandEyeMethod::ALL.iter().map(|m| m.name()).collect();
                CalibError::UnknownMethod {
                    kind: "hand-eye",
                    name: s.to_owned(),
                    expected: names.join(", "),
                }
            })
    }
}

/// An AX = ZB robot-world hand-eye method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RobotWorldMethod {
    /// Shah 2013: Kronecker product, rotations then translations.
    Shah,
    /// Li, Wang & Wu 2010: one linear system in both rotations and translations.
    Li,
}

impl RobotWorldMethod {
    /// All methods, in OpenCV's enum order.
    pub const ALL: [RobotWorldMethod; 2] = [RobotWorldMethod::Shah, RobotWorldMethod::Li];

    /// The lowercase name, as accepted by [`FromStr`].
    pub fn name(self) -> &'static str {
        match self {
            RobotWorldMethod::Shah => "shah",
            RobotWorldMethod::Li => "li",
        }
    }
}

impl fmt::Display for RobotWorldMethod {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.pad(self.name())
    }
}

impl FromStr for RobotWorldMethod {
    type Err = CalibError;

    /// Parses a method name (ASCII case-insensitive).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        RobotWorldMethod::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| {
                let names: Vec<&str> = RobotWorldMethod::ALL.iter().map(|m| m.name()).collect();
                CalibError::UnknownMethod {
                    kind: "robot-world",
                    name: s.to_owned(),
                    expected: names.join(", "),
                }
            })
    }
}

/// The result of [`robot_world`]: both unknowns of `A X = Z B`, in this crate's
/// naming.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotWorld {
    /// The hand-eye (the inverse of OpenCV's `gripper2cam`).
    pub flange_from_camera: Iso3,
    /// The board in the robot base (the inverse of OpenCV's `base2world`).
    pub base_from_target: Iso3,
}

/// Solves `A X = X B` for `flange_from_camera` with the default
/// [`MotionThresholds`]. See the module docs for conventions.
pub fn hand_eye(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
    method: HandEyeMethod,
) -> Result<Iso3, CalibError> {
    hand_eye_with(
        base_from_flange,
        camera_from_target,
        method,
        &MotionThresholds::default(),
    )
}

/// [`hand_eye`] with custom degeneracy thresholds.
pub fn hand_eye_with(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
    method: HandEyeMethod,
    thresholds: &MotionThresholds,
) -> Result<Iso3, CalibError> {
    validate(base_from_flange, camera_from_target, thresholds)?;
    let pairs = relative_motions(base_from_flange, camera_from_target);
    let x = match method {
        HandEyeMethod::Tsai => axxb::tsai(&pairs)?,
        HandEyeMethod::Park => axxb::park(&pairs)?,
        HandEyeMethod::Horaud => axxb::horaud(&pairs)?,
        HandEyeMethod::Andreff => axxb::andreff(&pairs)?,
        HandEyeMethod::Daniilidis => axxb::daniilidis(&pairs)?,
    };
    finite_result(x, method.name())
}

/// Solves `A X = Z B` for the hand-eye and the board pose together, with the
/// default [`MotionThresholds`]. See the module docs for conventions.
pub fn robot_world(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
    method: RobotWorldMethod,
) -> Result<RobotWorld, CalibError> {
    robot_world_with(
        base_from_flange,
        camera_from_target,
        method,
        &MotionThresholds::default(),
    )
}

/// [`robot_world`] with custom degeneracy thresholds.
pub fn robot_world_with(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
    method: RobotWorldMethod,
    thresholds: &MotionThresholds,
) -> Result<RobotWorld, CalibError> {
    validate(base_from_flange, camera_from_target, thresholds)?;
    let (target_from_base, camera_from_flange) = match method {
        RobotWorldMethod::Shah => axzb::shah(base_from_flange, camera_from_target)?,
        RobotWorldMethod::Li => axzb::li(base_from_flange, camera_from_target)?,
    };
    Ok(RobotWorld {
        flange_from_camera: finite_result(camera_from_flange.inverse(), method.name())?,
        base_from_target: finite_result(target_from_base.inverse(), method.name())?,
    })
}

/// The board pose implied by a known hand-eye: a robust average of
/// `base_from_flange[i] · flange_from_camera · camera_from_target[i]` over the
/// captures.
///
/// The rotation is the chordal mean ([`crate::pose::average_rotations`]) and the
/// translation the mean, both over the inliers. Inliers are the captures whose
/// rotation and translation lie within three times the median distance of a first
/// estimate (chordal mean of all, component-wise median translation). For
/// Gaussian noise that keeps about 99.9% of the captures. A grossly wrong capture
/// is dropped instead of pulling the mean. A known hand-eye makes motions
/// unnecessary, so this needs one capture and runs only the length and finiteness
/// checks.
pub fn base_from_target_given(
    flange_from_camera: &Iso3,
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
) -> Result<Iso3, CalibError> {
    check_same_length(base_from_flange, camera_from_target)?;
    check_finite(
        std::slice::from_ref(flange_from_camera),
        "flange_from_camera",
    )?;
    check_finite(base_from_flange, "base_from_flange")?;
    check_finite(camera_from_target, "camera_from_target")?;
    if base_from_flange.is_empty() {
        return Err(CalibError::TooFewCaptures { got: 0, need: 1 });
    }
    let samples: Vec<Iso3> = base_from_flange
        .iter()
        .zip(camera_from_target)
        .map(|(bf, ct)| bf * flange_from_camera * ct)
        .collect();
    let rotations: Vec<UnitQuaternion<f64>> = samples.iter().map(|s| s.rotation).collect();

    // First estimate: chordal mean rotation, component-wise median translation.
    let rot0 = crate::pose::average_rotations(&rotations, None)?;
    let t0 = Vector3::from_fn(|k, _| median(samples.iter().map(|s| s.translation.vector[k])));
    let dr: Vec<f64> = rotations.iter().map(|r| r.angle_to(&rot0)).collect();
    let dt: Vec<f64> = samples
        .iter()
        .map(|s| (s.translation.vector - t0).norm())
        .collect();
    // Floors keep noise-free data (median distance 0) from rejecting rounding error.
    let r_gate = (3.0 * median(dr.iter().copied())).max(1e-9);
    let t_gate = (3.0 * median(dt.iter().copied())).max(1e-9);
    let inliers: Vec<usize> = (0..samples.len())
        .filter(|&i| dr[i] <= r_gate && dt[i] <= t_gate)
        .collect();
    // Rotation and translation may disagree about which samples are typical so
    // that none passes both gates; then fall back to all samples.
    let inliers: Vec<usize> = if inliers.is_empty() {
        (0..samples.len()).collect()
    } else {
        inliers
    };

    let rot_in: Vec<UnitQuaternion<f64>> = inliers.iter().map(|&i| rotations[i]).collect();
    let rotation = crate::pose::average_rotations(&rot_in, None)?;
    let t = inliers
        .iter()
        .map(|&i| samples[i].translation.vector)
        .sum::<Vector3<f64>>()
        / inliers.len() as f64;
    finite_result(
        Iso3::from_parts(Translation3::from(t), rotation),
        "base_from_target_given",
    )
}

/// The degeneracy report the solvers would compute for this input, for callers
/// that want to log or display it alongside a result.
pub fn motion_report(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
) -> Result<MotionReport, CalibError> {
    validate(
        base_from_flange,
        camera_from_target,
        &MotionThresholds::default(),
    )
}

fn validate(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
    thresholds: &MotionThresholds,
) -> Result<MotionReport, CalibError> {
    check_same_length(base_from_flange, camera_from_target)?;
    check_finite(camera_from_target, "camera_from_target")?;
    check_motions(base_from_flange, thresholds)
}

fn finite_result(x: Iso3, what: &str) -> Result<Iso3, CalibError> {
    let finite = x.translation.vector.iter().all(|v| v.is_finite())
        && x.rotation.coords.iter().all(|v| v.is_finite());
    if finite {
        Ok(x)
    } else {
        Err(CalibError::NonFinite(format!(
            "result of the {what} solver"
        )))
    }
}

fn median(values: impl Iterator<Item = f64>) -> f64 {
    crate::metrics::median(&mut values.collect::<Vec<f64>>())
}

/// One relative motion `A X = X B` between captures `i < j`.
#[derive(Debug, Clone)]
struct Motion {
    /// flange_j_from_flange_i.
    ra: Matrix3<f64>,
    ta: Vector3<f64>,
    /// Its unit quaternion with `w >= 0`, as (w, x, y, z).
    qa: Vector4<f64>,
    /// camera_j_from_camera_i.
    rb: Matrix3<f64>,
    tb: Vector3<f64>,
    qb: Vector4<f64>,
    /// Relative rotation angle (radians) of `A`.
    angle: f64,
}

impl Motion {
    /// Whether the quaternion signs of `A` and `B` are reliably matched.
    fn sign_safe(&self) -> bool {
        self.angle <= MAX_SIGN_SAFE_ANGLE_DEG.to_radians()
    }
}

/// (w, x, y, z) with `w >= 0`.
fn wxyz(q: &UnitQuaternion<f64>) -> Vector4<f64> {
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    Vector4::new(s * q.w, s * q.i, s * q.j, s * q.k)
}

fn relative_motions(base_from_flange: &[Iso3], camera_from_target: &[Iso3]) -> Vec<Motion> {
    let n = base_from_flange.len();
    let mut out = Vec::with_capacity(n * n.saturating_sub(1) / 2);
    for i in 0..n {
        for j in (i + 1)..n {
            let a = base_from_flange[j].inv_mul(&base_from_flange[i]);
            let b = camera_from_target[j] * camera_from_target[i].inverse();
            out.push(Motion {
                ra: *a.rotation.to_rotation_matrix().matrix(),
                ta: a.translation.vector,
                qa: wxyz(&a.rotation),
                rb: *b.rotation.to_rotation_matrix().matrix(),
                tb: b.translation.vector,
                qb: wxyz(&b.rotation),
                angle: a.rotation.angle(),
            });
        }
    }
    out
}

fn quaternion_wxyz(q: &Vector4<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// Solves the normal equations `ata x = atb` (symmetric positive definite) by
/// Cholesky, refusing (numerically) rank-deficient systems.
fn solve_normal<const N: usize>(
    ata: &SMatrix<f64, N, N>,
    atb: &SVector<f64, N>,
    what: &str,
) -> Result<SVector<f64, N>, CalibError> {
    let chol = ata.cholesky().ok_or_else(|| rank_deficient(what))?;
    let d = chol.l_dirty().diagonal();
    let (lo, hi) = d.iter().fold((f64::INFINITY, 0.0_f64), |(lo, hi), v| {
        (lo.min(*v), hi.max(*v))
    });
    if !(lo > 0.0 && (lo / hi).powi(2) > 1e-13) {
        return Err(rank_deficient(what));
    }
    Ok(chol.solve(atb))
}

fn rank_deficient(what: &str) -> CalibError {
    CalibError::RankDeficient {
        what: what.to_owned(),
    }
}

/// OpenCV's `normalizeRotation`: scale to `det = +1` (flipping the sign if the
/// determinant is negative), then the nearest rotation (SVD).
fn normalize_rotation(r: &Matrix3<f64>, what: &str) -> Result<UnitQuaternion<f64>, CalibError> {
    let det = r.determinant();
    if !det.is_finite() || det.abs() < 1e-12 {
        return Err(CalibError::SingularRotationBlock {
            what: what.to_owned(),
            det,
        });
    }
    let m = if det < 0.0 { -r } else { *r };
    Ok(crate::pose::nearest_rotation(&m))
}

/// The translation step shared by Tsai, Park and Horaud: the least squares
/// `(Ra - I) t = R tb - ta` over all pairs.
fn translation_given_rotation(
    pairs: &[Motion],
    rotation: &UnitQuaternion<f64>,
) -> Result<Vector3<f64>, CalibError> {
    let r = rotation.to_rotation_matrix();
    let mut ata = Matrix3::zeros();
    let mut atb = Vector3::zeros();
    for p in pairs {
        let c = p.ra - Matrix3::identity();
        let d = r * p.tb - p.ta;
        ata += c.transpose() * c;
        atb += c.transpose() * d;
    }
    solve_normal(&ata, &atb, "hand-eye translation")
}
