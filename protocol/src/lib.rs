//! Wire and file types of the base-to-base calibration service.
//!
//! This crate is the bottom layer: plain serde types and their validation, nothing
//! else. It performs no I/O, links no OpenCV, starts no runtime. Everything that
//! crosses a process boundary (zenoh messages, result files, hand-eye files, the
//! verification report) is described here, so every service and every test agrees
//! on one definition.
//!
//! Poses are written as `{"t": [x, y, z], "q": [qx, qy, qz, qw]}`: metres, Hamilton
//! quaternion in x, y, z, w order, and a pose named `T_a_b` maps points of frame `b`
//! into frame `a` (`p_a = T_a_b * p_b`). In Rust the same transform is `a_from_b`.

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

/// Format tag of a base-to-base result file.
pub const RESULT_FORMAT: &str = "b2b-result/1";
/// Format tag of a hand-eye result file.
pub const HANDEYE_FORMAT: &str = "b2b-handeye/1";

/// How far from unit norm a quaternion on the wire may be before it is rejected
/// rather than normalised. Six printed digits per component stay well inside it.
pub const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

/// Errors of this crate: a wire value that cannot be trusted.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ProtocolError {
    /// A number that must be finite is NaN or infinite.
    #[error("{field}: value {value} is not finite")]
    NonFinite { field: String, value: f64 },
    /// A quaternion whose norm is too far from 1 to be a rotation.
    #[error("{field}: quaternion norm {norm:.6} is not 1 (tolerance {tolerance})")]
    NotUnitQuaternion {
        field: String,
        norm: f64,
        tolerance: f64,
    },
    /// A covariance that is not symmetric positive semi-definite or not finite.
    #[error("{field}: {reason}")]
    BadCovariance { field: String, reason: String },
    /// Any other field with a value that cannot be trusted.
    #[error("{field}: {reason}")]
    BadField { field: String, reason: String },
}

/// A rigid transform as it is written in files and messages.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Translation in metres.
    pub t: [f64; 3],
    /// Rotation as a Hamilton quaternion, x, y, z, w.
    pub q: [f64; 4],
}

impl Pose {
    /// The identity transform.
    pub const IDENTITY: Pose = Pose {
        t: [0.0; 3],
        q: [0.0, 0.0, 0.0, 1.0],
    };

    /// Converts to an isometry, checking that every number is finite and that the
    /// quaternion is a rotation; `field` names the value in the error.
    pub fn to_isometry(&self, field: &str) -> Result<Isometry3<f64>, ProtocolError> {
        for (i, v) in self.t.iter().enumerate() {
            if !v.is_finite() {
                return Err(ProtocolError::NonFinite {
                    field: format!("{field}.t[{i}]"),
                    value: *v,
                });
            }
        }
        for (i, v) in self.q.iter().enumerate() {
            if !v.is_finite() {
                return Err(ProtocolError::NonFinite {
                    field: format!("{field}.q[{i}]"),
                    value: *v,
                });
            }
        }
        let [x, y, z, w] = self.q;
        let q = Quaternion::new(w, x, y, z);
        let norm = q.norm();
        if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
            return Err(ProtocolError::NotUnitQuaternion {
                field: format!("{field}.q"),
                norm,
                tolerance: QUATERNION_NORM_TOLERANCE,
            });
        }
        Ok(Isometry3::from_parts(
            Translation3::new(self.t[0], self.t[1], self.t[2]),
            UnitQuaternion::from_quaternion(q),
        ))
    }

    /// Writes an isometry. The quaternion is put in the hemisphere `w >= 0` so that
    /// the same rotation always prints the same way.
    pub fn from_isometry(a_from_b: &Isometry3<f64>) -> Self {
        let t = a_from_b.translation.vector;
        let mut q = *a_from_b.rotation.quaternion();
        if q.w < 0.0 {
            q = -q;
        }
        Pose {
            t: [t.x, t.y, t.z],
            q: [q.i, q.j, q.k, q.w],
        }
    }
}

impl From<&Isometry3<f64>> for Pose {
    fn from(value: &Isometry3<f64>) -> Self {
        Pose::from_isometry(value)
    }
}

