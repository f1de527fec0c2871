//! Joint reprojection-error refinement (the Tabb–Ahmad Yousef "RP" family).
//!
//! Closed forms fit transforms to transforms and so weigh every capture's PnP
//! pose equally, whatever its conditioning. Here the unknown transforms are fitted
//! directly to the board corners' pixels of all captures at once, which is the
//! maximum-likelihood estimate under pixel noise. The same engine serves one robot
//! (unknowns `flange_from_camera`, `base_from_target`) and two robots sharing a
//! board (see [`crate::base_to_base`]), because a capture's board pose is always
//!
//! `camera_from_target = inverse(ref_from_base * base_from_flange * flange_from_camera) * ref_from_target`
//!
//! with `ref_from_base` the identity for robot 1 and `base1_from_base2` for robot 2.
//!
//! Robustness: a Huber-weighted fit first, then MAD rejection of corners whose
//! residual lies more than `k = 3.5` scaled MADs above the median.
//!
//! Noise model: a robot's pose error moves every corner of a capture together, so
//! corner residuals are not independent. After the robust stage the inliers are
//! fitted by generalised least squares: each capture's residuals are whitened by
//! their covariance `C_c = σ² I + G_c Σ_robot G_cᵀ` (`G_c` the residuals'
//! sensitivity to that capture's flange pose, `Σ_robot` the configured robot
//! noise), with the pixel noise σ chosen so that the whitened residuals have unit
//! variance. The low-rank form makes whitening cheap. Over 100 random problems
//! (0.2 px, 0.05 mm, 0.01°) this halves the hand-eye error of plain reprojection
//! least squares (0.165 → 0.075 mm, 0.035 → 0.015°), against 0.16 mm / 0.027° for
//! the best closed form, and the covariance `(J̃ᵀJ̃)⁻¹` of the whitened problem is
//! calibrated: the true error lies inside the 95% ellipsoid 95% of the time
//! (0% if the robot term is left out, 79% when that model's covariance is then
//! widened to the captures' leave-one-out spread, below). See the tests below and
//! `tests/refine_vs_closed_form.rs`.
//!
//! The noise model's covariance holds only when the model does. The fit then
//! gives the spread of the reported unknowns over leave-one-capture-out fits
//! (the capture-clustered jackknife, one Gauss-Newton step per capture left
//! out). The default estimator ([`crate::estimate`]) widens the covariance to
//! it in every direction where that spread is wider, after the split-half
//! check ([`widen_to_spread`]; `spread_factor` is the largest ratio); it is
//! never narrowed.
//!
//! Parameters are left perturbations (see [`crate::pose`]) of reference poses; the
//! fit is re-centred between rounds so that the analytic Jacobians are exact at
//! the solution.

use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{
    DMatrix, DVector, Dyn, Matrix2x3, Matrix3, Matrix3x6, Matrix6, Owned, Point2, Point3, SMatrix,
    U1, VecStorage, Vector6,
};

use crate::camera::{CameraModel, N_INTRINSICS};
use crate::metrics::median;
use crate::pose::{perturb_left, skew};
use crate::{CalibError, Iso3};

/// The robot's pose error per capture (one standard deviation). KUKA specifies
/// the iiwa's pose repeatability as ±0.1 mm; the defaults (0.05 mm, 0.01°)
/// match that. With [`NoiseModel::Estimated`] (the default) these only weigh
/// the first fit from the seed: the data then decide.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotNoise {
    pub sigma_t_m: f64,
    pub sigma_r_rad: f64,
}

impl RobotNoise {
    /// The covariance of `[rx, ry, rz, tx, ty, tz]`: isotropic rotation and translation.
    pub fn covariance(&self) -> Matrix6<f64> {
        iso6(self.sigma_r_rad.powi(2), self.sigma_t_m.powi(2))
    }
}

impl Default for RobotNoise {
    fn default() -> Self {
        RobotNoise {
            sigma_t_m: 0.05e-3,
            sigma_r_rad: 0.01_f64.to_radians(),
        }
    }
}

/// Where a robot's pose error acts.
///
/// - `Base`: `delta * base_from_flange`, a rotation about the base origin (a
///   base that rocks, errors of the first joints): a small angle moves a flange
///   a metre away by a millimetre.
/// - `Flange`: `base_from_flange * delta`, a rotation about the flange with its
///   own position error (wrist joints, a tool-side mount). For isotropic errors
///   this equals an orientation turned in the base frame and a position moved
///   independently.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoiseFrame {
    Base,
    Flange,
}

impl NoiseFrame {
    /// The map from this frame's error `[rx, ry, rz, tx, ty, tz]` to the left
    /// perturbation of `base_from_flange` (in the base).
    pub fn to_base_left(&self, base_from_flange: &Iso3) -> Matrix6<f64> {
        match self {
            NoiseFrame::Base => Matrix6::identity(),
            NoiseFrame::Flange => crate::pose::adjoint(base_from_flange),
        }
    }

    pub fn name(&self) -> &'static str {
        match self {
            NoiseFrame::Base => "base",
            NoiseFrame::Flange => "flange",
        }
    }
}

/// How the robots' pose errors enter the noise model of the fit.
#[derive(Debug, Clone, PartialEq)]
pub enum NoiseModel {
    /// Estimated per robot from the residuals (the default): for each
    /// [`NoiseFrame`] the rotation and translation variances by maximum
    /// likelihood, and the frame whose likelihood is higher.
    Estimated,
    /// Estimated from the residuals as [`NoiseModel::Estimated`], in this one
    /// shape (the model selection's candidates, [`crate::select`]).
    EstimatedShape(NoiseShape),
    /// The configured [`RobotNoise`], isotropic in the given frame, not estimated.
    Fixed(NoiseFrame),
    /// Known covariances of the left perturbation of each capture's
    /// `base_from_flange` (in its base), in capture order (robot 1's captures,
    /// then robot 2's). Studies use it for the maximum-likelihood limit.
    PerCapture(Vec<Matrix6<f64>>),
}

/// A corner this close (px) to its capture's pose subspace is never an
/// outlier, however small the others' spread: no detector locates a corner
/// better than a few hundredths of a pixel, and rows that give the board pose
/// instead of an image carry corners projected exactly from it, whose spread
/// is rounding alone.
pub const CORNER_OUTLIER_FLOOR_PX: f64 = 0.05;

/// Options of the refinement.
#[derive(Debug, Clone, PartialEq)]
pub struct RefineOptions {
    /// Also estimate `fx, fy, cx, cy, k1, k2, p1, p2, k3`.
    pub refine_intrinsics: bool,
    /// Corner rejection: a corner whose residual off its capture's pose
    /// subspace exceeds median + k * 1.4826 * MAD is left out.
    pub mad_k: f64,
    /// The configured robot noise (see [`RobotNoise`]).
    pub robot_noise: RobotNoise,
    /// The arm's systematic pose error (absolute accuracy: kinematic parameter
    /// errors, a sagging base), the same at nearby configurations. It does not
    /// show in the residuals, so no fit can estimate it: the estimate's
    /// covariance adds it as an error common to all of a robot's captures
    /// (see [`crate::estimate`]). Zero (the default) adds nothing.
    pub systematic: RobotNoise,
    /// How the robot noise is modelled.
    pub noise: NoiseModel,
    /// Capture rejection: a capture whose pose residual has a Mahalanobis
    /// distance² (6 dof, scaled so the captures' median is the chi-square
    /// median) above this is left out, with the reason. `f64::INFINITY` keeps all.
    pub capture_chi2_limit: f64,
    /// Smallest number of corners a capture must keep to stay in the fit.
    pub min_corners_per_capture: usize,
    /// Rounds of (reject, estimate the noise, fit) after the first fit; they
    /// stop earlier once the inliers settle. 0: the first fit only.
    pub max_rounds: usize,
    /// The motion checks run before any fit (too few captures, pure
    /// translation, parallel rotation axes, rotations too small).
    pub motion: crate::degeneracy::MotionThresholds,
    /// Widen the covariance to the captures' leave-one-out spread where that
    /// is wider (see the module docs). Off only to study the noise model alone.
    pub widen_to_spread: bool,
}

impl Default for RefineOptions {
    fn default() -> Self {
        RefineOptions {
            refine_intrinsics: false,
            mad_k: 3.5,
            robot_noise: RobotNoise::default(),
            systematic: RobotNoise {
                sigma_t_m: 0.0,
                sigma_r_rad: 0.0,
            },
            noise: NoiseModel::Estimated,
            // chi-square(6) exceeds 40 with probability 3e-7.
            capture_chi2_limit: 40.0,
            min_corners_per_capture: 4,
            max_rounds: 5,
            motion: crate::degeneracy::MotionThresholds::default(),
            widen_to_spread: true,
        }
    }
}

/// The shape of a robot noise model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoiseShape {
    /// Isotropic rotation and translation in one frame (2 parameters).
    Isotropic(NoiseFrame),
    /// Rotations about a point on the base's z axis and about the flange, and
    /// a translation (4 parameters: three variances and the point's height).
    /// Encoder errors of a serial arm turn it about its joints: those near
    /// the base about points on the first joint's axis, which is the base's z
    /// axis by convention (ISO 9787), those of the wrist about the flange. The
    /// height is where the first joints' rotations balance (the shoulder and
    /// above, with the elbow's share); it is found by likelihood, so a base
    /// that rocks about its origin gives zero.
    TwoCentres,
    /// Given per capture ([`NoiseModel::PerCapture`]).
    Given,
}

impl NoiseShape {
    fn frames(&self) -> &'static [NoiseFrame] {
        match self {
            NoiseShape::Isotropic(NoiseFrame::Base) => &[NoiseFrame::Base],
            NoiseShape::Isotropic(NoiseFrame::Flange) => &[NoiseFrame::Flange],
            NoiseShape::TwoCentres => &[NoiseFrame::Base, NoiseFrame::Flange],
            NoiseShape::Given => &[],
        }
    }

    fn n_params(&self) -> f64 {
        match self {
            NoiseShape::Isotropic(_) => 2.0,
            NoiseShape::TwoCentres => 4.0,
            NoiseShape::Given => 0.0,
        }
    }

    pub fn name(&self) -> String {
        match self {
            NoiseShape::Isotropic(f) => format!("isotropic about the {}", f.name()),
            NoiseShape::TwoCentres => "rotations about the base axis and the flange".into(),
            NoiseShape::Given => "given per capture".into(),
        }
    }
}

/// The robot noise the fit settled on, per robot.
#[derive(Debug, Clone, PartialEq)]
pub struct FittedNoise {
    pub shape: NoiseShape,
    /// One covariance (`[rx, ry, rz, tx, ty, tz]`) per frame of the shape.
    pub components: Vec<Matrix6<f64>>,
    /// RMS per-axis rotation and translation standard deviations at the flange
    /// (summed over components).
    pub sigma_r_rad: f64,
    pub sigma_t_m: f64,
    /// Corner noise of this robot's camera (px, per axis).
    pub sigma_px: f64,
    /// The height on the base's z axis (m) of the point the base-side
    /// rotations turn about (0: the base origin).
    pub centre_height_m: f64,
}

