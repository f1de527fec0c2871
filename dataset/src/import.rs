//! Pose samples other calibration tools save, as `b2b-dataset/1` pose-only rows
//! (`T_base_flange` with `T_camera_target`, no image), so their users can run
//! our estimator on data they already have.
//!
//! **easy_handeye2** (ROS 2) saves a calibration's samples as YAML, `NAME.samples`:
//!
//! ```yaml
//! parameters:
//!   calibration_type: eye_in_hand     # or eye_on_base; may be empty
//!   robot_base_frame: ...             # the other frame names are kept as text
//! samples:
//! - robot:    {translation: {x, y, z}, rotation: {x, y, z, w}}
//!   tracking: {translation: {x, y, z}, rotation: {x, y, z, w}}
//! ```
//!
//! Each sample is two tf lookups (`lookup_transform(target, source)`, the pose of
//! `source` in `target`): for an eye-in-hand calibration, `robot` is the effector in
//! the robot base, `T_base_flange` (with the effector frame as the flange), and
//! `tracking` the marker in the camera (tracking base) frame, `T_camera_target`.
//! An eye-on-base file has the robot transform inverted and a camera that does not
//! ride on the arm: it is refused, as this project calibrates flange cameras. An
//! empty `calibration_type` is taken as eye-in-hand.
//!
//! **MoveIt Calibration** ("Save samples" in its RViz plugin) saves a YAML list:
//!
//! ```yaml
//! - effector_wrt_world: [16 numbers]   # 4x4, row-major
//!   object_wrt_sensor: [16 numbers]
//! ```
//!
//! `effector_wrt_world` is `lookupTransform(base, eef)`, the effector in the robot
//! base: `T_base_flange`; `object_wrt_sensor` is `lookupTransform(sensor, object)`,
//! the target in the camera: `T_camera_target`. The file does not say how the
//! camera was mounted; it is taken as eye-in-hand.

use std::path::Path;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde::Deserialize;

use crate::{Capture, DatasetError, Location};

#[derive(Debug, Deserialize)]
struct SamplesFile {
    #[serde(default)]
    parameters: Option<Parameters>,
    samples: Vec<Sample>,
}

#[derive(Debug, Deserialize)]
struct Parameters {
    #[serde(default)]
    calibration_type: Option<String>,
}

#[derive(Debug, Deserialize)]
struct Sample {
    robot: Transform,
    tracking: Transform,
}

#[derive(Debug, Deserialize)]
struct Transform {
    translation: Xyz,
    rotation: Xyzw,
}

#[derive(Debug, Deserialize)]
struct Xyz {
    x: f64,
    y: f64,
    z: f64,
}

#[derive(Debug, Deserialize)]
struct Xyzw {
    x: f64,
    y: f64,
    z: f64,
    w: f64,
}

impl Transform {
    /// The transform, or what is wrong with it (`field` names it in the error).
    fn isometry(&self, file: &Path, field: &str) -> Result<Isometry3<f64>, DatasetError> {
        let at = || Location::field(file, field);
        let t = &self.translation;
        let r = &self.rotation;
        for value in [t.x, t.y, t.z, r.x, r.y, r.z, r.w] {
            if !value.is_finite() {
                return Err(DatasetError::NonFinite { at: at(), value });
            }
        }
        for value in [t.x, t.y, t.z] {
            if value.abs() > crate::MAX_COORDINATE_M {
                return Err(DatasetError::LooksLikeMillimetres { at: at(), value });
            }
        }
        let q = Quaternion::new(r.w, r.x, r.y, r.z);
        let norm = q.norm();
        if (norm - 1.0).abs() > b2b_protocol::QUATERNION_NORM_TOLERANCE {
            return Err(DatasetError::NotUnitQuaternion { at: at(), norm });
        }
        Ok(Isometry3::from_parts(
            Translation3::new(t.x, t.y, t.z),
            UnitQuaternion::from_quaternion(q),
        ))
    }
}