/// A 6x6 covariance over the perturbation `[rx, ry, rz, tx, ty, tz]` (radians,
/// metres) applied on the left of the pose it belongs to.
pub type Covariance6 = [[f64; 6]; 6];

/// Checks a covariance for finiteness, symmetry and a non-negative diagonal.
pub fn validate_covariance(field: &str, c: &Covariance6) -> Result<(), ProtocolError> {
    let scale = c.iter().flatten().fold(1.0f64, |m, v| m.max(v.abs()));
    for (i, row) in c.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            if !v.is_finite() {
                return Err(ProtocolError::NonFinite {
                    field: format!("{field}[{i}][{j}]"),
                    value: *v,
                });
            }
            if (v - c[j][i]).abs() > 1e-12 * scale {
                return Err(ProtocolError::BadCovariance {
                    field: field.to_owned(),
                    reason: format!("not symmetric at [{i}][{j}]"),
                });
            }
        }
        if row[i] < 0.0 {
            return Err(ProtocolError::BadCovariance {
                field: field.to_owned(),
                reason: format!("negative variance {} at [{i}][{i}]", row[i]),
            });
        }
    }
    // Positive semi-definite: no direction with a negative variance (a bound
    // computed from such a matrix would be imaginary or infinite). Rounding
    // may leave an eigenvalue a hair below zero; a real one is not that small.
    let m = nalgebra::Matrix6::from_fn(|i, j| c[i][j]);
    let eigen = m.symmetric_eigenvalues();
    let largest = eigen.amax();
    let smallest = eigen.min();
    if smallest < -1e-9 * largest {
        return Err(ProtocolError::BadCovariance {
            field: field.to_owned(),
            reason: format!(
                "not positive semi-definite: an eigenvalue is {smallest:.3e} (the largest {largest:.3e})"
            ),
        });
    }
    Ok(())
}

/// The predicted error of a touch-point check, in metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PredictedError {
    pub mean: f64,
    pub p95: f64,
}

/// A capture that was not used, and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RejectedCapture {
    pub robot: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<String>,
    /// Row of `captures.csv` (1-based, header excluded), when the capture came from a file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub row: Option<usize>,
    pub reason: String,
}

/// Which captures went into a result.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CaptureSummary {
    /// Robot id to the number of captures used.
    pub used: BTreeMap<String, usize>,
    pub rejected: Vec<RejectedCapture>,
    /// Each capture the fit saw, in each robot's order: how well the result
    /// explains it, and where it was seen from (optional; older files have
    /// none). Reports draw their per-capture panels from it.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub per_capture: Vec<CaptureFit>,
}

/// One capture in a result's [`CaptureSummary::per_capture`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureFit {
    pub robot: String,
    /// Its row in the robot's capture list (1-based), or its number live.
    pub row: usize,
    /// Image file or other name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<String>,
    /// RMS of its inlier corners under the result; `null` when it was left out
    /// before the fit or has no inlier corner. The RGB-D method: of its inlier
    /// features, each matched point carried from the other camera through the
    /// result and projected.
    pub rms_px: Option<f64>,
    /// Corners the robust stage rejected (the RGB-D method: matches RANSAC
    /// rejected in the accepted pairs the capture is in).
    pub outlier_corners: usize,
    /// Unit vector from the target's origin to the camera, in the target frame
    /// (the RGB-D method: from the scene centre, in base 1's axes).
    pub view_direction: [f64; 3],
}

/// Wall-clock time spent, in milliseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Timings {
    pub detect: f64,
    pub solve: f64,
    pub total: f64,
}