impl FittedNoise {
    fn new(shape: NoiseShape, components: Vec<Matrix6<f64>>, sigma_px: f64) -> Self {
        let d = components
            .iter()
            .fold(Vector6::zeros(), |acc, c| acc + c.diagonal());
        FittedNoise {
            shape,
            components,
            sigma_r_rad: ((d[0] + d[1] + d[2]) / 3.0).max(0.0).sqrt(),
            sigma_t_m: ((d[3] + d[4] + d[5]) / 3.0).max(0.0).sqrt(),
            sigma_px,
            centre_height_m: 0.0,
        }
    }

    fn isotropic(frame: NoiseFrame, noise: &RobotNoise, sigma_px: f64) -> Self {
        FittedNoise::new(
            NoiseShape::Isotropic(frame),
            vec![noise.covariance()],
            sigma_px,
        )
    }

    /// One line for an operator: the robot's pose error per axis at the
    /// flange, its shape, and the corner noise.
    pub fn describe(&self) -> String {
        let shape = match self.shape {
            NoiseShape::TwoCentres => format!(
                "rotations about the base's z axis {:.2} m up and about the flange",
                self.centre_height_m
            ),
            other => other.name(),
        };
        format!(
            "{:.3} mm, {:.4}° per axis at the flange ({shape}); corners {:.2} px",
            self.sigma_t_m * 1e3,
            self.sigma_r_rad.to_degrees(),
            self.sigma_px
        )
    }

    /// The covariance of the left perturbation of `base_from_flange` (in the base).
    pub fn base_covariance(&self, base_from_flange: &Iso3) -> Matrix6<f64> {
        self.shape
            .frames()
            .iter()
            .zip(&self.components)
            .map(|(f, c)| {
                let s = frame_map(*f, base_from_flange, self.centre_height_m);
                s * c * s.transpose()
            })
            .fold(Matrix6::zeros(), |a, b| a + b)
    }
}

/// The map from an error in `frame` to the left perturbation of
/// `base_from_flange`, with the base frame's rotations about the point
/// `centre_height` up its z axis.
fn frame_map(frame: NoiseFrame, base_from_flange: &Iso3, centre_height: f64) -> Matrix6<f64> {
    match frame {
        NoiseFrame::Base => crate::pose::adjoint(&Iso3::translation(0.0, 0.0, centre_height)),
        NoiseFrame::Flange => frame.to_base_left(base_from_flange),
    }
}

fn iso6(a: f64, b: f64) -> Matrix6<f64> {
    Matrix6::from_diagonal(&Vector6::new(a, a, a, b, b, b))
}

/// Why a capture was left out of the fit.
#[derive(Debug, Clone, PartialEq)]
pub enum CaptureRejection {
    /// Its flange pose disagrees with the board it saw far beyond the noise the
    /// other captures show (a typo, a wrong row, a bumped camera).
    PoseOutlier { chi2: f64, limit: f64 },
    /// Too few corners survived corner rejection.
    TooFewCorners { kept: usize, need: usize },
    /// Its corners project behind the camera at the estimate.
    BehindCamera,
}

impl std::fmt::Display for CaptureRejection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CaptureRejection::PoseOutlier { chi2, limit } => write!(
                f,
                "its flange pose disagrees with the board it saw: Mahalanobis distance² {chi2:.0} \
                 (6 dof, limit {limit:.0}) against the robot noise the other captures show"
            ),
            CaptureRejection::TooFewCorners { kept, need } => {
                write!(f, "only {kept} corners fit (need {need})")
            }
            CaptureRejection::BehindCamera => {
                write!(f, "its corners project behind the camera at the estimate")
            }
        }
    }
}

/// One capture: where the robot said its flange was, and the board corners seen.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardCapture {
    pub base_from_flange: Iso3,
    /// Corner positions in the target frame, paired with `pixels`.
    pub target_points: Vec<Point3<f64>>,
    pub pixels: Vec<Point2<f64>>,
    /// Which target the capture saw, when a problem has several (robots that
    /// do not all see one target): an index into the problem's targets, 0 when
    /// there is one.
    pub target: usize,
}

/// How one capture enters the joint problem (indices into the pose blocks).
#[derive(Debug, Clone)]
pub(crate) struct CaptureModel {
    pub capture: BoardCapture,
    /// The hand-eye block, which is also the robot's index in the noise model.
    pub hand_eye: usize,
    pub ref_from_base: Option<usize>,
    pub target: usize,
    pub camera: usize,
    /// Which corners are in the fit.
    pub inlier: Vec<bool>,
    /// Why the whole capture is out of the fit, if it is.
    pub rejection: Option<CaptureRejection>,
}

impl CaptureModel {
    pub(crate) fn new(
        capture: BoardCapture,
        hand_eye: usize,
        ref_from_base: Option<usize>,
        target: usize,
        camera: usize,
    ) -> Self {
        let n = capture.pixels.len();
        CaptureModel {
            capture,
            hand_eye,
            ref_from_base,
            target,
            camera,
            inlier: vec![true; n],
            rejection: None,
        }
    }

    /// `(base_from_camera, camera_from_ref)` for the current poses: the chain
    /// every residual of this capture goes through.
    fn chain(&self, poses: &[Iso3]) -> (Iso3, Iso3) {
        let base_from_camera = self.capture.base_from_flange * poses[self.hand_eye];
        let ref_from_camera = match self.ref_from_base {
            Some(z) => poses[z] * base_from_camera,
            None => base_from_camera,
        };
        (base_from_camera, ref_from_camera.inverse())
    }

    fn used(&self) -> bool {
        self.rejection.is_none()
    }

    fn n_inliers(&self) -> usize {
        if self.used() {
            self.inlier.iter().filter(|v| **v).count()
        } else {
            0
        }
    }
}

/// How far (px) each higher radial distortion term (`k2`'s r⁴, `k3`'s r⁶)
/// may move the image's farthest corner, one sigma, in the prior that holds
/// them where no corner was seen. Corners seen across the image outweigh it;
/// a board seen only near the centre (far away, or small) cannot tell these
/// terms from `k1`, and without it they took values that moved the image's
/// corners by 80% (k2 -1.1, k3 13.5 for a board 2 m away). Ten pixels at the
/// corner is the size of a mild lens's own `k2` (the simulated 640x480
/// cameras': 8.6 px); a lens that needs far more is a wide-angle one, which
/// this model (no `k4..k6`) does not fit anyway.
pub const DISTORTION_PRIOR_PX: f64 = 10.0;

/// `(index in the intrinsic parameters, prior sigma)` of `k2` and `k3` for
/// `cam`: [`DISTORTION_PRIOR_PX`] at its farthest corner.
fn distortion_prior(cam: &CameraModel) -> [(usize, f64); 2] {
    let f = 0.5 * (cam.fx + cam.fy);
    let (w, h) = (f64::from(cam.width), f64::from(cam.height));
    let r2 = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
        .iter()
        .map(|(u, v)| ((u - cam.cx) / cam.fx).powi(2) + ((v - cam.cy) / cam.fy).powi(2))
        .fold(0.0, f64::max);
    let r = r2.sqrt();
    // Indices in `fx, fy, cx, cy, k1, k2, p1, p2, k3`.
    [
        (5, DISTORTION_PRIOR_PX / (f * r2 * r2 * r)),
        (8, DISTORTION_PRIOR_PX / (f * r2 * r2 * r2 * r)),
    ]
}

/// The result of the joint problem, in the engine's terms.
#[derive(Debug, Clone)]
pub(crate) struct EngineSolution {
    pub poses: Vec<Iso3>,
    pub cameras: Vec<CameraModel>,
    /// Covariance of all parameters (6 per pose block, then 9 per camera when
    /// intrinsics are refined).
    pub covariance: DMatrix<f64>,
    pub sigma_px: f64,
    /// How many times the configured robot pose variance the data show.
    pub robot_noise_scale: f64,
    /// The captures' leave-one-out spread of the reported unknowns
    /// ([`Engine::leave_one_out_spread`]); `None` when not asked for or not
    /// available. The covariance above does not hold it yet.
    pub spread: Option<DMatrix<f64>>,
    /// The noise model per robot (hand-eye block).
    pub noise: Vec<FittedNoise>,
    pub rms_px: f64,
    /// Per capture: RMS over inlier corners, and the number of rejected corners.
    pub per_capture: Vec<(f64, usize)>,
    /// Per capture: why it was left out, if it was.
    pub rejections: Vec<Option<CaptureRejection>>,
}

#[derive(Debug, Clone)]
struct Engine {
    reference_poses: Vec<Iso3>,
    reference_cameras: Vec<CameraModel>,
    /// The cameras as the fit started: where the `k2`/`k3` prior
    /// ([`distortion_prior`]) holds them, and its scale. Unlike
    /// `reference_cameras` never recentred, so the prior stays put over the
    /// rounds.
    prior_cameras: Vec<CameraModel>,
    refine_intrinsics: bool,
    captures: Vec<CaptureModel>,
    /// Per capture, the whitening of its residuals by their covariance (pixel
    /// noise plus the robot's pose noise).
    whitening: Option<Vec<Whitening>>,
    /// The noise model per robot, once estimated.
    noise: Vec<FittedNoise>,
    /// Per robot and noise shape, where its EM last ended.
    shape_cache: Vec<ShapeFit>,
    params: DVector<f64>,
}

/// One robot's noise shape as its EM last ended: the starting point of the
/// next round's.
#[derive(Debug, Clone)]
struct ShapeFit {
    robot: usize,
    shape: NoiseShape,
    components: Vec<Matrix6<f64>>,
    /// The base-side rotations' centre height (m), for shapes that have one.
    height: f64,
}

/// `C^{-1/2} = (I + Q diag(d) Qᵀ) / σ` for a capture's residual covariance
/// `C = σ² I + Q diag(s²) Qᵀ` (rank-6 robot term; `d = σ / sqrt(σ² + s²) - 1`).
#[derive(Debug, Clone)]
struct Whitening {
    q: DMatrix<f64>,
    d: Vector6<f64>,
    inv_sigma: f64,
}

impl Whitening {
    fn apply_vector(&self, r: &mut nalgebra::DVectorViewMut<'_, f64>) {
        if self.q.nrows() == 0 {
            *r *= self.inv_sigma;
            return;
        }
        let mut qtr = self.q.transpose() * &*r;
        qtr.component_mul_assign(&self.d);
        *r += &self.q * qtr;
        *r *= self.inv_sigma;
    }

    fn apply_matrix(&self, j: &mut nalgebra::DMatrixViewMut<'_, f64>) {
        if self.q.nrows() == 0 {
            *j *= self.inv_sigma;
            return;
        }
        let mut qtj = self.q.transpose() * &*j;
        for (k, mut row) in qtj.row_iter_mut().enumerate() {
            row *= self.d[k];
        }
        *j += &self.q * qtj;
        *j *= self.inv_sigma;
    }
}

