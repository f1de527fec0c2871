//! `ground_truth.json` and `reference.json`: known transforms, for evaluation only.
//!
//! They are deliberately not part of [`crate::Dataset`]: a calibration that is handed a
//! `Dataset` cannot peek at the answer, because the answer is not in it. Evaluation code
//! calls [`load_ground_truth`] or [`load_reference`] explicitly.
//!
//! Poses use [`b2b_protocol::Pose`] on the wire, checked like every pose of the format
//! (unit quaternion, metres). Robot ids are checked against `dataset.json`, so that a
//! misspelt id is an error rather than an evaluation that silently compares nothing.

use std::collections::BTreeMap;
use std::path::Path;

use b2b_protocol::Pose;
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::error::{DatasetError, Location};
use crate::manifest::Manifest;
use crate::pose;
use crate::{GROUND_TRUTH_FILE, REFERENCE_FILE};

/// The known transforms of `ground_truth.json`. Every part is optional.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GroundTruth {
    /// `T_base1_base2`.
    pub base1_from_base2: Option<Isometry3<f64>>,
    /// `T_flange_camera` by robot id.
    pub flange_from_camera: BTreeMap<String, Isometry3<f64>>,
    /// `T_base_target` by robot id.
    pub base_from_target: BTreeMap<String, Isometry3<f64>>,
}

/// Another tool's published result (`reference.json`): a comparison, not the truth.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Reference {
    /// Which tool, which version, where it was published.
    pub source: String,
    /// `T_base1_base2`.
    pub base1_from_base2: Option<Isometry3<f64>>,
    /// `T_flange_camera` by robot id.
    pub flange_from_camera: BTreeMap<String, Isometry3<f64>>,
    /// `T_base_target` by robot id.
    pub base_from_target: BTreeMap<String, Isometry3<f64>>,
}

#[derive(Debug, Serialize, Deserialize)]
struct RawReference {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    source: Option<String>,
    #[serde(
        rename = "T_base1_base2",
        default,
        skip_serializing_if = "Option::is_none"
    )]
    base1_base2: Option<Pose>,
    #[serde(
        rename = "T_flange_camera",
        default,
        skip_serializing_if = "BTreeMap::is_empty"
    )]
    flange_camera: BTreeMap<String, Pose>,
    #[serde(
        rename = "T_base_target",
        default,
        skip_serializing_if = "BTreeMap::is_empty"
    )]
    base_target: BTreeMap<String, Pose>,
}

type Transforms = (
    Option<Isometry3<f64>>,
    BTreeMap<String, Isometry3<f64>>,
    BTreeMap<String, Isometry3<f64>>,
);

/// Reads `<dir>/ground_truth.json`, or `None` when the dataset has none.
pub fn load_ground_truth(dir: &Path) -> Result<Option<GroundTruth>, DatasetError> {
    let Some((_, (base1_from_base2, flange_from_camera, base_from_target))) =
        load_raw(dir, GROUND_TRUTH_FILE)?
    else {
        return Ok(None);
    };
    Ok(Some(GroundTruth {
        base1_from_base2,
        flange_from_camera,
        base_from_target,
    }))
}

/// Reads `<dir>/reference.json`, or `None` when the dataset has none.
pub fn load_reference(dir: &Path) -> Result<Option<Reference>, DatasetError> {
    let Some((source, (base1_from_base2, flange_from_camera, base_from_target))) =
        load_raw(dir, REFERENCE_FILE)?
    else {
        return Ok(None);
    };
    let file = crate::absolute(dir).join(REFERENCE_FILE);
    let Some(source) = source else {
        return Err(DatasetError::InvalidManifest {
            at: Location::field(file, "source"),
            reason: "reference.json must say in `source` whose result it is".into(),
        });
    };
    Ok(Some(Reference {
        source,
        base1_from_base2,
        flange_from_camera,
        base_from_target,
    }))
}

fn load_raw(dir: &Path, name: &str) -> Result<Option<(Option<String>, Transforms)>, DatasetError> {
    let dir = crate::absolute(dir);
    let file = dir.join(name);
    if !file.exists() {
        return Ok(None);
    }
    let text = crate::read_text(&file, "it disappeared while being read")?;
    let raw: RawReference = crate::parse_json(&text, &file)?;
    let manifest = Manifest::load(&dir)?;
    let at = |f: String| Location::field(&file, f);
    let base1_from_base2 = match &raw.base1_base2 {
        Some(p) => Some(pose::isometry_from_pose(p, "T_base1_base2", at)?),
        None => None,
    };
    let by_robot = |key: &str, poses: &BTreeMap<String, Pose>| {
        let mut out = BTreeMap::new();
        for (id, p) in poses {
            let name = format!("{key}.{id}");
            if manifest.robot(id).is_none() {
                return Err(DatasetError::UnknownRobot {
                    at: at(name),
                    robot: id.clone(),
                });
            }
            out.insert(id.clone(), pose::isometry_from_pose(p, &name, at)?);
        }
        Ok(out)
    };
    let flange_from_camera = by_robot("T_flange_camera", &raw.flange_camera)?;
    let base_from_target = by_robot("T_base_target", &raw.base_target)?;
    Ok(Some((
        raw.source,
        (base1_from_base2, flange_from_camera, base_from_target),
    )))
}

/// Writes `<dir>/ground_truth.json`, poses exactly as given.
pub fn write_ground_truth(dir: &Path, truth: &GroundTruth) -> Result<(), DatasetError> {
    let transforms = (
        truth.base1_from_base2,
        truth.flange_from_camera.clone(),
        truth.base_from_target.clone(),
    );
    write_raw(dir, GROUND_TRUTH_FILE, None, &transforms)
}

/// Writes `<dir>/reference.json`, poses exactly as given.
pub fn write_reference(dir: &Path, reference: &Reference) -> Result<(), DatasetError> {
    let transforms = (
        reference.base1_from_base2,
        reference.flange_from_camera.clone(),
        reference.base_from_target.clone(),
    );
    write_raw(
        dir,
        REFERENCE_FILE,
        Some(reference.source.clone()),
        &transforms,
    )
}

fn write_raw(
    dir: &Path,
    name: &str,
    source: Option<String>,
    (b12, fc, bt): &Transforms,
) -> Result<(), DatasetError> {
    let file = crate::absolute(dir).join(name);
    let at = |f: String| Location::field(&file, f);
    let check = |iso: &Isometry3<f64>, name: &str| {
        pose::isometry_from_pose(&pose::pose_from_isometry(iso), name, at).map(|_| ())
    };
    if let Some(iso) = b12 {
        check(iso, "T_base1_base2")?;
    }
    for (key, map) in [("T_flange_camera", fc), ("T_base_target", bt)] {
        for (id, iso) in map {
            check(iso, &format!("{key}.{id}"))?;
        }
    }
    let poses = |m: &BTreeMap<String, Isometry3<f64>>| {
        m.iter()
            .map(|(k, v)| (k.clone(), pose::pose_from_isometry(v)))
            .collect()
    };
    let raw = RawReference {
        source,
        base1_base2: b12.as_ref().map(pose::pose_from_isometry),
        flange_camera: poses(fc),
        base_target: poses(bt),
    };
    let mut text = serde_json::to_string_pretty(&raw).map_err(|e| DatasetError::json(&file, e))?;
    text.push('\n');
    std::fs::create_dir_all(dir).map_err(|e| DatasetError::io(dir, e))?;
    crate::write_atomic(&file, text.as_bytes())
}