/// `RESULT.json`: the base-to-base result (shared/interfaces.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationResult {
    pub format: String,
    pub method: String,
    #[serde(rename = "T_base1_base2")]
    pub base1_from_base2: Pose,
    pub covariance: Covariance6,
    pub predicted_touch_error_m: PredictedError,
    /// Robot id to `T_flange_camera`.
    pub hand_eye: BTreeMap<String, Pose>,
    pub captures: CaptureSummary,
    pub timings_ms: Timings,
    /// The robot whose base the others are given in: the first in the
    /// dataset (`T_base1_base2` is robot 2's base in it). Older files have none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference: Option<String>,
    /// With more than two robots: every other robot's base in the reference's,
    /// by robot id (the second robot's repeats `T_base1_base2`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub bases: BTreeMap<String, BaseResult>,
    /// With more than two robots: each pair without the reference, from the
    /// same joint solve (its covariance includes what the two bases share).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pairs: Vec<PairResult>,
    /// Robot id to the covariance of its `hand_eye`, as HANDEYE.json's
    /// `covariance`. Older files and the RGB-D method have none.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub hand_eye_covariance: BTreeMap<String, Covariance6>,
    /// What an operator must see before trusting the result (for example, a
    /// hand-eye that no longer matches its cart's history). Empty when none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// What the checks of the input and of the fit found, each with its
    /// evidence: a named likely cause (poses inverted, a change mid-run, a
    /// board at another scale, intrinsics that do not fit, marker widths in
    /// the wrong unit), or the covariance widened beyond chance. Empty when
    /// none; older files have none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub findings: Vec<Finding>,
    /// The verdict against the operator's tolerance (`--tolerance-mm`).
    /// Older files have none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verdict: Option<Verdict>,
    /// How the estimator was chosen: by cross-validation over the captures
    /// (`b2b_calib::select`). Older files, the RGB-D method and problems that
    /// were not cross-validated (several targets, too few captures) have none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_selection: Option<ModelSelection>,
}

/// Something the checks found ([`CalibrationResult::findings`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Finding {
    /// What kind: `inverted_poses`, `change_point`, `board_scale`,
    /// `intrinsics`, `multimarker_units`, `spread_beyond_chance`,
    /// `depth_scale`; in a verification, `swapped_robots`.
    pub kind: String,
    /// The robot it concerns, when one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robot: Option<String>,
    /// The row of the robot's capture list it concerns, when one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub row: Option<usize>,
    /// Whether it fails the verdict (a named cause of a wrong result), or
    /// only informs (the reported uncertainty already holds it).
    pub fails: bool,
    /// The finding and its evidence, for an operator.
    pub message: String,
}

/// A verdict against the tolerance the operation needs: the largest
/// acceptable p95 touch error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    pub pass: bool,
    /// The tolerance, mm.
    pub tolerance_mm: f64,
    /// Why it fails; empty when it passes.
    pub reasons: Vec<String>,
}

impl Verdict {
    /// The last line a command prints: `VERDICT: PASS ...` or `VERDICT: FAIL <why>`.
    pub fn line(&self, what: &str) -> String {
        if self.pass {
            format!(
                "VERDICT: PASS ({what} within the tolerance of {:.2} mm)",
                self.tolerance_mm
            )
        } else {
            format!("VERDICT: FAIL {}", self.reasons.join("; "))
        }
    }
}

/// Which estimator the held-out captures chose ([`CalibrationResult::model_selection`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelSelection {
    /// The candidate chosen: `refined/<noise shape>` or a closed form's name.
    pub chosen: String,
    /// Candidate to the RMS (px) of the held-out captures' corners about where
    /// its fits without them put them; a candidate whose fit failed on a fold
    /// is absent.
    pub held_out_px: BTreeMap<String, f64>,
    /// Folds of consecutive captures per robot.
    pub folds: usize,
    /// The factor the chosen estimate's covariance was scaled by so that it
    /// holds the scatter of the fits without each fold (absent when it could
    /// not be computed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spread_scale: Option<f64>,
    /// The folds' scatter over what the chosen estimate's covariance predicts,
    /// applied (as `spread_scale`) or not: not where a fold's fit kept too few
    /// captures of a robot for the scatter to be evidence.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fold_scatter: Option<f64>,
    /// The candidates whose held-out figure lay within the selection's margin
    /// of the chosen one's: the evidence cannot tell them apart, so the bases
    /// are their mean with the chosen one's and their spread about it is part
    /// of the covariance (empty when none agreed or the folds were too small
    /// for their fits to be evidence).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub agreeing: Vec<String>,
}

/// One robot's base in the reference robot's base ([`CalibrationResult::bases`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BaseResult {
    #[serde(rename = "T_ref_base")]
    pub ref_from_base: Pose,
    /// Over the left perturbation `[rx, ry, rz, tx, ty, tz]` of `T_ref_base`.
    pub covariance: Covariance6,
    pub predicted_touch_error_m: PredictedError,
}