/// One capture's whitened normal equations over the unknowns it depends on
/// ([`Engine::capture_columns`]).
#[derive(Debug, Clone)]
struct CaptureNormal {
    cols: Vec<usize>,
    /// `J_cᵀJ_c` over `cols`.
    jtj: DMatrix<f64>,
    /// `J_cᵀr_c` over `cols`.
    jtr: DVector<f64>,
}

impl CaptureNormal {
    /// Adds this capture's block into the whole problem's normal equations.
    fn add_to(&self, jtj: &mut DMatrix<f64>, jtr: &mut DVector<f64>) {
        for (a, &i) in self.cols.iter().enumerate() {
            jtr[i] += self.jtr[a];
            for (b, &j) in self.cols.iter().enumerate() {
                jtj[(i, j)] += self.jtj[(a, b)];
            }
        }
    }

    /// The Gauss-Newton step `(A - J_cᵀJ_c)⁻¹ J_cᵀr_c` that leaving this
    /// capture out would take, from `p = A⁻¹` without refactorising `A`: with
    /// `E` the columns `cols` of the identity and `M = J_cᵀJ_c`,
    /// `(A - E M Eᵀ)⁻¹ E h = P E (I - M P_SS)⁻¹ h` (the push-through form of
    /// the Woodbury identity, valid for a singular `M`). `None` when
    /// `A - E M Eᵀ` is not positive definite (the other captures do not
    /// determine every unknown): exactly when `I - Lᵀ M L` is not, for
    /// `P_SS = L Lᵀ`.
    fn left_out_step(&self, p: &DMatrix<f64>) -> Option<DVector<f64>> {
        let k = self.cols.len();
        let p_ss = p.select_rows(&self.cols).select_columns(&self.cols);
        let l = p_ss.clone().cholesky()?.l();
        let c = DMatrix::identity(k, k) - l.transpose() * &self.jtj * &l;
        // Positive definite with some room: a capture whose removal leaves an
        // unknown determined to less than 1e-9 of its information cannot go.
        let c = (&c + c.transpose()) * 0.5;
        let eig = c.clone().symmetric_eigenvalues();
        if eig.iter().any(|v| v.is_nan() || *v <= 1e-9) {
            return None;
        }
        let kmat = DMatrix::identity(k, k) - &self.jtj * &p_ss;
        let y = kmat.lu().solve(&self.jtr)?;
        Some(p.select_columns(&self.cols) * y)
    }
}

/// One capture's residuals split into the part a flange pose error can explain
/// (its 6-D pose subspace) and the rest, which only corner noise reaches: the
/// unknowns move each capture's camera pose only, so they never reach the rest.
struct Span {
    robot: usize,
    /// `Qᵀ G` (6x6) for the orthonormal basis `Q` of the pose subspace.
    r0: Matrix6<f64>,
    /// `Qᵀ r`.
    p: Vector6<f64>,
    /// Energy and degrees of freedom off the pose subspace.
    perp2: f64,
    perp_dof: f64,
    /// Per corner, the norm of its residual off the pose subspace.
    corner_perp: Vec<f64>,
    base_from_flange: Iso3,
}

impl Engine {
    fn n_params(&self) -> usize {
        6 * self.reference_poses.len()
            + if self.refine_intrinsics {
                N_INTRINSICS * self.reference_cameras.len()
            } else {
                0
            }
    }

    fn n_robots(&self) -> usize {
        self.captures
            .iter()
            .map(|c| c.hand_eye + 1)
            .max()
            .unwrap_or(0)
    }

    fn pose(&self, b: usize) -> Iso3 {
        let d = Vector6::from_iterator(self.params.rows(6 * b, 6).iter().copied());
        perturb_left(&d, &self.reference_poses[b])
    }

    fn camera(&self, c: usize) -> CameraModel {
        let mut cam = self.reference_cameras[c].clone();
        if self.refine_intrinsics {
            let off = 6 * self.reference_poses.len() + N_INTRINSICS * c;
            let mut p = cam.params();
            for (k, v) in p.iter_mut().enumerate() {
                *v += self.params[off + k];
            }
            cam.set_params(&p);
        }
        cam
    }

    fn n_residuals(&self) -> usize {
        self.captures.iter().map(|c| 2 * c.n_inliers()).sum()
    }

    fn current(&self) -> (Vec<Iso3>, Vec<CameraModel>) {
        (
            (0..self.reference_poses.len())
                .map(|b| self.pose(b))
                .collect(),
            (0..self.reference_cameras.len())
                .map(|c| self.camera(c))
                .collect(),
        )
    }

    /// The unknowns one capture's residuals depend on, as indices into the
    /// parameter vector: its target's pose, its hand-eye, its robot's base
    /// (when not the reference) and its camera's intrinsics (when refined).
    /// Every other column of its Jacobian is zero, so each capture adds a
    /// small dense block to the normal equations and the work per capture does
    /// not grow with the number of robots.
    fn capture_columns(&self, ci: usize) -> Vec<usize> {
        let cap = &self.captures[ci];
        let mut blocks = vec![cap.target, cap.hand_eye];
        blocks.extend(cap.ref_from_base);
        let mut cols: Vec<usize> = Vec::with_capacity(6 * blocks.len() + N_INTRINSICS);
        for b in blocks {
            if !cols.contains(&(6 * b)) {
                cols.extend(6 * b..6 * b + 6);
            }
        }
        if self.refine_intrinsics {
            let off = 6 * self.reference_poses.len() + N_INTRINSICS * cap.camera;
            cols.extend(off..off + N_INTRINSICS);
        }
        cols
    }