/// The `i`-th sample as a pose-only row (numbered from 1, no image).
fn pose_only(
    i: usize,
    base_from_flange: Isometry3<f64>,
    camera_from_target: Isometry3<f64>,
) -> Capture {
    Capture {
        row: i + 1,
        image: None,
        depth: None,
        base_from_flange,
        camera_from_target: Some(camera_from_target),
        target: None,
    }
}

/// Refuses more than [`crate::MAX_IMPORT_SAMPLES`] samples.
fn check_sample_count(file: &Path, n: usize) -> Result<(), DatasetError> {
    if n <= crate::MAX_IMPORT_SAMPLES {
        return Ok(());
    }
    Err(DatasetError::TooManyRows {
        file: file.to_owned(),
        what: "samples",
        limit: crate::MAX_IMPORT_SAMPLES,
        constant: "MAX_IMPORT_SAMPLES",
        advice: "the samples become one robot's captures, and a hand-eye needs tens: keep a subset",
    })
}

/// Reads a YAML file into `T`, naming the file in errors.
fn read_yaml<T: serde::de::DeserializeOwned>(file: &Path) -> Result<T, DatasetError> {
    let bytes = crate::read_bytes_max(
        file,
        "expected another tool's saved samples (YAML)",
        crate::MAX_SAMPLES_FILE_BYTES,
    )?;
    serde_yaml::from_slice(&bytes).map_err(|source| DatasetError::Yaml {
        file: file.to_owned(),
        source,
    })
}

#[derive(Debug, Deserialize)]
struct MoveItSample {
    effector_wrt_world: Vec<f64>,
    object_wrt_sensor: Vec<f64>,
}

/// Largest deviation from a rotation (`|RᵀR - I|`, `|det R - 1|`) a 4x4 matrix
/// of another tool may carry (its numbers are printed to about 6 digits).
const ROTATION_TOLERANCE: f64 = 1e-4;

/// A row-major 4x4 homogeneous transform, or what is wrong with it.
fn matrix_isometry(
    values: &[f64],
    file: &Path,
    field: &str,
) -> Result<Isometry3<f64>, DatasetError> {
    let at = || Location::field(file, field);
    if values.len() != 16 {
        return Err(DatasetError::Unsupported {
            at: at(),
            reason: format!("{} numbers, a 4x4 matrix has 16", values.len()),
        });
    }
    if let Some(&value) = values.iter().find(|v| !v.is_finite()) {
        return Err(DatasetError::NonFinite { at: at(), value });
    }
    let m = nalgebra::Matrix4::from_row_slice(values);
    if (m.row(3) - nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0))
        .abs()
        .max()
        > ROTATION_TOLERANCE
    {
        return Err(DatasetError::Unsupported {
            at: at(),
            reason: format!(
                "last row {:?} is not 0 0 0 1",
                m.row(3).iter().collect::<Vec<_>>()
            ),
        });
    }
    let r: nalgebra::Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into();
    let off = (r.transpose() * r - nalgebra::Matrix3::identity())
        .abs()
        .max();
    let det = r.determinant();
    if off > ROTATION_TOLERANCE || (det - 1.0).abs() > ROTATION_TOLERANCE {
        return Err(DatasetError::Unsupported {
            at: at(),
            reason: format!(
                "the upper-left 3x3 is not a rotation (|RᵀR - I| = {off:.2e}, det = {det:.6})"
            ),
        });
    }
    let t = m.fixed_view::<3, 1>(0, 3);
    for &value in t.iter() {
        if value.abs() > crate::MAX_COORDINATE_M {
            return Err(DatasetError::LooksLikeMillimetres { at: at(), value });
        }
    }
    Ok(Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_matrix(&r),
    ))
}