/// Robot `b`'s base in robot `a`'s ([`CalibrationResult::pairs`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PairResult {
    pub a: String,
    pub b: String,
    #[serde(rename = "T_a_b")]
    pub a_from_b: Pose,
    /// Over the left perturbation of `T_a_b` (in `a`'s base).
    pub covariance: Covariance6,
    pub predicted_touch_error_m: PredictedError,
}

impl CalibrationResult {
    /// Checks every pose and the covariance.
    pub fn validate(&self) -> Result<(), ProtocolError> {
        if self.format != RESULT_FORMAT {
            return Err(ProtocolError::BadField {
                field: "format".into(),
                reason: format!("expected {RESULT_FORMAT}, found {}", self.format),
            });
        }
        self.base1_from_base2.to_isometry("T_base1_base2")?;
        validate_covariance("covariance", &self.covariance)?;
        for (id, p) in &self.hand_eye {
            p.to_isometry(&format!("hand_eye.{id}"))?;
        }
        for (id, b) in &self.bases {
            b.ref_from_base
                .to_isometry(&format!("bases.{id}.T_ref_base"))?;
            validate_covariance(&format!("bases.{id}.covariance"), &b.covariance)?;
        }
        for (id, c) in &self.hand_eye_covariance {
            validate_covariance(&format!("hand_eye_covariance.{id}"), c)?;
        }
        for (i, p) in self.pairs.iter().enumerate() {
            p.a_from_b.to_isometry(&format!("pairs[{i}].T_a_b"))?;
            validate_covariance(&format!("pairs[{i}].covariance"), &p.covariance)?;
        }
        Ok(())
    }
}

/// Per-capture reprojection RMS in a hand-eye result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureResidual {
    pub image: String,
    /// RMS of the capture's inlier corners; `null` when it has none to measure
    /// (left out before the fit as a gross row, or every corner an outlier).
    pub rms_px: Option<f64>,
    /// Corners that the robust stage rejected as outliers.
    pub outlier_corners: usize,
}

/// `HANDEYE.json`: the hand-eye of one robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HandEyeResult {
    pub format: String,
    pub robot: String,
    pub method: String,
    #[serde(rename = "T_flange_camera")]
    pub flange_from_camera: Pose,
    /// Over `[rx, ry, rz, tx, ty, tz]` applied on the left of `T_flange_camera`.
    pub covariance: Covariance6,
    /// `T_base_target` estimated together with the hand-eye, when the method gives it.
    #[serde(
        rename = "T_base_target",
        default,
        skip_serializing_if = "Option::is_none"
    )]
    pub base_from_target: Option<Pose>,
    pub reprojection_rms_px: f64,
    pub per_capture: Vec<CaptureResidual>,
    pub captures: CaptureSummary,
    pub timings_ms: Timings,
}

/// `verify --json`: the touch-point check of a result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VerifyReport {
    pub n: usize,
    pub touch_mean_mm: f64,
    pub touch_rms_mm: f64,
    pub touch_max_mm: f64,
    pub procrustes_linear_error_mm: f64,
    pub procrustes_angular_error_deg: f64,
    pub within_predicted_p95: f64,
    /// Per location touched more than once (the touch file's `location` column):
    /// ISO 9283 pose accuracy and repeatability of robot 2's touches mapped into
    /// `base1`, against robot 1's mean touch of that location. Empty (and left out
    /// of the JSON) without repeated locations.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub iso9283: Vec<LocationIso9283>,
    /// All touches at once against the result's error model: the result's
    /// error as the touches see it (against its covariance) and their scatter
    /// about it (against the tip noise). Absent in files of older versions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bound_check: Option<TouchBoundCheck>,
    /// The verdict against the operator's tolerance (`--tolerance-mm`).
    /// Absent in files of older versions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verdict: Option<Verdict>,
    /// Named causes the touches show (`swapped_robots`: the touches fit the
    /// result inverted). Empty (and left out of the JSON) when none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub findings: Vec<Finding>,
}