    /// One capture's residuals (2 per corner in `corners`), their Jacobian (when
    /// asked; over [`Engine::capture_columns`] only, in that order) and their
    /// sensitivity `G` to the capture's flange pose (left perturbation in its
    /// base), whitened when `whiten` (`G` stays raw).
    fn capture_block(
        &self,
        ci: usize,
        corners: &[bool],
        poses: &[Iso3],
        cameras: &[CameraModel],
        with_jacobian: bool,
        whiten: bool,
    ) -> Option<(DVector<f64>, DMatrix<f64>, DMatrix<f64>)> {
        let cap = &self.captures[ci];
        let cols = if with_jacobian {
            self.capture_columns(ci)
        } else {
            Vec::new()
        };
        // Where a parameter block starts in the compact Jacobian.
        let at = |global: usize| cols.iter().position(|c| *c == global);
        let x = poses[cap.hand_eye];
        let w = poses[cap.target];
        let (base_from_camera, camera_from_ref) = cap.chain(poses);
        let camera_from_target = camera_from_ref * w;
        let cam = &cameras[cap.camera];
        // Sensitivities of the camera-frame left perturbation to each block.
        let d_target = crate::pose::adjoint(&camera_from_ref);
        let d_link = -d_target;
        let d_hand_eye = -crate::pose::adjoint(&x.inverse());
        let d_robot = -crate::pose::adjoint(&base_from_camera.inverse());
        let n_in = corners.iter().filter(|v| **v).count();
        let mut r = DVector::zeros(2 * n_in);
        let mut g = DMatrix::zeros(2 * n_in, 6);
        let mut j = DMatrix::zeros(if with_jacobian { 2 * n_in } else { 0 }, cols.len());
        let intr_off = 6 * poses.len();
        let mut row = 0;
        for (k, (p, uv)) in cap
            .capture
            .target_points
            .iter()
            .zip(&cap.capture.pixels)
            .enumerate()
        {
            if !corners[k] {
                continue;
            }
            let p_c = camera_from_target * p;
            let (proj, jp): (Point2<f64>, Matrix2x3<f64>) = cam.project_with_jacobian(&p_c)?;
            let e = proj - uv;
            r[row] = e.x;
            r[row + 1] = e.y;
            let mut dp = Matrix3x6::zeros();
            dp.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(-skew(&p_c.coords)));
            dp.fixed_view_mut::<3, 3>(0, 3)
                .copy_from(&Matrix3::identity());
            let jd: SMatrix<f64, 2, 6> = jp * dp;
            g.view_mut((row, 0), (2, 6)).copy_from(&(jd * d_robot));
            if with_jacobian {
                let mut put = |block: usize, d: &Matrix6<f64>| {
                    let v = jd * d;
                    if let Some(c) = at(6 * block) {
                        let mut dst = j.view_mut((row, c), (2, 6));
                        dst += v;
                    }
                };
                put(cap.target, &d_target);
                put(cap.hand_eye, &d_hand_eye);
                if let Some(zb) = cap.ref_from_base {
                    put(zb, &d_link);
                }
                if self.refine_intrinsics {
                    let ji = cam.intrinsics_jacobian(&p_c)?;
                    let c = at(intr_off + N_INTRINSICS * cap.camera)?;
                    j.view_mut((row, c), (2, N_INTRINSICS)).copy_from(&ji);
                }
            }
            row += 2;
        }
        if whiten && let Some(wh) = self.whitening.as_ref().map(|w| &w[ci]) {
            wh.apply_vector(&mut r.rows_mut(0, row));
            if with_jacobian {
                wh.apply_matrix(&mut j.rows_mut(0, row));
            }
        }
        Some((r, j, g))
    }

    /// Each used capture's whitened `J_cᵀJ_c` and `J_cᵀr_c` over its own
    /// columns: once, for the final covariance (their sum) and its
    /// leave-one-out spread.
    fn capture_normals(&self) -> Option<Vec<CaptureNormal>> {
        let (poses, cameras) = self.current();
        self.captures
            .iter()
            .enumerate()
            .filter(|(_, cap)| cap.used())
            .map(|(ci, cap)| {
                let (rc, jc, _) =
                    self.capture_block(ci, &cap.inlier, &poses, &cameras, true, true)?;
                Some(CaptureNormal {
                    cols: self.capture_columns(ci),
                    jtj: jc.transpose() * &jc,
                    jtr: jc.transpose() * rc,
                })
            })
            .collect()
    }

    /// The whitened normal equations `JᵀJ`, `Jᵀr` and `rᵀr`, accumulated capture
    /// by capture: each capture's small dense block (over the few unknowns it
    /// depends on) added into the whole, so the work grows with the captures
    /// and not with the square of the robots.
    fn normal_equations(&self) -> Option<(DMatrix<f64>, DVector<f64>, f64)> {
        let n = self.n_params();
        let (poses, cameras) = self.current();
        let mut jtj = DMatrix::zeros(n, n);
        let mut jtr = DVector::zeros(n);
        let mut rss = 0.0;
        for (ci, cap) in self.captures.iter().enumerate() {
            if !cap.used() {
                continue;
            }
            let (rc, jc, _) = self.capture_block(ci, &cap.inlier, &poses, &cameras, true, true)?;
            let normal = CaptureNormal {
                cols: self.capture_columns(ci),
                jtj: jc.transpose() * &jc,
                jtr: jc.transpose() * &rc,
            };
            normal.add_to(&mut jtj, &mut jtr);
            rss += rc.norm_squared();
        }
        if self.refine_intrinsics {
            for (c, (cam, prior)) in cameras.iter().zip(&self.prior_cameras).enumerate() {
                let start = prior.params();
                for (index, sigma) in distortion_prior(prior) {
                    let i = 6 * poses.len() + N_INTRINSICS * c + index;
                    let r = (cam.params()[index] - start[index]) / sigma;
                    jtj[(i, i)] += 1.0 / (sigma * sigma);
                    jtr[i] += r / sigma;
                    rss += r * r;
                }
            }
        }
        Some((jtj, jtr, rss))
    }

    /// The captures' leave-one-out spread of the reported unknowns (each
    /// robot link when there is one, else each hand-eye), in their order:
    /// `V = (G-1)/G Σ_c (δ_c - δ̄)(δ_c - δ̄)ᵀ` over the `G` captures, with
    /// `δ_c = (A - J_cᵀJ_c)⁻¹ J_cᵀ r_c` the Gauss-Newton step that leaving
    /// capture `c` out would take (`A` the whitened normal matrix): the
    /// capture-clustered jackknife.
    /// [`widen_to_spread`] makes a covariance hold it.
    ///
    /// Why: the model's covariance is right only when the noise model is. A
    /// robot error whose shape changes with the configuration (joint encoder
    /// noise through the kinematics) has no shape the fit can estimate from
    /// poses alone, and the model then understates the spread; the jackknife
    /// sees the spread itself, whatever its cause, as long as captures err
    /// independently. It cannot see an error common to many captures (a
    /// systematic kinematic error): see the split-half check in
    /// [`crate::estimate`]. `None` when a capture cannot be left out (the rest
    /// would not determine every unknown), or with fewer than two captures per
    /// reported dimension.
    ///
    /// `p` is `A⁻¹`; each step costs the cube of one capture's unknowns
    /// ([`CaptureNormal::left_out_step`]), not of the whole problem's.
    fn leave_one_out_spread(
        &self,
        p: &DMatrix<f64>,
        normals: &[CaptureNormal],
    ) -> Option<DMatrix<f64>> {
        let n = self.n_params();
        let mut steps = Vec::with_capacity(normals.len());
        for normal in normals {
            steps.push(normal.left_out_step(p)?);
        }
        // The jackknife's variance: (G - 1) / G times the leave-one-out
        // estimates' scatter about their mean.
        let clusters = steps.len();
        let g = clusters as f64;
        let mean = steps.iter().fold(DVector::zeros(n), |acc, d| acc + d) / g.max(1.0);
        let mut spread = DMatrix::zeros(n, n);
        for d in &steps {
            let c = d - &mean;
            spread.ger((g - 1.0) / g, &c, &c, 1.0);
        }
        let mut blocks: Vec<usize> = self
            .captures
            .iter()
            .filter_map(|c| c.ref_from_base)
            .collect();
        if blocks.is_empty() {
            blocks = self.captures.iter().map(|c| c.hand_eye).collect();
        }
        blocks.sort_unstable();
        blocks.dedup();
        let idx: Vec<usize> = blocks.iter().flat_map(|b| 6 * b..6 * b + 6).collect();
        if clusters < 2 * idx.len() {
            return None;
        }
        let v = spread.select_rows(&idx).select_columns(&idx);
        v.iter().all(|x| x.is_finite()).then_some(v)
    }

    /// A capture's residuals split along its pose subspace, over `corners`.
    /// `None` when a corner projects behind the camera.
    fn span(
        &self,
        ci: usize,
        corners: &[bool],
        (poses, cameras): &(Vec<Iso3>, Vec<CameraModel>),
    ) -> Option<Span> {
        let cap = &self.captures[ci];
        let (r, _, g) = self.capture_block(ci, corners, poses, cameras, false, false)?;
        let rows = r.len();
        if rows < 6 {
            return Some(Span {
                robot: cap.hand_eye,
                r0: Matrix6::zeros(),
                p: Vector6::zeros(),
                perp2: r.norm_squared(),
                perp_dof: rows as f64,
                corner_perp: r
                    .as_slice()
                    .chunks(2)
                    .map(|c| (c[0] * c[0] + c[1] * c[1]).sqrt())
                    .collect(),
                base_from_flange: cap.capture.base_from_flange,
            });
        }
        let qr = g.clone().qr();
        let q = qr.q();
        let r0: Matrix6<f64> = qr.r().fixed_view::<6, 6>(0, 0).into();
        let pv = q.transpose() * &r;
        let p = Vector6::from_iterator(pv.iter().copied());
        let perp = &r - &q * &pv;
        Some(Span {
            robot: cap.hand_eye,
            r0,
            p,
            perp2: perp.norm_squared(),
            perp_dof: (rows - 6) as f64,
            corner_perp: perp
                .as_slice()
                .chunks(2)
                .map(|c| (c[0] * c[0] + c[1] * c[1]).sqrt())
                .collect(),
            base_from_flange: cap.capture.base_from_flange,
        })
    }

    /// Re-decides which corners and captures are in the fit (when `reject`),
    /// estimates the noise model from the inliers and sets the whitening.
    fn update_noise(&mut self, options: &RefineOptions, reject: bool) -> Result<(), CalibError> {
        let n_robots = self.n_robots();
        if reject {
            // Corners: by their residual off the pose subspace, which neither the
            // unknowns nor the robot's error reach.
            for cap in &mut self.captures {
                cap.rejection = None;
            }
            let current = self.current();
            let all: Vec<Option<Span>> = (0..self.captures.len())
                .map(|ci| {
                    let corners = vec![true; self.captures[ci].capture.pixels.len()];
                    self.span(ci, &corners, &current)
                })
                .collect();
            for robot in 0..n_robots {
                let mut norms: Vec<f64> = all
                    .iter()
                    .zip(&self.captures)
                    .filter(|(_, c)| c.hand_eye == robot)
                    .filter_map(|(s, _)| s.as_ref())
                    .flat_map(|s| s.corner_perp.iter().copied())
                    .collect();
                if norms.is_empty() {
                    continue;
                }
                let med = median(&mut norms);
                let mut dev: Vec<f64> = norms.iter().map(|e| (e - med).abs()).collect();
                let mad = median(&mut dev);
                let limit = (med + options.mad_k * 1.4826 * mad).max(CORNER_OUTLIER_FLOOR_PX);
                for (cap, s) in self.captures.iter_mut().zip(&all) {
                    if cap.hand_eye != robot {
                        continue;
                    }
                    match s {
                        None => cap.rejection = Some(CaptureRejection::BehindCamera),
                        Some(s) => {
                            for (inl, e) in cap.inlier.iter_mut().zip(&s.corner_perp) {
                                *inl = *e <= limit;
                            }
                            let kept = cap.inlier.iter().filter(|v| **v).count();
                            if kept < options.min_corners_per_capture {
                                cap.rejection = Some(CaptureRejection::TooFewCorners {
                                    kept,
                                    need: options.min_corners_per_capture,
                                });
                            }
                        }
                    }
                }
            }
        }
        let spans = self.inlier_spans()?;
        self.noise = self.estimate_noise(&spans, options)?;
        if reject && options.capture_chi2_limit.is_finite() {
            // Captures: by the Mahalanobis distance of their pose residual under
            // the noise the captures show, scaled by the median so that one wild
            // capture cannot hide itself by inflating the estimate. At most a
            // fifth of a robot's captures go: more than that is no outlier but a
            // model that does not fit, which the caller must see.
            let mut changed = false;
            for robot in 0..n_robots {
                let mut chi: Vec<(usize, f64)> = spans
                    .iter()
                    .filter(|(_, s)| s.robot == robot)
                    .map(|(ci, s)| (*ci, self.capture_chi2(*ci, s, options)))
                    .collect();
                if chi.len() < 6 {
                    continue;
                }
                let mut values: Vec<f64> = chi.iter().map(|(_, v)| *v).collect();
                let scale = median(&mut values) / CHI2_6_MEDIAN;
                if scale <= 0.0 {
                    continue;
                }
                chi.sort_by(|a, b| b.1.total_cmp(&a.1));
                let most = chi.len() / 5;
                for (ci, v) in chi.into_iter().take(most) {
                    let scaled = v / scale;
                    if scaled > options.capture_chi2_limit {
                        self.captures[ci].rejection = Some(CaptureRejection::PoseOutlier {
                            chi2: scaled,
                            limit: options.capture_chi2_limit,
                        });
                        changed = true;
                    }
                }
            }
            if changed {
                let spans = self.inlier_spans()?;
                self.noise = self.estimate_noise(&spans, options)?;
            }
        }
        self.set_whitening(options)
    }

    fn inlier_spans(&self) -> Result<Vec<(usize, Span)>, CalibError> {
        let mut out = Vec::new();
        let current = self.current();
        for (ci, cap) in self.captures.iter().enumerate() {
            if !cap.used() {
                continue;
            }
            let s = self.span(ci, &cap.inlier, &current).ok_or_else(|| {
                CalibError::Optimisation(format!("capture {ci}: a corner went behind its camera"))
            })?;
            out.push((ci, s));
        }
        Ok(out)
    }

    /// The covariance (6x6, left perturbation of `base_from_flange` in its base)
    /// of capture `ci`'s flange pose under the current noise model.
    fn pose_covariance(&self, ci: usize, options: &RefineOptions) -> Matrix6<f64> {
        let cap = &self.captures[ci];
        if let NoiseModel::PerCapture(covs) = &options.noise {
            return covs[ci];
        }
        self.noise[cap.hand_eye].base_covariance(&cap.capture.base_from_flange)
    }

    fn capture_chi2(&self, ci: usize, s: &Span, options: &RefineOptions) -> f64 {
        let sigma2 = self.noise[s.robot].sigma_px.powi(2);
        let c = s.r0 * self.pose_covariance(ci, options) * s.r0.transpose()
            + Matrix6::identity() * sigma2;
        c.cholesky()
            .map_or(f64::INFINITY, |ch| s.p.dot(&ch.solve(&s.p)))
    }

    /// The noise model per robot from the inlier residuals: corner noise from
    /// the energy off each capture's pose subspace; the robot's rotation and
    /// translation variances by maximum likelihood (EM) in each frame, and the
    /// frame of higher likelihood.
    fn estimate_noise(
        &mut self,
        spans: &[(usize, Span)],
        options: &RefineOptions,
    ) -> Result<Vec<FittedNoise>, CalibError> {
        let n_robots = self.n_robots();
        let n_captures = spans.len().max(1);
        let mut out = Vec::with_capacity(n_robots);
        for robot in 0..n_robots {
            let mine: Vec<&Span> = spans
                .iter()
                .filter(|(_, s)| s.robot == robot)
                .map(|(_, s)| s)
                .collect();
            let (perp, dof) = mine
                .iter()
                .fold((0.0, 0.0), |(e, d), s| (e + s.perp2, d + s.perp_dof));
            let sigma2 = if dof > 0.0 {
                (perp / dof).max(1e-10)
            } else {
                1e-4
            };
            let rn = &options.robot_noise;
            let fitted = match &options.noise {
                NoiseModel::PerCapture(_) => {
                    FittedNoise::new(NoiseShape::Given, vec![], sigma2.sqrt())
                }
                NoiseModel::Fixed(frame) => FittedNoise::isotropic(*frame, rn, sigma2.sqrt()),
                NoiseModel::Estimated | NoiseModel::EstimatedShape(_) => {
                    // The unknowns absorb part of the pose subspaces' energy: a
                    // robot's share of them is put back (restricted likelihood).
                    let share = self.n_params() as f64 * mine.len() as f64 / n_captures as f64;
                    let dims = 6.0 * mine.len() as f64;
                    let dof_factor = if dims > share + 1.0 {
                        dims / (dims - share)
                    } else {
                        1.0
                    };
                    // Candidates, chosen by the Bayesian information criterion so
                    // that a richer shape must earn its parameters.
                    let penalty = 0.5 * dims.max(2.0).ln();
                    let start = rn.covariance();
                    let shapes = match &options.noise {
                        NoiseModel::EstimatedShape(shape) => vec![*shape],
                        _ => vec![
                            NoiseShape::Isotropic(NoiseFrame::Base),
                            NoiseShape::Isotropic(NoiseFrame::Flange),
                            NoiseShape::TwoCentres,
                        ],
                    };
                    let mut best: Option<(f64, FittedNoise)> = None;
                    for shape in shapes {
                        // Each shape's EM starts where it ended in the previous
                        // round: the fit moves little between rounds, so a few
                        // iterations reach the maximum again.
                        let cached = self
                            .shape_cache
                            .iter()
                            .find(|c| c.robot == robot && c.shape == shape)
                            .map(|c| (c.components.clone(), c.height));
                        let (starts, previous_height) = match cached {
                            Some((c, h)) => (c, Some(h)),
                            None => (vec![start; shape.frames().len()], None),
                        };
                        let (components, ll, height) = if shape == NoiseShape::TwoCentres {
                            fit_centre_height(&mine, sigma2, starts, previous_height)
                        } else {
                            let (c, ll) = em_components(&mine, shape, sigma2, starts, 100, 0.0);
                            (c, ll, 0.0)
                        };
                        let entry = ShapeFit {
                            robot,
                            shape,
                            components: components.clone(),
                            height,
                        };
                        match self
                            .shape_cache
                            .iter_mut()
                            .find(|c| c.robot == robot && c.shape == shape)
                        {
                            Some(c) => *c = entry,
                            None => self.shape_cache.push(entry),
                        }
                        let score = ll - shape.n_params() * penalty;
                        if best.as_ref().is_none_or(|(l, _)| score > *l) {
                            let mut fitted = FittedNoise::new(
                                shape,
                                components.into_iter().map(|c| c * dof_factor).collect(),
                                sigma2.sqrt(),
                            );
                            fitted.centre_height_m = height;
                            best = Some((score, fitted));
                        }
                    }
                    best.map(|(_, f)| f).unwrap_or(FittedNoise::isotropic(
                        NoiseFrame::Base,
                        rn,
                        sigma2.sqrt(),
                    ))
                }
            };
            out.push(fitted);
        }
        Ok(out)
    }

    /// Each capture's whitening by its residual covariance under the noise model.
    fn set_whitening(&mut self, options: &RefineOptions) -> Result<(), CalibError> {
        self.whitening = None;
        let (poses, cameras) = self.current();
        let mut out = Vec::with_capacity(self.captures.len());
        for (ci, cap) in self.captures.iter().enumerate() {
            let sigma = self.noise[cap.hand_eye].sigma_px;
            if !cap.used() {
                out.push(Whitening {
                    q: DMatrix::zeros(0, 6),
                    d: Vector6::zeros(),
                    inv_sigma: 1.0 / sigma,
                });
                continue;
            }
            let (_, _, g) = self
                .capture_block(ci, &cap.inlier, &poses, &cameras, false, false)
                .ok_or_else(|| {
                    CalibError::Optimisation(format!(
                        "capture {ci}: a corner went behind its camera"
                    ))
                })?;
            if g.nrows() < 6 {
                out.push(Whitening {
                    q: DMatrix::zeros(0, 6),
                    d: Vector6::zeros(),
                    inv_sigma: 1.0 / sigma,
                });
                continue;
            }
            let cov = self.pose_covariance(ci, options);
            let eig = cov.symmetric_eigen();
            let root = eig.eigenvectors
                * Matrix6::from_diagonal(&eig.eigenvalues.map(|v| v.max(0.0).sqrt()));
            // B = G L = Q (R L) with G = Q R (thin QR): the SVD of the 6x6
            // `R L` gives B's left singular vectors as `Q U`.
            let qr = g.qr();
            let small: Matrix6<f64> = qr.r().fixed_view::<6, 6>(0, 0) * root;
            let svd = small.svd(true, false);
            let u = svd
                .u
                .ok_or_else(|| CalibError::Optimisation("SVD failed".into()))?;
            let q = qr.q() * DMatrix::from_column_slice(6, 6, u.as_slice());
            let s2 = Vector6::from_iterator(svd.singular_values.iter().map(|v| v * v));
            out.push(Whitening {
                d: s2.map(|s2| sigma / (sigma * sigma + s2).sqrt() - 1.0),
                q,
                inv_sigma: 1.0 / sigma,
            });
        }
        self.whitening = Some(out);
        Ok(())
    }

    /// Makes the current estimate the new reference (parameters back to zero).
    fn recentre(&mut self) {
        self.reference_poses = (0..self.reference_poses.len())
            .map(|b| self.pose(b))
            .collect();
        self.reference_cameras = (0..self.reference_cameras.len())
            .map(|c| self.camera(c))
            .collect();
        self.params = DVector::zeros(self.n_params());
    }

    /// Per-corner residual norms (unweighted) for all corners, inliers or not.
    fn corner_errors(&self) -> Vec<Vec<f64>> {
        let (poses, cameras) = self.current();
        self.captures
            .iter()
            .map(|cap| {
                let camera_from_target = cap.chain(&poses).1 * poses[cap.target];
                cap.capture
                    .target_points
                    .iter()
                    .zip(&cap.capture.pixels)
                    .map(|(p, uv)| {
                        cameras[cap.camera]
                            .project(&(camera_from_target * p))
                            .map_or(f64::INFINITY, |q| (q - uv).norm())
                    })
                    .collect()
            })
            .collect()
    }
}