/// Reads a MoveIt Calibration samples file as pose-only captures, in the file's
/// order (rows numbered from 1).
pub fn read_moveit_samples(file: &Path) -> Result<Vec<Capture>, DatasetError> {
    let samples: Vec<MoveItSample> = read_yaml(file)?;
    if samples.is_empty() {
        return Err(DatasetError::Unsupported {
            at: Location::file(file),
            reason: "no samples".into(),
        });
    }
    check_sample_count(file, samples.len())?;
    samples
        .iter()
        .enumerate()
        .map(|(i, s)| {
            Ok(pose_only(
                i,
                matrix_isometry(
                    &s.effector_wrt_world,
                    file,
                    &format!("[{i}].effector_wrt_world"),
                )?,
                matrix_isometry(
                    &s.object_wrt_sensor,
                    file,
                    &format!("[{i}].object_wrt_sensor"),
                )?,
            ))
        })
        .collect()
}

/// Reads an easy_handeye2 `.samples` file as pose-only captures, in the file's
/// order (rows numbered from 1).
pub fn read_easy_handeye_samples(file: &Path) -> Result<Vec<Capture>, DatasetError> {
    let parsed: SamplesFile = read_yaml(file)?;
    let kind = parsed
        .parameters
        .and_then(|p| p.calibration_type)
        .unwrap_or_default();
    match kind.as_str() {
        "" | "eye_in_hand" => {}
        other => {
            return Err(DatasetError::Unsupported {
                at: Location::field(file, "parameters.calibration_type"),
                reason: format!(
                    "`{other}`: only eye-in-hand samples (a camera on the flange) can be imported"
                ),
            });
        }
    }
    if parsed.samples.is_empty() {
        return Err(DatasetError::Unsupported {
            at: Location::field(file, "samples"),
            reason: "no samples".into(),
        });
    }
    check_sample_count(file, parsed.samples.len())?;
    parsed
        .samples
        .iter()
        .enumerate()
        .map(|(i, s)| {
            Ok(pose_only(
                i,
                s.robot.isometry(file, &format!("samples[{i}].robot"))?,
                s.tracking
                    .isometry(file, &format!("samples[{i}].tracking"))?,
            ))
        })
        .collect()
}

/// Adds `robot`'s imported `captures` (with its `camera`) to the dataset in `dir`,
/// or creates it there with `target`, and writes it. An existing dataset must
/// have the same target and not list `robot` yet: nothing is replaced.
/// `source` says where the captures came from (kept in the manifest's `source`).
pub fn add_robot(
    dir: &Path,
    robot: &str,
    target: crate::Target,
    camera: crate::Intrinsics,
    captures: Vec<Capture>,
    source: &str,
) -> Result<crate::Dataset, DatasetError> {
    let manifest_file = dir.join(crate::MANIFEST_FILE);
    let mut dataset = if manifest_file.exists() {
        let ds = crate::Dataset::load(dir)?;
        if ds.manifest.target != target {
            return Err(DatasetError::Unsupported {
                at: Location::field(&manifest_file, "target"),
                reason: format!(
                    "the dataset's target is {:?}, the import's {:?}: one dataset has one target",
                    ds.manifest.target, target
                ),
            });
        }
        if ds.manifest.robot(robot).is_some() {
            return Err(DatasetError::Unsupported {
                at: Location::field(&manifest_file, "robots"),
                reason: format!("robot `{robot}` is already in the dataset; nothing was replaced"),
            });
        }
        ds
    } else {
        let name = dir.file_name().map_or_else(
            || "imported".to_owned(),
            |n| n.to_string_lossy().into_owned(),
        );
        crate::Dataset {
            root: dir.to_owned(),
            manifest: crate::Manifest::new(name, target, vec![]),
            robots: vec![],
            touch_points: None,
            pair_touch_points: Default::default(),
        }
    };
    let mut entry = crate::RobotManifest::new(robot);
    entry.camera = Some(camera);
    dataset.manifest.robots.push(entry);
    dataset.robots.push(crate::RobotData {
        id: robot.to_owned(),
        captures,
    });
    let line = format!("{robot}: imported from {source}");
    dataset.manifest.source = if dataset.manifest.source.is_empty() {
        line
    } else {
        format!("{}; {line}", dataset.manifest.source)
    };
    dataset.write(dir)?;
    crate::Dataset::load(dir)
}