/// See [`VerifyReport::bound_check`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TouchBoundCheck {
    pub offset_chi2: f64,
    pub offset_dof: usize,
    /// How often a right error model gives an offset this large.
    pub offset_p: f64,
    pub scatter_chi2: f64,
    pub scatter_dof: usize,
    pub scatter_p: f64,
    /// Each part beyond chance: p below 0.005 (together, 1% of right models
    /// are called wrong).
    pub offset_beyond_chance: bool,
    pub scatter_beyond_chance: bool,
    /// The error per axis common to each arm (mm) that would bring the
    /// offset to its expected size (0 when it fits): a rough size for
    /// `--robot-accuracy-mm`.
    pub offset_sigma_mm: f64,
    /// The error per axis, arm and touch (mm) beyond the tip noise (0 when
    /// the scatter fits).
    pub scatter_sigma_mm: f64,
}

impl TouchBoundCheck {
    /// Either part beyond chance.
    pub fn beyond_chance(&self) -> bool {
        self.offset_beyond_chance || self.scatter_beyond_chance
    }
}

/// ISO 9283 figures of one repeatedly touched location.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LocationIso9283 {
    pub location: String,
    /// Touches of this location.
    pub n: usize,
    /// AP: robot 2's barycentre (in `base1`, through the result) to robot 1's mean touch, mm.
    pub accuracy_mm: f64,
    /// RP: mean distance of robot 2's touches to their barycentre plus three standard
    /// deviations, mm.
    pub repeatability_mm: f64,
}

pub mod messages;

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn pose_round_trips_through_json_exactly() {
        let a_from_b = Isometry3::new(Vector3::new(0.1, -0.2, 0.3), Vector3::new(0.4, -1.1, 2.0));
        let pose = Pose::from_isometry(&a_from_b);
        let json = serde_json::to_string(&pose).unwrap();
        let back: Pose = serde_json::from_str(&json).unwrap();
        assert_eq!(back, pose);
        let iso = back.to_isometry("x").unwrap();
        assert!((iso.translation.vector - a_from_b.translation.vector).norm() < 1e-15);
        assert!(iso.rotation.angle_to(&a_from_b.rotation) < 1e-12);
    }

    #[test]
    fn non_unit_quaternion_is_rejected_with_field_name() {
        let p = Pose {
            t: [0.0; 3],
            q: [0.0, 0.0, 0.0, 2.0],
        };
        let err = p.to_isometry("hand_eye.robot1").unwrap_err();
        assert!(err.to_string().contains("hand_eye.robot1.q"), "{err}");
    }

    #[test]
    fn nan_translation_is_rejected() {
        let p = Pose {
            t: [0.0, f64::NAN, 0.0],
            q: [0.0, 0.0, 0.0, 1.0],
        };
        assert!(matches!(
            p.to_isometry("T").unwrap_err(),
            ProtocolError::NonFinite { .. }
        ));
    }

    #[test]
    fn asymmetric_covariance_is_rejected() {
        let mut c = [[0.0; 6]; 6];
        c[0][1] = 1.0;
        assert!(validate_covariance("covariance", &c).is_err());
    }

    /// Positive variances on the diagonal, symmetric, finite, and still no
    /// covariance: the direction (1, -1) in tx, ty has variance -1e-6.
    #[test]
    fn a_covariance_that_is_not_positive_semi_definite_is_rejected() {
        let mut c = [[0.0; 6]; 6];
        for (i, row) in c.iter_mut().enumerate() {
            row[i] = if i < 3 { 1e-8 } else { 1e-6 };
        }
        c[3][4] = 2e-6;
        c[4][3] = 2e-6;
        let e = validate_covariance("covariance", &c).unwrap_err();
        assert!(e.to_string().contains("not positive semi-definite"), "{e}");
        // At the edge: a singular one (rank 5) passes, as computed ones may be.
        c[3][4] = 1e-6;
        c[4][3] = 1e-6;
        validate_covariance("covariance", &c).unwrap();
        c[0][0] = f64::INFINITY;
        assert!(matches!(
            validate_covariance("covariance", &c),
            Err(ProtocolError::NonFinite { .. })
        ));
    }
}