/// [`NoiseShape::TwoCentres`]'s components and the height of its base-side
/// centre by maximum likelihood, with the log-likelihood. The first round
/// searches the height over plus and minus the captures' reach (a grid of
/// seven, then a golden section over the cells either side of the best, to
/// a few centimetres, where the likelihood is flat; each EM shortened and
/// started where the last ended); later rounds keep it, since the fit moves
/// little between rounds.
fn fit_centre_height(
    spans: &[&Span],
    sigma2: f64,
    start: Vec<Matrix6<f64>>,
    previous: Option<f64>,
) -> (Vec<Matrix6<f64>>, f64, f64) {
    let shape = NoiseShape::TwoCentres;
    if let Some(h) = previous {
        let (components, ll) = em_components(spans, shape, sigma2, start, 100, h);
        return (components, ll, h);
    }
    let reach = spans
        .iter()
        .map(|s| s.base_from_flange.translation.vector.norm())
        .fold(0.0, f64::max)
        .max(0.1);
    let cell = reach / 3.0;
    let mut warm = start;
    let mut eval = |h: f64| {
        let (c, ll) = em_components(spans, shape, sigma2, warm.clone(), 6, h);
        warm = c;
        ll
    };
    let mut centre = (f64::NEG_INFINITY, 0.0);
    for i in -3..=3 {
        let h = f64::from(i) * cell;
        let ll = eval(h);
        if ll > centre.0 {
            centre = (ll, h);
        }
    }
    // Golden section on the cells either side of the grid's best.
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut a, mut b) = (centre.1 - cell, centre.1 + cell);
    let mut x1 = b - g * (b - a);
    let mut x2 = a + g * (b - a);
    let mut f1 = eval(x1);
    let mut f2 = eval(x2);
    for _ in 0..5 {
        if f1 >= f2 {
            b = x2;
            x2 = x1;
            f2 = f1;
            x1 = b - g * (b - a);
            f1 = eval(x1);
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + g * (b - a);
            f2 = eval(x2);
        }
    }
    let h = 0.5 * (a + b);
    let (components, ll) = em_components(spans, shape, sigma2, warm, 100, h);
    (components, ll, h)
}

/// The median of chi-square with 6 degrees of freedom.
const CHI2_6_MEDIAN: f64 = 5.348;

/// Maximum-likelihood noise components of one robot's pose error, from its
/// captures' pose-subspace residuals `p = R Σ_i S_i η_i + ε` (`η_i ~ N(0, Σ_i)`
/// the error in frame `i` of the shape, `S_i` its map to the base, `ε ~ N(0,
/// σ² I)`), by expectation-maximisation; with the log-likelihood.
fn em_components(
    spans: &[&Span],
    shape: NoiseShape,
    sigma2: f64,
    start: Vec<Matrix6<f64>>,
    iterations: usize,
    centre_height: f64,
) -> (Vec<Matrix6<f64>>, f64) {
    let frames = shape.frames();
    // Per capture, each frame's map from its error to the pose-subspace part.
    let maps: Vec<Vec<Matrix6<f64>>> = spans
        .iter()
        .map(|s| {
            frames
                .iter()
                .map(|f| s.r0 * frame_map(*f, &s.base_from_flange, centre_height))
                .collect()
        })
        .collect();
    let floor = 1e-20;
    let n = spans.len().max(1) as f64;
    let mut comps: Vec<Matrix6<f64>> = start
        .into_iter()
        .map(|c| c + Matrix6::identity() * floor)
        .collect();
    // The residual covariance `C = σ² I + Σ_i M_i Σ_i M_iᵀ` of one capture.
    let covariance = |m: &[Matrix6<f64>], comps: &[Matrix6<f64>]| {
        m.iter()
            .zip(comps)
            .fold(Matrix6::identity() * sigma2, |c, (mi, ci)| {
                c + mi * ci * mi.transpose()
            })
    };
    for _ in 0..iterations {
        // E-step in the 6-D residual space (Woodbury): with `A_i = Σ_i M_iᵀ`,
        // each error's posterior mean is `A_i C⁻¹ p` and its covariance
        // `Σ_i - A_i C⁻¹ A_iᵀ`; only the per-frame blocks are needed.
        let mut acc = vec![Matrix6::zeros(); comps.len()];
        for (s, m) in spans.iter().zip(&maps) {
            let Some(ch) = covariance(m, &comps).cholesky() else {
                return (comps, f64::NEG_INFINITY);
            };
            let c_inv = ch.inverse();
            let w = c_inv * s.p;
            for ((acc, mi), ci) in acc.iter_mut().zip(m).zip(&comps) {
                let a = ci * mi.transpose();
                let mean = a * w;
                *acc += mean * mean.transpose() + ci - a * c_inv * a.transpose();
            }
        }
        for a in acc.iter_mut() {
            *a /= n;
        }
        let block = |i: usize| -> Matrix6<f64> { acc[i] };
        let iso = |c: &Matrix6<f64>| {
            (
                ((c[(0, 0)] + c[(1, 1)] + c[(2, 2)]) / 3.0).max(floor),
                ((c[(3, 3)] + c[(4, 4)] + c[(5, 5)]) / 3.0).max(floor),
            )
        };
        let next: Vec<Matrix6<f64>> = match shape {
            NoiseShape::Isotropic(_) => {
                let (a, b) = iso(&block(0));
                vec![iso6(a, b)]
            }
            NoiseShape::TwoCentres => {
                // One translation term: both frames' translations are the same
                // isotropic error, so it lives in the flange component.
                let (a0, _) = iso(&block(0));
                let (a1, b1) = iso(&block(1));
                vec![iso6(a0, floor), iso6(a1, b1)]
            }
            NoiseShape::Given => {
                let c = block(0);
                vec![(c + c.transpose()) * 0.5 + Matrix6::identity() * floor]
            }
        };
        let scale = comps
            .iter()
            .map(|c| c.diagonal().max())
            .fold(floor, f64::max);
        let change = next
            .iter()
            .zip(&comps)
            .map(|(a, b)| (a - b).abs().max())
            .fold(0.0, f64::max)
            / scale;
        comps = next;
        if change <= 1e-3 {
            break;
        }
    }
    let mut ll = 0.0;
    for (s, m) in spans.iter().zip(&maps) {
        match covariance(m, &comps).cholesky() {
            Some(ch) => {
                let logdet: f64 = 2.0 * ch.l().diagonal().iter().map(|v| v.ln()).sum::<f64>();
                ll -= 0.5 * (s.p.dot(&ch.solve(&s.p)) + logdet);
            }
            None => return (comps, f64::NEG_INFINITY),
        }
    }
    (comps, ll)
}

