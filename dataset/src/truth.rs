//! `ground_truth.json` and `reference.json`: known transforms, for evaluation only.
//!
//! They are deliberately not part of [`crate::Dataset`]: a calibration that is handed a
//! `Dataset` cannot peek at the answer, because the answer is not in it. Evaluation code
//! calls [`load_ground_truth`] or [`load_reference`] explicitly.
//!
//! Poses use [`b2b_protocol::Pose`] on the wire, checked like every pose of the format
//! (unit quaternion, metres). Robot ids are checked against `dataset.json`, so that a
//! misspelt id is an error rather than an evaluation that silently compares nothing.
//! For the same reason a key `T_base1_base<n>` must name a further robot of the
//! manifest (`n` from 3 to the number of robots): `T_base1_base03`, `T_base1_base1` or
//! `T_base1_base7` in a three-robot dataset is an error, not a pose nobody compares.

use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;

use b2b_protocol::Pose;
use nalgebra::Isometry3;
use serde::de::{IgnoredAny, MapAccess, Visitor};
use serde::ser::SerializeMap;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::error::{DatasetError, Location};
use crate::manifest::Manifest;
use crate::pose;
use crate::{GROUND_TRUTH_FILE, REFERENCE_FILE};

/// The known transforms of `ground_truth.json`. Every part is optional.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GroundTruth {
    /// `T_base1_base2`.
    pub base1_from_base2: Option<Isometry3<f64>>,
    /// `T_base1_base<n>` of the further robots, keyed by the 1-based robot number
    /// `n >= 3` in `dataset.json` order.
    pub base1_from_base_n: BTreeMap<usize, Isometry3<f64>>,
    /// `T_flange_camera` by robot id.
    pub flange_from_camera: BTreeMap<String, Isometry3<f64>>,
    /// `T_base_target` by robot id.
    pub base_from_target: BTreeMap<String, Isometry3<f64>>,
}

impl GroundTruth {
    /// `T_base1_base<n>` of robot `n` (1-based, `dataset.json` order): the identity for
    /// robot 1, [`Self::base1_from_base2`] for robot 2, [`Self::base1_from_base_n`]
    /// otherwise; `None` when not known (or `n == 0`).
    pub fn base1_from_base(&self, n: usize) -> Option<Isometry3<f64>> {
        base1_from_base(n, self.base1_from_base2, &self.base1_from_base_n)
    }
}

/// Another tool's published result (`reference.json`): a comparison, not the truth.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Reference {
    /// Which tool, which version, where it was published.
    pub source: String,
    /// `T_base1_base2`.
    pub base1_from_base2: Option<Isometry3<f64>>,
    /// `T_base1_base<n>` of the further robots, keyed by the 1-based robot number
    /// `n >= 3` in `dataset.json` order.
    pub base1_from_base_n: BTreeMap<usize, Isometry3<f64>>,
    /// `T_flange_camera` by robot id.
    pub flange_from_camera: BTreeMap<String, Isometry3<f64>>,
    /// `T_base_target` by robot id.
    pub base_from_target: BTreeMap<String, Isometry3<f64>>,
}

impl Reference {
    /// Like [`GroundTruth::base1_from_base`].
    pub fn base1_from_base(&self, n: usize) -> Option<Isometry3<f64>> {
        base1_from_base(n, self.base1_from_base2, &self.base1_from_base_n)
    }
}

fn base1_from_base(
    n: usize,
    base1_from_base2: Option<Isometry3<f64>>,
    further: &BTreeMap<usize, Isometry3<f64>>,
) -> Option<Isometry3<f64>> {
    match n {
        0 => None,
        1 => Some(Isometry3::identity()),
        2 => base1_from_base2,
        n => further.get(&n).copied(),
    }
}

/// The prefix of every base key (`T_base1_base2`, `T_base1_base3`, ...).
const BASE_KEY_PREFIX: &str = "T_base1_base";
/// The first robot number written as a `T_base1_base<n>` key of its own.
const FIRST_FURTHER_ROBOT: usize = 3;

/// The key of robot `n`'s base.
fn base_key(n: usize) -> String {
    format!("{BASE_KEY_PREFIX}{n}")
}

/// The robot number of a base key, when the key is `T_base1_base` and a number written
/// as Rust prints it (no sign, no leading zero).
fn base_number(key: &str) -> Option<usize> {
    let digits = key.strip_prefix(BASE_KEY_PREFIX)?;
    let n: usize = digits.parse().ok()?;
    (n.to_string() == digits).then_some(n)
}

/// The known keys, as read (the further robots' bases are read by [`RawBases`]).
#[derive(Debug, Deserialize)]
struct RawReference {
    #[serde(default)]
    source: Option<String>,
    #[serde(rename = "T_base1_base2", default)]
    base1_base2: Option<Pose>,
    #[serde(rename = "T_flange_camera", default)]
    flange_camera: BTreeMap<String, Pose>,
    #[serde(rename = "T_base_target", default)]
    base_target: BTreeMap<String, Pose>,
}

/// Every key of the file that starts with `T_base1_base`, except `T_base1_base2`: the
/// pose when the key is `T_base1_base<n>` with `n >= 3`, `None` (value not read) for
/// any other such key, so that the check after parsing can name it.
#[derive(Debug, Default)]
struct RawBases(Vec<(String, Option<Pose>)>);

impl<'de> Deserialize<'de> for RawBases {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Keys;
        impl<'de> Visitor<'de> for Keys {
            type Value = RawBases;

            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a JSON object")
            }

            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<RawBases, A::Error> {
                let mut out = vec![];
                while let Some(key) = map.next_key::<String>()? {
                    if !key.starts_with(BASE_KEY_PREFIX) || key == base_key(2) {
                        map.next_value::<IgnoredAny>()?;
                    } else if base_number(&key).is_some_and(|n| n >= FIRST_FURTHER_ROBOT) {
                        let pose = map.next_value::<Pose>()?;
                        out.push((key, Some(pose)));
                    } else {
                        map.next_value::<IgnoredAny>()?;
                        out.push((key, None));
                    }
                }
                Ok(RawBases(out))
            }
        }
        deserializer.deserialize_map(Keys)
    }
}

/// What is written: the keys in the format's order, the further robots' bases after
/// `T_base1_base2` in robot order.
#[derive(Debug, Serialize)]
struct RawOut {
    #[serde(skip_serializing_if = "Option::is_none")]
    source: Option<String>,
    #[serde(rename = "T_base1_base2", skip_serializing_if = "Option::is_none")]
    base1_base2: Option<Pose>,
    #[serde(flatten)]
    further: FurtherBases,
    #[serde(rename = "T_flange_camera", skip_serializing_if = "BTreeMap::is_empty")]
    flange_camera: BTreeMap<String, Pose>,
    #[serde(rename = "T_base_target", skip_serializing_if = "BTreeMap::is_empty")]
    base_target: BTreeMap<String, Pose>,
}

/// `T_base1_base<n>` entries, in the order of `n` (not of the keys' text, which would
/// put `T_base1_base10` before `T_base1_base3`).
#[derive(Debug)]
struct FurtherBases(BTreeMap<usize, Pose>);

impl Serialize for FurtherBases {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let mut map = serializer.serialize_map(Some(self.0.len()))?;
        for (n, pose) in &self.0 {
            map.serialize_entry(&base_key(*n), pose)?;
        }
        map.end()
    }
}

/// The transforms both files hold.
#[derive(Debug, Default)]
struct Transforms {
    base1_from_base2: Option<Isometry3<f64>>,
    base1_from_base_n: BTreeMap<usize, Isometry3<f64>>,
    flange_from_camera: BTreeMap<String, Isometry3<f64>>,
    base_from_target: BTreeMap<String, Isometry3<f64>>,
}

/// Reads `<dir>/ground_truth.json`, or `None` when the dataset has none.
pub fn load_ground_truth(dir: &Path) -> Result<Option<GroundTruth>, DatasetError> {
    let Some((_, t)) = load_raw(dir, GROUND_TRUTH_FILE)? else {
        return Ok(None);
    };
    Ok(Some(GroundTruth {
        base1_from_base2: t.base1_from_base2,
        base1_from_base_n: t.base1_from_base_n,
        flange_from_camera: t.flange_from_camera,
        base_from_target: t.base_from_target,
    }))
}

/// Reads `<dir>/reference.json`, or `None` when the dataset has none.
pub fn load_reference(dir: &Path) -> Result<Option<Reference>, DatasetError> {
    let Some((source, t)) = load_raw(dir, REFERENCE_FILE)? else {
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
        base1_from_base2: t.base1_from_base2,
        base1_from_base_n: t.base1_from_base_n,
        flange_from_camera: t.flange_from_camera,
        base_from_target: t.base_from_target,
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
    let bases: RawBases = crate::parse_json(&text, &file)?;
    let manifest = Manifest::load(&dir)?;
    let at = |f: String| Location::field(&file, f);
    let base1_from_base2 = match &raw.base1_base2 {
        Some(p) => Some(pose::isometry_from_pose(p, &base_key(2), at)?),
        None => None,
    };
    let robots = manifest.robots.len();
    let mut base1_from_base_n = BTreeMap::new();
    for (key, p) in &bases.0 {
        let bad = |reason: String| DatasetError::UnknownBaseKey {
            at: at(key.clone()),
            reason,
        };
        let (n, p) = match (base_number(key), p) {
            (Some(n), Some(p)) if n <= robots => (n, p),
            (Some(n), Some(_)) => {
                return Err(bad(format!(
                    "`{key}` is the base of robot {n}, but dataset.json lists {robots} robot(s)"
                )));
            }
            (Some(n), None) => {
                return Err(bad(format!(
                    "`{key}` names robot {n}: robot 1's base is base1 itself, robot 2's is \
                     `T_base1_base2`, and keys of their own start at `T_base1_base3`"
                )));
            }
            (None, _) => {
                return Err(bad(format!(
                    "unknown key `{key}`; the further robots' bases are `T_base1_base3`, \
                     `T_base1_base4`, ... (robots numbered from 1 in dataset.json order)"
                )));
            }
        };
        let iso = pose::isometry_from_pose(p, key, at)?;
        if base1_from_base_n.insert(n, iso).is_some() {
            return Err(bad(format!("`{key}` is given twice")));
        }
    }
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
        Transforms {
            base1_from_base2,
            base1_from_base_n,
            flange_from_camera,
            base_from_target,
        },
    )))
}