/// The problem as the least-squares crate sees it, compressed to `n + 1`
/// residuals: with `JᵀJ = L Lᵀ`, the residuals `[L⁻¹ Jᵀr; sqrt(rᵀr - |L⁻¹ Jᵀr|²)]`
/// and the Jacobian `[Lᵀ; 0]` have the same norm, gradient and Gauss-Newton
/// normal matrix as the full stack of 2 residuals per corner, so every
/// Levenberg-Marquardt step is the same, while the solver's QR works on an
/// `(n + 1) x n` matrix instead of thousands of rows. Both are computed together
/// and cached per parameter vector.
/// Compressed residuals and Jacobian at one parameter vector.
type CompressedValue = (DVector<f64>, DMatrix<f64>);

struct Compressed {
    engine: Engine,
    /// The last parameters and the compressed residuals and Jacobian there.
    cache: std::cell::RefCell<Option<(DVector<f64>, Option<CompressedValue>)>>,
}

impl Compressed {
    fn evaluate(&self) -> Option<(DVector<f64>, DMatrix<f64>)> {
        if let Some((p, v)) = self.cache.borrow().as_ref()
            && p == &self.engine.params
        {
            return v.clone();
        }
        let value = self.engine.normal_equations().and_then(|(jtj, jtr, rss)| {
            let n = jtj.nrows();
            let chol = jtj.cholesky()?;
            let l = chol.l();
            let r1 = l.solve_lower_triangular(&jtr)?;
            let rest = (rss - r1.norm_squared()).max(0.0).sqrt();
            let mut r = DVector::zeros(n + 1);
            r.rows_mut(0, n).copy_from(&r1);
            r[n] = rest;
            let mut j = DMatrix::zeros(n + 1, n);
            j.view_mut((0, 0), (n, n)).copy_from(&l.transpose());
            Some((r, j))
        });
        *self.cache.borrow_mut() = Some((self.engine.params.clone(), value.clone()));
        value
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for Compressed {
    type ResidualStorage = VecStorage<f64, Dyn, U1>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.engine.params.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.engine.params.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        self.evaluate().map(|(r, _)| r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        self.evaluate().map(|(_, j)| j)
    }
}

/// Levenberg-Marquardt's evaluation budget per parameter ([`minimise`]).
const PATIENCE: usize = 40;

fn minimise(engine: Engine) -> Result<Engine, CalibError> {
    // Relative tolerances of 1e-7 stop far below the noise (parameters move by
    // ~1e-7 of their size) and save a third of the evaluations of the defaults.
    // A fit that holds converges in a few evaluations (over the real splits'
    // 297 fits: median 5, 90% within 17, the slowest 701 for 24 parameters). One
    // whose model does not hold (intrinsics 10% off: residuals of many pixels)
    // converges linearly, taking thousands that only polish a fit the checks then
    // name as wrong; a patience of 40 (evaluations per parameter) stops it there.
    let problem = Compressed {
        engine,
        cache: std::cell::RefCell::new(None),
    };
    let (problem, report) = LevenbergMarquardt::new()
        .with_ftol(1e-7)
        .with_xtol(1e-7)
        .with_patience(PATIENCE)
        .minimize(problem);
    let engine = problem.engine;
    tracing::trace!(termination = ?report.termination, evaluations = report.number_of_evaluations, "lm");
    if !report.termination.was_successful()
        && !matches!(
            report.termination,
            levenberg_marquardt::TerminationReason::LostPatience
        )
    {
        return Err(CalibError::Optimisation(crate::error::solver_stopped(
            &report.termination,
        )));
    }
    if engine.params.iter().any(|v| !v.is_finite()) {
        return Err(CalibError::Optimisation(
            "parameters became non-finite".into(),
        ));
    }
    Ok(engine)
}

/// Runs the joint problem: a first fit from the seed under the configured
/// noise, then rounds of (reject corners and captures, estimate the noise
/// model, generalised least squares) until the inlier sets settle; then the
/// covariance.
///
/// Why no robust loss on corners: a robot's pose error moves every corner of a
/// capture together, so large residuals of a whole capture are information
/// about the robot, not outliers. Corners are judged only by the part of their
/// residual that no pose error can make (off the capture's pose subspace), and
/// whole captures by their pose residual against the noise the others show.
pub(crate) fn solve(
    poses: Vec<Iso3>,
    cameras: Vec<CameraModel>,
    captures: Vec<CaptureModel>,
    options: &RefineOptions,
    optimise: bool,
) -> Result<EngineSolution, CalibError> {
    let n_corners: usize = captures.iter().map(|c| c.capture.pixels.len()).sum();
    for (i, c) in captures.iter().enumerate() {
        if c.capture.pixels.len() != c.capture.target_points.len() {
            return Err(CalibError::CornerCountMismatch {
                capture: i,
                pixels: c.capture.pixels.len(),
                target_points: c.capture.target_points.len(),
            });
        }
        if c.capture
            .pixels
            .iter()
            .any(|p| !p.x.is_finite() || !p.y.is_finite())
            || c.capture
                .target_points
                .iter()
                .any(|p| !p.coords.iter().all(|v| v.is_finite()))
        {
            return Err(CalibError::NonFinite(format!("capture {i} corners")));
        }
    }
    if let NoiseModel::PerCapture(covs) = &options.noise
        && covs.len() != captures.len()
    {
        return Err(CalibError::MismatchedLengths {
            len_a: covs.len(),
            what_a: "capture covariances",
            len_b: captures.len(),
            what_b: "captures",
        });
    }
    let mut engine = Engine {
        reference_poses: poses,
        prior_cameras: cameras.clone(),
        reference_cameras: cameras,
        refine_intrinsics: options.refine_intrinsics,
        captures,
        whitening: None,
        noise: Vec::new(),
        shape_cache: Vec::new(),
        params: DVector::zeros(0),
    };
    engine.params = DVector::zeros(engine.n_params());
    if engine.n_residuals() <= engine.n_params() {
        return Err(CalibError::TooFewCaptures {
            got: n_corners,
            need: engine.n_params() / 2 + 1,
        });
    }
    let first = RefineOptions {
        noise: match &options.noise {
            NoiseModel::Estimated | NoiseModel::EstimatedShape(_) => {
                NoiseModel::Fixed(NoiseFrame::Base)
            }
            other => other.clone(),
        },
        ..options.clone()
    };
    if optimise {
        // From the seed: its own error would read as robot noise, so the first
        // fit weighs by the configured noise, rejecting nothing but what cannot
        // be projected.
        engine.update_noise(&first, false)?;
        engine = minimise(engine)?;
        engine.recentre();
        let mut last: Vec<(Vec<bool>, bool)> = engine
            .captures
            .iter()
            .map(|c| (c.inlier.clone(), c.used()))
            .collect();
        for round in 0..options.max_rounds {
            engine.update_noise(options, true)?;
            if engine.n_residuals() <= engine.n_params() {
                return Err(CalibError::TooFewInliers(format!(
                    "{} residuals left for {} parameters",
                    engine.n_residuals(),
                    engine.n_params()
                )));
            }
            let sets: Vec<(Vec<bool>, bool)> = engine
                .captures
                .iter()
                .map(|c| (c.inlier.clone(), c.used()))
                .collect();
            // Settled: no capture changed and at most 1% of the corners, whose
            // effect on the estimate is far below its uncertainty.
            let captures_changed = sets.iter().zip(&last).any(|(a, b)| a.1 != b.1);
            let (toggled, total) = sets.iter().zip(&last).fold((0, 0), |(t, n), (a, b)| {
                (
                    t + a.0.iter().zip(&b.0).filter(|(x, y)| x != y).count(),
                    n + a.0.len(),
                )
            });
            let settled = round > 0 && !captures_changed && toggled * 100 <= total;
            if settled {
                break;
            }
            engine = minimise(engine)?;
            engine.recentre();
            last = sets;
        }
        engine.update_noise(options, false)?;
    } else {
        engine.update_noise(options, true)?;
    }
    if engine.n_residuals() <= engine.n_params() {
        return Err(CalibError::TooFewInliers(format!(
            "{} residuals left for {} parameters",
            engine.n_residuals(),
            engine.n_params()
        )));
    }
    let normals = engine
        .capture_normals()
        .ok_or_else(|| CalibError::Optimisation("a corner went behind its camera".into()))?;
    let n = engine.n_params();
    let mut a = DMatrix::zeros(n, n);
    let mut unused = DVector::zeros(n);
    for normal in &normals {
        normal.add_to(&mut a, &mut unused);
    }
    let mut covariance = a.try_inverse().ok_or_else(|| {
        CalibError::Optimisation(
            "normal matrix is singular: the data do not determine every unknown".into(),
        )
    })?;
    covariance = (&covariance + covariance.transpose()) * 0.5;
    let spread = if options.widen_to_spread {
        engine.leave_one_out_spread(&covariance, &normals)
    } else {
        None
    };
    let errors = engine.corner_errors();
    let per_capture = engine
        .captures
        .iter()
        .zip(&errors)
        .map(|(cap, es)| {
            let inl: Vec<f64> = es
                .iter()
                .zip(&cap.inlier)
                .filter(|(_, i)| **i && cap.used())
                .map(|(e, _)| *e)
                .collect();
            let rms = if inl.is_empty() {
                f64::NAN
            } else {
                (inl.iter().map(|e| e * e).sum::<f64>() / inl.len() as f64).sqrt()
            };
            let out = if cap.used() {
                cap.inlier.iter().filter(|v| !**v).count()
            } else {
                cap.inlier.len()
            };
            (rms, out)
        })
        .collect();
    let inlier_errors: Vec<f64> = errors
        .iter()
        .zip(&engine.captures)
        .filter(|(_, cap)| cap.used())
        .flat_map(|(es, cap)| {
            es.iter()
                .zip(&cap.inlier)
                .filter(|(_, i)| **i)
                .map(|(e, _)| *e)
        })
        .collect();
    let rms_px = (inlier_errors.iter().map(|e| e * e).sum::<f64>()
        / inlier_errors.len().max(1) as f64)
        .sqrt();
    let rn = &options.robot_noise;
    let robot_noise_scale = engine
        .noise
        .iter()
        .filter(|n| n.sigma_t_m.is_finite())
        .map(|n| {
            ((n.sigma_t_m / rn.sigma_t_m).powi(2)).max((n.sigma_r_rad / rn.sigma_r_rad).powi(2))
        })
        .fold(0.0, f64::max);
    let sigma_px = {
        let v: Vec<f64> = engine.noise.iter().map(|n| n.sigma_px).collect();
        (v.iter().map(|s| s * s).sum::<f64>() / v.len().max(1) as f64).sqrt()
    };
    Ok(EngineSolution {
        poses: engine.reference_poses.clone(),
        cameras: engine.reference_cameras.clone(),
        covariance,
        sigma_px,
        robot_noise_scale,
        spread,
        noise: engine.noise.clone(),
        rms_px,
        per_capture,
        rejections: engine
            .captures
            .iter()
            .map(|c| c.rejection.clone())
            .collect(),
    })
}

/// The result of refining one robot's hand-eye.
#[derive(Debug, Clone)]
pub struct HandEyeEstimate {
    pub flange_from_camera: Iso3,
    pub base_from_target: Iso3,
    /// The camera after refinement (unchanged unless intrinsics were refined).
    pub camera: CameraModel,
    /// Covariance of the left perturbation of `flange_from_camera` (in `flange`).
    pub flange_from_camera_covariance: Matrix6<f64>,
    /// Covariance of the left perturbation of `base_from_target` (in `base`).
    pub base_from_target_covariance: Matrix6<f64>,
    /// Estimated corner noise (px, per axis).
    pub sigma_px: f64,
    /// How many times the configured robot pose variance the data show.
    pub robot_noise_scale: f64,
    /// The captures' leave-one-out spread of `flange_from_camera` (see the
    /// module docs), when computed. The covariance above is the noise model's;
    /// [`crate::estimate::estimate_hand_eye`] widens it to this spread after the
    /// split-half check ([`widen_to_spread`]).
    pub flange_from_camera_spread: Option<Matrix6<f64>>,
    /// The largest factor (at least 1) a direction of the covariance was
    /// widened by to hold that spread; 1 until it is.
    pub spread_factor: f64,
    /// RMS of the inlier corner residual norms (px).
    pub rms_px: f64,
    /// Per capture: RMS residual norm (px) and number of rejected corners.
    pub per_capture: Vec<(f64, usize)>,
    /// Per capture: why it was left out of the fit, if it was.
    pub rejections: Vec<Option<CaptureRejection>>,
    /// The robot noise the fit found in the residuals.
    pub noise: FittedNoise,
}

/// Refines one robot's hand-eye and board pose from all captures' corners.
/// `initial` is `(flange_from_camera, base_from_target)`, typically a closed form.
pub fn refine_hand_eye(
    camera: &CameraModel,
    captures: &[BoardCapture],
    initial: (Iso3, Iso3),
    options: &RefineOptions,
) -> Result<HandEyeEstimate, CalibError> {
    hand_eye_problem(camera, captures, initial, options, true)
}

/// Evaluates residuals, outliers and the covariance of a given (closed-form)
/// estimate without moving it: how sure a closed form may be, in the same terms
/// as the refinement.
pub fn evaluate_hand_eye(
    camera: &CameraModel,
    captures: &[BoardCapture],
    estimate: (Iso3, Iso3),
    options: &RefineOptions,
) -> Result<HandEyeEstimate, CalibError> {
    hand_eye_problem(camera, captures, estimate, options, false)
}

/// One robot's fit takes the captures of one target.
pub(crate) fn one_target(captures: &[BoardCapture]) -> Result<(), CalibError> {
    let mut targets: Vec<usize> = captures.iter().map(|c| c.target).collect();
    targets.sort_unstable();
    targets.dedup();
    if targets.len() > 1 {
        return Err(CalibError::SeveralTargets {
            targets: targets.len(),
        });
    }
    Ok(())
}

fn hand_eye_problem(
    camera: &CameraModel,
    captures: &[BoardCapture],
    initial: (Iso3, Iso3),
    options: &RefineOptions,
    optimise: bool,
) -> Result<HandEyeEstimate, CalibError> {
    one_target(captures)?;
    let base_from_flange: Vec<Iso3> = captures.iter().map(|c| c.base_from_flange).collect();
    crate::degeneracy::check_motions(&base_from_flange, &options.motion)?;
    let models = captures
        .iter()
        .map(|c| CaptureModel::new(c.clone(), 0, None, 1, 0))
        .collect();
    let sol = solve(
        vec![initial.0, initial.1],
        vec![camera.clone()],
        models,
        options,
        optimise,
    )?;
    Ok(HandEyeEstimate {
        flange_from_camera: sol.poses[0],
        base_from_target: sol.poses[1],
        camera: sol.cameras[0].clone(),
        flange_from_camera_covariance: sol.covariance.fixed_view::<6, 6>(0, 0).into(),
        base_from_target_covariance: sol.covariance.fixed_view::<6, 6>(6, 6).into(),
        sigma_px: sol.sigma_px,
        robot_noise_scale: sol.robot_noise_scale,
        flange_from_camera_spread: sol
            .spread
            .as_ref()
            .map(|v| v.fixed_view::<6, 6>(0, 0).into()),
        spread_factor: 1.0,
        rms_px: sol.rms_px,
        per_capture: sol.per_capture,
        rejections: sol.rejections,
        noise: sol.noise[0].clone(),
    })
}

/// Widens `covariance` to hold `spread` in every direction where the spread is
/// wider, and nowhere else: with `covariance = L Lᵀ` and
/// `L⁻¹ spread L⁻ᵀ = U Λ Uᵀ`, it becomes `L U max(Λ, 1) Uᵀ Lᵀ`. Returns the
/// largest factor a direction was widened by (1: unchanged). A covariance that
/// is not positive definite, or a spread that is not finite, is left as it is.
pub fn widen_to_spread(covariance: &mut DMatrix<f64>, spread: &DMatrix<f64>) -> f64 {
    if covariance.shape() != spread.shape() {
        return 1.0;
    }
    let Some(chol) = covariance.clone().cholesky() else {
        return 1.0;
    };
    let l = chol.l();
    let Some(l_inv) = l.clone().try_inverse() else {
        return 1.0;
    };
    let m = &l_inv * spread * l_inv.transpose();
    let eig = ((&m + m.transpose()) * 0.5).symmetric_eigen();
    if !eig.eigenvalues.iter().all(|x| x.is_finite()) {
        return 1.0;
    }
    let widened = eig.eigenvalues.map(|x| x.max(1.0));
    *covariance = &l
        * &eig.eigenvectors
        * DMatrix::from_diagonal(&widened)
        * eig.eigenvectors.transpose()
        * l.transpose();
    eig.eigenvalues.iter().copied().fold(1.0, f64::max)
}

/// [`widen_to_spread`] for one 6x6 block.
pub fn widen6_to_spread(covariance: &mut Matrix6<f64>, spread: &Matrix6<f64>) -> f64 {
    let mut c = DMatrix::from_column_slice(6, 6, covariance.as_slice());
    let factor = widen_to_spread(&mut c, &DMatrix::from_column_slice(6, 6, spread.as_slice()));
    *covariance = Matrix6::from_column_slice(c.as_slice());
    factor
}

/// Mahalanobis distance squared of a 6-vector under a covariance.
pub fn mahalanobis2(delta: &Vector6<f64>, cov: &Matrix6<f64>) -> Option<f64> {
    cov.try_inverse()
        .map(|inv| (delta.transpose() * inv * delta)[(0, 0)])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::{left_difference, pose_distance};
    use crate::synth::{SynthConfig, random_robot};

    /// One sigma of `k2` or `k3` moves the image's farthest corner by
    /// DISTORTION_PRIOR_PX, whatever the camera.
    #[test]
    fn the_distortion_prior_is_ten_pixels_at_the_farthest_corner() {
        for (w, h, f, cx, cy) in [
            (640, 480, 615.0, 321.4, 238.7),
            (1280, 720, 912.3, 641.2, 362.5),
            (424, 240, 300.0, 200.0, 130.0),
        ] {
            let cam = CameraModel::new(w, h, [f, f, cx, cy], &[0.0; 5]).unwrap();
            // The farthest corner from the principal point.
            let corner = [
                (0.0, 0.0),
                (w as f64, 0.0),
                (0.0, h as f64),
                (w as f64, h as f64),
            ]
            .into_iter()
            .map(|(u, v)| Point2::new(u, v))
            .max_by(|a, b| {
                let d = |p: &Point2<f64>| (p.x - cx).hypot(p.y - cy);
                d(a).total_cmp(&d(b))
            })
            .unwrap();
            let xy = cam.unproject(&corner);
            for (index, sigma) in distortion_prior(&cam) {
                let mut moved = cam.clone();
                let mut p = moved.params();
                p[index] = sigma;
                moved.set_params(&p);
                let uv = moved.project(&Point3::new(xy.x, xy.y, 1.0)).unwrap();
                let shift = (uv - corner).norm();
                assert!(
                    (shift - DISTORTION_PRIOR_PX).abs() < 1e-6,
                    "{w}x{h}, parameter {index}: {shift} px"
                );
            }
        }
    }

    fn captures_of(robot: &crate::synth::SynthRobot) -> Vec<BoardCapture> {
        robot.board_captures()
    }

    fn perturbed_start(robot: &crate::synth::SynthRobot) -> (Iso3, Iso3) {
        let d = Vector6::new(0.02, -0.03, 0.01, 0.01, -0.02, 0.015);
        (
            perturb_left(&d, &robot.flange_from_camera),
            perturb_left(&(-d), &robot.base_from_target),
        )
    }

    #[test]
    fn recovers_truth_without_noise() {
        let cfg = SynthConfig {
            pixel_sigma: 0.0,
            robot_sigma_t: 0.0,
            robot_sigma_r: 0.0,
            ..Default::default()
        };
        let robot = random_robot(7, &cfg).unwrap();
        let est = refine_hand_eye(
            &cfg.camera,
            &captures_of(&robot),
            perturbed_start(&robot),
            &RefineOptions::default(),
        )
        .unwrap();
        let (dt, da) = pose_distance(&est.flange_from_camera, &robot.flange_from_camera);
        assert!(dt < 1e-9 && da < 1e-9, "{dt} {da}");
        let (dt, da) = pose_distance(&est.base_from_target, &robot.base_from_target);
        assert!(dt < 1e-9 && da < 1e-9, "{dt} {da}");
    }

    #[test]
    fn refines_intrinsics_too() {
        let cfg = SynthConfig {
            robot_sigma_t: 0.0,
            robot_sigma_r: 0.0,
            pixel_sigma: 0.05,
            ..Default::default()
        };
        let robot = random_robot(3, &cfg).unwrap();
        let mut wrong = cfg.camera.clone();
        wrong.fx += 4.0;
        wrong.cy -= 3.0;
        let opts = RefineOptions {
            refine_intrinsics: true,
            ..Default::default()
        };
        let est =
            refine_hand_eye(&wrong, &captures_of(&robot), perturbed_start(&robot), &opts).unwrap();
        assert!(
            (est.camera.fx - cfg.camera.fx).abs() < 0.5,
            "fx {}",
            est.camera.fx
        );
        assert!(
            (est.camera.cy - cfg.camera.cy).abs() < 0.5,
            "cy {}",
            est.camera.cy
        );
        let (dt, _) = pose_distance(&est.flange_from_camera, &robot.flange_from_camera);
        assert!(dt < 1e-3, "{dt}");
    }

    /// Robot errors that turn the arm about a point on its base's z axis
    /// (encoder errors of the first joints) give that point's height; errors
    /// about the base origin give none.
    #[test]
    fn finds_the_height_the_base_side_errors_turn_about() {
        use rand::SeedableRng;
        let cfg = SynthConfig {
            captures: 40,
            pixel_sigma: 0.1,
            robot_sigma_t: 0.0,
            robot_sigma_r: 0.0,
            ..Default::default()
        };
        for (seed, height) in [(5, 0.6), (6, 0.3), (7, 0.0)] {
            let mut robot = random_robot(seed, &cfg).unwrap();
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            let about = crate::pose::adjoint(&Iso3::translation(0.0, 0.0, height));
            let sigma = 0.05_f64.to_radians();
            for pose in robot.base_from_flange.iter_mut() {
                let w = Vector6::new(
                    sigma * crate::synth::gauss(&mut rng),
                    sigma * crate::synth::gauss(&mut rng),
                    sigma * crate::synth::gauss(&mut rng),
                    0.0,
                    0.0,
                    0.0,
                );
                *pose = perturb_left(&(about * w), pose);
            }
            let est = refine_hand_eye(
                &cfg.camera,
                &captures_of(&robot),
                perturbed_start(&robot),
                &RefineOptions::default(),
            )
            .unwrap();
            let found = match est.noise.shape {
                NoiseShape::TwoCentres => {
                    let line = est.noise.describe();
                    assert!(
                        line.contains(&format!("{:.2} m up", est.noise.centre_height_m)),
                        "{line}"
                    );
                    est.noise.centre_height_m
                }
                NoiseShape::Isotropic(NoiseFrame::Base) => 0.0,
                other => panic!("seed {seed}: shape {other:?} for rotations about a point"),
            };
            assert!(
                (found - height).abs() < 0.08,
                "seed {seed}: height {found:.3} m, truth {height} m ({:?})",
                est.noise.shape
            );
        }
    }

    #[test]
    fn rejects_outlier_corners() {
        let cfg = SynthConfig::default();
        let robot = random_robot(11, &cfg).unwrap();
        let mut caps = captures_of(&robot);
        // 20 corners moved by 15 px: detector blunders.
        for (i, cap) in caps.iter_mut().enumerate().take(10) {
            cap.pixels[i].x += 15.0;
            cap.pixels[i + 20].y -= 15.0;
        }
        let est = refine_hand_eye(
            &cfg.camera,
            &caps,
            perturbed_start(&robot),
            &RefineOptions::default(),
        )
        .unwrap();
        let rejected: usize = est.per_capture.iter().map(|(_, n)| n).sum();
        assert!(rejected >= 20, "only {rejected} rejected");
        let (dt, da) = pose_distance(&est.flange_from_camera, &robot.flange_from_camera);
        assert!(dt < 0.5e-3 && da < 0.05f64.to_radians(), "{dt} {da}");
    }

    #[test]
    fn too_few_captures_is_an_error() {
        let robot = random_robot(1, &SynthConfig::default()).unwrap();
        let caps = captures_of(&robot);
        let err = refine_hand_eye(
            &SynthConfig::default().camera,
            &caps[..2],
            perturbed_start(&robot),
            &RefineOptions::default(),
        )
        .unwrap_err();
        assert!(matches!(err, CalibError::TooFewCaptures { .. }));
    }

    #[test]
    fn degenerate_motions_are_named_errors() {
        use nalgebra::{Translation3, UnitQuaternion, Vector3};
        let cfg = SynthConfig::default();
        let robot = random_robot(1, &cfg).unwrap();
        let caps = captures_of(&robot);
        // Pure translation: every flange pose with the first pose's rotation.
        let mut pure = caps.clone();
        for (i, c) in pure.iter_mut().enumerate() {
            c.base_from_flange = Iso3::from_parts(
                Translation3::new(0.4 + 0.01 * i as f64, 0.0, 0.3),
                caps[0].base_from_flange.rotation,
            );
        }
        let err = refine_hand_eye(
            &cfg.camera,
            &pure,
            perturbed_start(&robot),
            &RefineOptions::default(),
        )
        .unwrap_err();
        assert!(matches!(err, CalibError::PureTranslation { .. }), "{err}");
        // Rotations about one axis only.
        let mut parallel = caps.clone();
        for (i, c) in parallel.iter_mut().enumerate() {
            c.base_from_flange = Iso3::from_parts(
                Translation3::new(0.4, 0.01 * i as f64, 0.3),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.2 * i as f64),
            );
        }
        let err = refine_hand_eye(
            &cfg.camera,
            &parallel,
            perturbed_start(&robot),
            &RefineOptions::default(),
        )
        .unwrap_err();
        assert!(
            matches!(err, CalibError::ParallelRotationAxes { .. }),
            "{err}"
        );
    }

    #[test]
    fn nan_pixel_is_an_error_not_a_number() {
        let robot = random_robot(1, &SynthConfig::default()).unwrap();
        let mut caps = captures_of(&robot);
        caps[3].pixels[5].x = f64::NAN;
        let err = refine_hand_eye(
            &SynthConfig::default().camera,
            &caps,
            perturbed_start(&robot),
            &RefineOptions::default(),
        )
        .unwrap_err();
        assert!(matches!(err, CalibError::NonFinite(_)));
    }

    #[test]
    fn widening_to_the_spread_takes_the_wider_in_every_direction_and_never_narrows() {
        // A correlated covariance, and a spread wider than it along one of its
        // own directions and narrower along another.
        let a = DMatrix::from_fn(6, 6, |i, j| ((i * 7 + j * 3) % 5) as f64 * 0.1);
        let c = &a * a.transpose() + DMatrix::identity(6, 6);
        let l = c.clone().cholesky().unwrap().l();
        let mut m = DMatrix::identity(6, 6);
        m[(0, 0)] = 4.0;
        m[(1, 1)] = 0.25;
        let spread = &l * &m * l.transpose();
        let mut widened = c.clone();
        let factor = widen_to_spread(&mut widened, &spread);
        assert!((factor - 4.0).abs() < 1e-9, "{factor}");
        let mut expected = DMatrix::identity(6, 6);
        expected[(0, 0)] = 4.0;
        let expected = &l * expected * l.transpose();
        assert!((&widened - expected).norm() < 1e-9 * c.norm());
        // A spread inside the covariance changes nothing.
        let mut same = c.clone();
        assert_eq!(widen_to_spread(&mut same, &(&c * 0.5)), 1.0);
        assert!((&same - &c).norm() < 1e-12 * c.norm());
        // A spread of another size, or not finite, is ignored.
        let mut kept = c.clone();
        assert_eq!(widen_to_spread(&mut kept, &DMatrix::identity(3, 3)), 1.0);
        assert_eq!(widen_to_spread(&mut kept, &(&c * f64::NAN)), 1.0);
        assert_eq!(kept, c);
    }

    /// The covariance is calibrated: over 100 random problems with realistic noise
    /// the true hand-eye error lies inside the 95% ellipsoid 90-99% of the time.
    /// Without the robot's pose noise in the model (corner noise only) it almost
    /// never does: the robot term is what makes it honest.
    #[test]
    fn covariance_is_calibrated_over_100_problems() {
        let cfg = SynthConfig::default();
        let chi2_6_95 = 12.5916;
        let pixels_only = RefineOptions {
            noise: NoiseModel::Fixed(NoiseFrame::Base),
            robot_noise: RobotNoise {
                sigma_t_m: 0.0,
                sigma_r_rad: 0.0,
            },
            ..Default::default()
        };
        let model_only = |o: &RefineOptions| RefineOptions {
            widen_to_spread: false,
            ..o.clone()
        };
        let n = 100;
        let mut inside = [0; 4];
        for seed in 0..n {
            let robot = random_robot(1000 + seed, &cfg).unwrap();
            for (k, options) in [
                RefineOptions::default(),
                model_only(&pixels_only),
                model_only(&RefineOptions::default()),
                pixels_only.clone(),
            ]
            .iter()
            .enumerate()
            {
                let est = refine_hand_eye(
                    &cfg.camera,
                    &captures_of(&robot),
                    perturbed_start(&robot),
                    options,
                )
                .unwrap();
                let d = left_difference(&est.flange_from_camera, &robot.flange_from_camera);
                let mut cov = est.flange_from_camera_covariance;
                if let Some(v) = &est.flange_from_camera_spread {
                    widen6_to_spread(&mut cov, v);
                }
                let m2 = mahalanobis2(&d, &cov).unwrap();
                if m2 <= chi2_6_95 {
                    inside[k] += 1;
                }
            }
        }
        let frac = inside.map(|v| v as f64 / n as f64);
        eprintln!(
            "hand-eye 95% ellipsoid coverage: {} (the noise model alone: {}; corner noise \
             only: {}, widened to the leave-one-out spread: {})",
            frac[0], frac[2], frac[1], frac[3]
        );
        assert!((0.90..=0.99).contains(&frac[0]), "coverage {}", frac[0]);
        assert!((0.90..=0.99).contains(&frac[2]), "model alone {}", frac[2]);
        // Without the robot term the model's covariance is far too small...
        assert!(
            frac[1] <= 0.05,
            "coverage without the robot term {}",
            frac[1]
        );
        // ...and the captures' leave-one-out spread recovers most of it
        // (79% here: fifteen captures give the spread of six dimensions).
        assert!(
            (0.79 / 1.5..0.99).contains(&frac[3]),
            "widened coverage without the robot term {}",
            frac[3]
        );
    }
}