/// Writes `<dir>/ground_truth.json`, poses exactly as given.
pub fn write_ground_truth(dir: &Path, truth: &GroundTruth) -> Result<(), DatasetError> {
    let transforms = Transforms {
        base1_from_base2: truth.base1_from_base2,
        base1_from_base_n: truth.base1_from_base_n.clone(),
        flange_from_camera: truth.flange_from_camera.clone(),
        base_from_target: truth.base_from_target.clone(),
    };
    write_raw(dir, GROUND_TRUTH_FILE, None, &transforms)
}

/// Writes `<dir>/reference.json`, poses exactly as given.
pub fn write_reference(dir: &Path, reference: &Reference) -> Result<(), DatasetError> {
    let transforms = Transforms {
        base1_from_base2: reference.base1_from_base2,
        base1_from_base_n: reference.base1_from_base_n.clone(),
        flange_from_camera: reference.flange_from_camera.clone(),
        base_from_target: reference.base_from_target.clone(),
    };
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
    t: &Transforms,
) -> Result<(), DatasetError> {
    let file = crate::absolute(dir).join(name);
    let at = |f: String| Location::field(&file, f);
    let check = |iso: &Isometry3<f64>, name: &str| {
        pose::isometry_from_pose(&pose::pose_from_isometry(iso), name, at).map(|_| ())
    };
    if let Some(iso) = &t.base1_from_base2 {
        check(iso, &base_key(2))?;
    }
    for (&n, iso) in &t.base1_from_base_n {
        if n < FIRST_FURTHER_ROBOT {
            return Err(DatasetError::UnknownBaseKey {
                at: at(base_key(n)),
                reason: format!(
                    "robot {n} has no key of its own: robot 1's base is base1 itself, robot \
                     2's is `T_base1_base2` (GroundTruth::base1_from_base2)"
                ),
            });
        }
        check(iso, &base_key(n))?;
    }
    for (key, map) in [
        ("T_flange_camera", &t.flange_from_camera),
        ("T_base_target", &t.base_from_target),
    ] {
        for (id, iso) in map {
            check(iso, &format!("{key}.{id}"))?;
        }
    }
    let poses = |m: &BTreeMap<String, Isometry3<f64>>| {
        m.iter()
            .map(|(k, v)| (k.clone(), pose::pose_from_isometry(v)))
            .collect()
    };
    let raw = RawOut {
        source,
        base1_base2: t.base1_from_base2.as_ref().map(pose::pose_from_isometry),
        further: FurtherBases(
            t.base1_from_base_n
                .iter()
                .map(|(n, v)| (*n, pose::pose_from_isometry(v)))
                .collect(),
        ),
        flange_camera: poses(&t.flange_from_camera),
        base_target: poses(&t.base_from_target),
    };
    let mut text = serde_json::to_string_pretty(&raw).map_err(|e| DatasetError::json(&file, e))?;
    text.push('\n');
    std::fs::create_dir_all(dir).map_err(|e| DatasetError::io(dir, e))?;
    crate::write_atomic(&file, text.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base_numbers_are_canonical() {
        assert_eq!(base_number("T_base1_base3"), Some(3));
        assert_eq!(base_number("T_base1_base12"), Some(12));
        for key in [
            "T_base1_base",
            "T_base1_baseX",
            "T_base1_base03",
            "T_base1_base+3",
            "T_base1_base 3",
            "T_base2_base3",
        ] {
            assert_eq!(base_number(key), None, "{key}");
        }
    }

    #[test]
    fn base1_from_base_covers_every_robot() {
        let b2 = Isometry3::translation(1.0, 0.0, 0.0);
        let b3 = Isometry3::translation(0.0, 1.0, 0.0);
        let truth = GroundTruth {
            base1_from_base2: Some(b2),
            base1_from_base_n: BTreeMap::from([(3, b3)]),
            ..GroundTruth::default()
        };
        assert_eq!(truth.base1_from_base(0), None);
        assert_eq!(truth.base1_from_base(1), Some(Isometry3::identity()));
        assert_eq!(truth.base1_from_base(2), Some(b2));
        assert_eq!(truth.base1_from_base(3), Some(b3));
        assert_eq!(truth.base1_from_base(4), None);
    }
}
