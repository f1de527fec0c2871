//! `dataset.json`: the manifest.
//!
//! It is read in three stages so that each kind of mistake gets the most useful message:
//!
//! 1. as untyped JSON, so a syntax error is reported with serde's line and column;
//! 2. the `format` tag and `target.kind` are checked on that untyped value, so a file of
//!    another format version, or a board kind this version does not know, is reported as
//!    such and not as some confusing "missing field" further down;
//! 3. as the typed [`Manifest`] (again with line and column for type errors), and then
//!    every value is range-checked by [`Manifest::validate`].
//!
//! Unknown extra fields are accepted and ignored, so that newer writers can add optional
//! information without breaking older readers; they are not preserved on rewrite.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use b2b_calib::camera::CameraModel;
use b2b_protocol::messages::Intrinsics;
use serde::{Deserialize, Serialize};

use crate::error::{DatasetError, Location};
use crate::{FORMAT, MANIFEST_FILE};

/// The contents of `dataset.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`FORMAT`].
    pub format: String,
    pub name: String,
    /// Free text: who recorded the data, and how.
    #[serde(default)]
    pub source: String,
    /// Free text.
    #[serde(default)]
    pub license: String,
    pub target: Target,
    /// Further targets by id, for robots that do not all see `target`: a
    /// capture names its target in the `target` column of `captures.csv`
    /// (empty: `target`). A project extension; left out when empty.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub targets: BTreeMap<String, Target>,
    /// In the order that defines robot 1, robot 2, ...
    pub robots: Vec<RobotManifest>,
}

/// The calibration target. The JSON tag is `kind`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Target {
    /// Inner corners `[columns, rows]`, square side in metres.
    Checkerboard {
        inner_corners: [u32; 2],
        square_m: f64,
    },
    /// Squares `[columns, rows]`; `dictionary` is an OpenCV name such as `DICT_5X5_100`.
    Charuco {
        squares: [u32; 2],
        square_m: f64,
        marker_m: f64,
        dictionary: String,
    },
    /// Markers `[columns, rows]`, ids starting at `first_id`.
    ArucoGrid {
        markers: [u32; 2],
        marker_m: f64,
        separation_m: f64,
        dictionary: String,
        first_id: u32,
    },
    /// An ARToolKit-style multimarker file, relative to the dataset folder.
    Multimarker { config: PathBuf, dictionary: String },
}

/// The names `target.kind` may take.
pub const TARGET_KINDS: [&str; 4] = ["checkerboard", "charuco", "aruco_grid", "multimarker"];

/// One robot of the dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotManifest {
    /// Also the name of the robot's folder.
    pub id: String,
    /// Left out when intrinsics must be estimated from calibration images.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<Intrinsics>,
    /// Metres per depth-image unit; required when the robot has depth images.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_unit_m: Option<f64>,
}

impl RobotManifest {
    /// A robot with no camera intrinsics and no depth.
    pub fn new(id: impl Into<String>) -> Self {
        RobotManifest {
            id: id.into(),
            camera: None,
            depth_unit_m: None,
        }
    }
}

/// Distortion vector lengths OpenCV accepts (12 and 14 with their thin-prism and
/// tilt terms zero: [`MODELLED_DIST_TERMS`]).
pub const DIST_LENGTHS: [usize; 5] = [4, 5, 8, 12, 14];
/// The distortion terms the calibration models: `k1, k2, p1, p2, k3, k4, k5, k6`.
pub const MODELLED_DIST_TERMS: usize = 8;

/// Number of markers of an OpenCV predefined dictionary, `None` for an unknown name.
pub fn dictionary_size(name: &str) -> Option<u64> {
    match name {
        "DICT_ARUCO_ORIGINAL" => return Some(1024),
        "DICT_APRILTAG_16h5" => return Some(30),
        "DICT_APRILTAG_25h9" => return Some(35),
        "DICT_APRILTAG_36h10" => return Some(2320),
        "DICT_APRILTAG_36h11" => return Some(587),
        "DICT_ARUCO_MIP_36h12" => return Some(250),
        _ => {}
    }
    let rest = name.strip_prefix("DICT_")?;
    let (bits, size) = rest.split_once('_')?;
    let ok_bits = matches!(bits, "4X4" | "5X5" | "6X6" | "7X7");
    let size = match size {
        "50" => 50,
        "100" => 100,
        "250" => 250,
        "1000" => 1000,
        _ => return None,
    };
    ok_bits.then_some(size)
}

impl Manifest {
    /// A manifest of [`FORMAT`] with empty source and license.
    pub fn new(name: impl Into<String>, target: Target, robots: Vec<RobotManifest>) -> Self {
        Manifest {
            format: FORMAT.to_owned(),
            name: name.into(),
            source: String::new(),
            license: String::new(),
            target,
            targets: BTreeMap::new(),
            robots,
        }
    }

    /// Reads and validates `<dir>/dataset.json` (and nothing else).
    pub fn load(dir: &Path) -> Result<Manifest, DatasetError> {
        let file = dir.join(MANIFEST_FILE);
        let text = crate::read_text(&file, "a dataset folder must contain dataset.json")?;
        let manifest = Self::parse(&text, &file)?;
        manifest.validate(&file)?;
        Ok(manifest)
    }

    /// Parses manifest text; `file` is only used in errors. Does not range-check.
    pub fn parse(text: &str, file: &Path) -> Result<Manifest, DatasetError> {
        // A UTF-8 byte order mark (editors on Windows write one) is not JSON, but it
        // is not the user's data either: accepted here as in the CSV files.
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        let value: serde_json::Value =
            serde_json::from_str(text).map_err(|e| DatasetError::json(file, e))?;
        let Some(object) = value.as_object() else {
            return Err(DatasetError::InvalidManifest {
                at: Location::file(file),
                reason: "the manifest must be a JSON object".into(),
            });
        };
        match object.get("format") {
            Some(serde_json::Value::String(s)) if s == FORMAT => {}
            Some(serde_json::Value::String(s)) => {
                return Err(DatasetError::WrongFormat {
                    at: Location::field(file, "format"),
                    found: s.clone(),
                });
            }
            Some(other) => {
                return Err(DatasetError::WrongFormat {
                    at: Location::field(file, "format"),
                    found: other.to_string(),
                });
            }
            None => {
                return Err(DatasetError::WrongFormat {
                    at: Location::field(file, "format"),
                    found: "(missing)".into(),
                });
            }
        }
        if let Some(target) = object.get("target") {
            check_kind(target, "target", file)?;
        }
        if let Some(targets) = object.get("targets") {
            let Some(targets) = targets.as_object() else {
                return Err(DatasetError::InvalidTarget {
                    at: Location::field(file, "targets"),
                    reason: format!(
                        "targets must be an object of targets by id, found {}",
                        b2b_errors::excerpt(&targets.to_string())
                    ),
                });
            };
            for (id, target) in targets {
                check_kind(target, &format!("targets.{id}"), file)?;
            }
        }
        crate::parse_json(text, file)
    }

    /// Range-checks every value; `file` is only used in errors.
    pub fn validate(&self, file: &Path) -> Result<(), DatasetError> {
        if self.format != FORMAT {
            return Err(DatasetError::WrongFormat {
                at: Location::field(file, "format"),
                found: self.format.clone(),
            });
        }
        if self.name.trim().is_empty() {
            return Err(DatasetError::InvalidManifest {
                at: Location::field(file, "name"),
                reason: "the dataset name is empty".into(),
            });
        }
        self.target.validate(file)?;
        for (id, target) in &self.targets {
            if let Some(reason) = bad_robot_id(id) {
                return Err(DatasetError::InvalidTarget {
                    at: Location::field(file, format!("targets.{id}")),
                    reason: format!("target id `{id}` {reason}"),
                });
            }
            target.validate_at(file, &format!("targets.{id}"))?;
        }
        if self.robots.is_empty() {
            return Err(DatasetError::InvalidManifest {
                at: Location::field(file, "robots"),
                reason: "no robots are listed".into(),
            });
        }
        if self.robots.len() > crate::MAX_ROBOTS {
            return Err(DatasetError::InvalidManifest {
                at: Location::field(file, "robots"),
                reason: format!(
                    "{} robots are listed; at most {} (MAX_ROBOTS) are calibrated in one dataset: \
                     the joint fit of every base grows with the cube of their number. Calibrate \
                     them in groups of at most {} that share the reference robot",
                    self.robots.len(),
                    crate::MAX_ROBOTS,
                    crate::MAX_ROBOTS
                ),
            });
        }
        let mut seen: HashMap<&str, usize> = HashMap::new();
        for (i, robot) in self.robots.iter().enumerate() {
            let field = |name: &str| Location::field(file, format!("robots[{i}].{name}"));
            if let Some(reason) = bad_robot_id(&robot.id) {
                return Err(DatasetError::InvalidManifest {
                    at: field("id"),
                    reason: format!("robot id `{}` {reason}", robot.id),
                });
            }
            if let Some(first) = seen.insert(&robot.id, i) {
                return Err(DatasetError::DuplicateRobot {
                    at: field("id"),
                    id: robot.id.clone(),
                    first,
                });
            }
            if let Some(camera) = &robot.camera {
                validate_camera(camera, |name| field(&format!("camera.{name}")))?;
            }
            if let Some(unit) = robot.depth_unit_m
                && !(unit.is_finite() && unit > 0.0)
            {
                return Err(DatasetError::InvalidManifest {
                    at: field("depth_unit_m"),
                    reason: format!(
                        "depth_unit_m is {unit}; it must be a positive number of metres"
                    ),
                });
            }
        }
        Ok(())
    }

    /// The manifest entry of robot `id`.
    pub fn robot(&self, id: &str) -> Option<&RobotManifest> {
        self.robots.iter().find(|r| r.id == id)
    }
}

/// The untyped check of one target's `kind` (at JSON path `at`).
fn check_kind(target: &serde_json::Value, at: &str, file: &Path) -> Result<(), DatasetError> {
    if !target.is_object() {
        return Err(DatasetError::InvalidTarget {
            at: Location::field(file, at),
            reason: format!(
                "target must be an object with a `kind`, found {}",
                b2b_errors::excerpt(&target.to_string())
            ),
        });
    }
    match target.get("kind") {
        Some(serde_json::Value::String(kind)) if TARGET_KINDS.contains(&kind.as_str()) => {}
        Some(serde_json::Value::String(kind)) => {
            return Err(DatasetError::UnknownTargetKind {
                at: Location::field(file, format!("{at}.kind")),
                kind: kind.clone(),
            });
        }
        Some(other) => {
            return Err(DatasetError::UnknownTargetKind {
                at: Location::field(file, format!("{at}.kind")),
                kind: other.to_string(),
            });
        }
        None => {
            return Err(DatasetError::InvalidTarget {
                at: Location::field(file, format!("{at}.kind")),
                reason: "`kind` is missing".into(),
            });
        }
    }
    Ok(())
}

/// Why `id` cannot name a robot folder, if it cannot.
fn bad_robot_id(id: &str) -> Option<&'static str> {
    if id.is_empty() {
        Some("is empty")
    } else if id == "." || id == ".." {
        Some("is not a folder name")
    } else if id.chars().any(|c| c == '/' || c == '\\' || c.is_control()) {
        Some("contains a path separator or control character; it must be a plain folder name")
    } else if id.trim() != id {
        Some("starts or ends with white space")
    } else {
        None
    }
}

fn positive(value: f64, file: &Path, field: &str) -> Result<(), DatasetError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(DatasetError::InvalidTarget {
            at: Location::field(file, field),
            reason: format!("{field} is {value}; it must be a positive length in metres"),
        })
    }
}

fn at_least(
    counts: [u32; 2],
    min: u32,
    file: &Path,
    field: &str,
    what: &str,
) -> Result<(), DatasetError> {
    for (i, n) in counts.iter().enumerate() {
        if *n < min {
            return Err(DatasetError::InvalidTarget {
                at: Location::field(file, format!("{field}[{i}]")),
                reason: format!("{n} {what}; at least {min} are needed along each side"),
            });
        }
    }
    Ok(())
}

fn known_dictionary(name: &str, needed: u64, file: &Path, field: &str) -> Result<(), DatasetError> {
    let at = || Location::field(file, field);
    let Some(size) = dictionary_size(name) else {
        return Err(DatasetError::InvalidTarget {
            at: at(),
            reason: format!(
                "`{name}` is not an OpenCV predefined dictionary (e.g. DICT_5X5_100, DICT_APRILTAG_36h11)"
            ),
        });
    };
    if needed > size {
        return Err(DatasetError::InvalidTarget {
            at: at(),
            reason: format!(
                "the board needs marker ids up to {}, but {name} has {size}",
                needed - 1
            ),
        });
    }
    Ok(())
}

impl Target {
    /// Range-checks the board parameters; `file` is only used in errors.
    pub fn validate(&self, file: &Path) -> Result<(), DatasetError> {
        self.validate_at(file, "target")
    }

    /// [`Target::validate`] of the target at JSON path `at` (`target`, or
    /// `targets.<id>` for a further target).
    pub fn validate_at(&self, file: &Path, at: &str) -> Result<(), DatasetError> {
        let f = |name: &str| format!("{at}.{name}");
        match self {
            Target::Checkerboard {
                inner_corners,
                square_m,
            } => {
                at_least(
                    *inner_corners,
                    2,
                    file,
                    &f("inner_corners"),
                    "inner corners",
                )?;
                positive(*square_m, file, &f("square_m"))
            }
            Target::Charuco {
                squares,
                square_m,
                marker_m,
                dictionary,
            } => {
                at_least(*squares, 2, file, &f("squares"), "squares")?;
                positive(*square_m, file, &f("square_m"))?;
                positive(*marker_m, file, &f("marker_m"))?;
                if marker_m >= square_m {
                    return Err(DatasetError::InvalidTarget {
                        at: Location::field(file, f("marker_m")),
                        reason: format!(
                            "marker_m {marker_m} is not smaller than square_m {square_m}; a ChArUco marker sits inside its square"
                        ),
                    });
                }
                let markers = u64::from(squares[0]) * u64::from(squares[1]) / 2;
                known_dictionary(dictionary, markers, file, &f("dictionary"))
            }
            Target::ArucoGrid {
                markers,
                marker_m,
                separation_m,
                dictionary,
                first_id,
            } => {
                at_least(*markers, 1, file, &f("markers"), "markers")?;
                positive(*marker_m, file, &f("marker_m"))?;
                positive(*separation_m, file, &f("separation_m"))?;
                let last = u64::from(*first_id) + u64::from(markers[0]) * u64::from(markers[1]);
                known_dictionary(dictionary, last, file, &f("dictionary"))
            }
            Target::Multimarker { config, dictionary } => {
                let at = || Location::field(file, f("config"));
                if config.as_os_str().is_empty() {
                    return Err(DatasetError::InvalidTarget {
                        at: at(),
                        reason: "config is empty".into(),
                    });
                }
                if config.is_absolute() || config.has_root() {
                    return Err(DatasetError::InvalidTarget {
                        at: at(),
                        reason: format!(
                            "config {} must be relative to the dataset folder",
                            config.display()
                        ),
                    });
                }
                if crate::climbs_out(config, 0) {
                    return Err(DatasetError::InvalidTarget {
                        at: at(),
                        reason: format!(
                            "config {} climbs out of the dataset folder with `..`; a dataset reads only its own files",
                            config.display()
                        ),
                    });
                }
                if config.to_str().is_none() {
                    return Err(DatasetError::InvalidTarget {
                        at: at(),
                        reason: "config is not valid UTF-8".into(),
                    });
                }
                if dictionary.trim().is_empty() {
                    return Err(DatasetError::InvalidTarget {
                        at: Location::field(file, f("dictionary")),
                        reason: "dictionary is empty".into(),
                    });
                }
                Ok(())
            }
        }
    }

    /// The JSON `kind` of this target.
    pub fn kind(&self) -> &'static str {
        match self {
            Target::Checkerboard { .. } => "checkerboard",
            Target::Charuco { .. } => "charuco",
            Target::ArucoGrid { .. } => "aruco_grid",
            Target::Multimarker { .. } => "multimarker",
        }
    }
}

/// Range-checks a `camera` block of `dataset.json`; `at` names a field in errors.
pub fn validate_camera(
    camera: &Intrinsics,
    at: impl Fn(&str) -> Location,
) -> Result<(), DatasetError> {
    let bad = |name: &str, reason: String| {
        Err(DatasetError::InvalidCamera {
            at: at(name),
            reason,
        })
    };
    if camera.width == 0 {
        return bad("width", "width is 0".into());
    }
    if camera.height == 0 {
        return bad("height", "height is 0".into());
    }
    for (name, v) in [("fx", camera.fx), ("fy", camera.fy)] {
        if !(v.is_finite() && v > 0.0) {
            return bad(
                name,
                format!("{name} is {v}; a focal length must be positive"),
            );
        }
    }
    for (name, v) in [("cx", camera.cx), ("cy", camera.cy)] {
        if !v.is_finite() {
            return bad(name, format!("{name} is {v}"));
        }
    }
    if !DIST_LENGTHS.contains(&camera.dist.len()) {
        return bad(
            "dist",
            format!(
                "dist has {} entries; OpenCV takes 4, 5, 8, 12 or 14 (k1, k2, p1, p2[, k3[, k4, \
                 k5, k6[, s1..s4[, tx, ty]]]]; the thin-prism and tilt terms must be 0 here)",
                camera.dist.len()
            ),
        );
    }
    if let Some(i) = camera.dist.iter().position(|v| !v.is_finite()) {
        return bad(
            &format!("dist[{i}]"),
            format!("dist[{i}] is {}", camera.dist[i]),
        );
    }
    // 12 or 14 terms: OpenCV's thin-prism s1..s4 and tilt tx, ty follow k1..k6;
    // the calibration models k1..k6, so those must be zero (as OpenCV writes
    // them when they were not fitted).
    if let Some(i) = (MODELLED_DIST_TERMS..camera.dist.len()).find(|&i| camera.dist[i] != 0.0) {
        return bad(
            &format!("dist[{i}]"),
            format!(
                "dist[{i}] is {}: the thin-prism (s1..s4, dist[8..12]) and tilt (tx, ty, \
                 dist[12..14]) terms are not modelled; 12 or 14 entries are accepted when \
                 those are 0, else give 4, 5 or 8 (k1, k2, p1, p2[, k3[, k4, k5, k6]])",
                camera.dist[i]
            ),
        );
    }
    Ok(())
}

/// The distortion terms the calibration models (`k1, k2, p1, p2[, k3[, k4, k5,
/// k6]]`): at most the first [`MODELLED_DIST_TERMS`]; the thin-prism and tilt terms
/// of a 12- or 14-entry `dist` are zero ([`validate_camera`]).
pub fn modelled_dist(camera: &Intrinsics) -> &[f64] {
    &camera.dist[..camera.dist.len().min(MODELLED_DIST_TERMS)]
}

/// The math core's projection for intrinsics (their modelled terms): the one
/// place the wire and file form becomes a [`CameraModel`].
pub fn camera_model(camera: &Intrinsics) -> Result<CameraModel, b2b_calib::CalibError> {
    CameraModel::new(
        camera.width,
        camera.height,
        [camera.fx, camera.fy, camera.cx, camera.cy],
        modelled_dist(camera),
    )
}

/// The intrinsics of a projection with its first `dist_terms` distortion terms
/// (5: OpenCV's `k1, k2, p1, p2, k3`; at most 8), not marked estimated: the one
/// place a [`CameraModel`] becomes the wire and file form.
pub fn intrinsics_of(camera: &CameraModel, dist_terms: usize) -> Intrinsics {
    Intrinsics {
        width: camera.width,
        height: camera.height,
        fx: camera.fx,
        fy: camera.fy,
        cx: camera.cx,
        cy: camera.cy,
        dist: camera.dist[..dist_terms.min(camera.dist.len())].to_vec(),
        estimated: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file() -> PathBuf {
        PathBuf::from("/x/dataset.json")
    }

    /// The one conversion each way between the intrinsics and the math core's
    /// projection: a camera written as a `camera` block reads back as the same
    /// projection, and the block is one `dataset.json` accepts.
    #[test]
    fn a_camera_round_trips_through_its_block() {
        let camera = CameraModel::new(
            1280,
            720,
            [910.5, 909.25, 640.125, 359.75],
            &[0.1, -0.2, 1e-3, -2e-3, 0.05],
        )
        .unwrap();
        let block = intrinsics_of(&camera, 5);
        assert_eq!(block.dist.len(), 5);
        assert!(!block.estimated);
        let json = serde_json::to_string(&block).unwrap();
        assert!(!json.contains("estimated"), "{json}");
        let read: Intrinsics = serde_json::from_str(&json).unwrap();
        validate_camera(&read, |name| Location::field(file(), name)).unwrap();
        assert_eq!(camera_model(&read).unwrap(), camera);
        // 14 terms with the thin-prism and tilt ones zero: the modelled eight.
        let mut wide = read.clone();
        wide.dist.resize(14, 0.0);
        validate_camera(&wide, |name| Location::field(file(), name)).unwrap();
        assert_eq!(camera_model(&wide).unwrap(), camera);
        // A block without `dist` reads, and is refused by name.
        let bare: Intrinsics = serde_json::from_str(
            r#"{"width": 640, "height": 480, "fx": 600, "fy": 600, "cx": 320, "cy": 240}"#,
        )
        .unwrap();
        let e = validate_camera(&bare, |name| Location::field(file(), name)).unwrap_err();
        assert!(e.to_string().contains("dist has 0 entries"), "{e}");
    }

    #[test]
    fn dictionaries() {
        assert_eq!(dictionary_size("DICT_5X5_100"), Some(100));
        assert_eq!(dictionary_size("DICT_APRILTAG_36h11"), Some(587));
        assert_eq!(dictionary_size("DICT_5X5_101"), None);
        assert_eq!(dictionary_size("DICT_3X3_50"), None);
        assert_eq!(dictionary_size("5X5_100"), None);
    }

    #[test]
    fn charuco_needs_enough_markers_in_dictionary() {
        let t = Target::Charuco {
            squares: [20, 20],
            square_m: 0.02,
            marker_m: 0.015,
            dictionary: "DICT_4X4_50".into(),
        };
        let e = t.validate(&file()).unwrap_err();
        assert!(e.to_string().contains("DICT_4X4_50 has 50"), "{e}");
    }

    #[test]
    fn a_byte_order_mark_is_accepted_as_in_csv_files() {
        let text = r#"{"format": "b2b-dataset/1", "name": "n",
            "target": {"kind": "checkerboard", "inner_corners": [9, 6], "square_m": 0.025},
            "robots": [{"id": "robot1"}]}"#;
        let plain = Manifest::parse(text, &file()).unwrap();
        let with_bom = Manifest::parse(&format!("\u{feff}{text}"), &file()).unwrap();
        assert_eq!(plain, with_bom);
    }

    #[test]
    fn huge_counts_do_not_overflow() {
        let t = Target::ArucoGrid {
            markers: [u32::MAX, u32::MAX],
            marker_m: 0.02,
            separation_m: 0.01,
            dictionary: "DICT_4X4_1000".into(),
            first_id: u32::MAX,
        };
        assert!(matches!(
            t.validate(&file()),
            Err(DatasetError::InvalidTarget { .. })
        ));
    }

    #[test]
    fn robot_ids() {
        assert!(bad_robot_id("robot1").is_none());
        for id in ["", ".", "..", "a/b", "a\\b", " a", "a\n"] {
            assert!(bad_robot_id(id).is_some(), "{id:?}");
        }
    }

    #[test]
    fn target_kinds_match_serde_names() {
        let targets = [
            Target::Checkerboard {
                inner_corners: [9, 6],
                square_m: 0.02,
            },
            Target::Charuco {
                squares: [5, 7],
                square_m: 0.03,
                marker_m: 0.02,
                dictionary: "DICT_5X5_100".into(),
            },
            Target::ArucoGrid {
                markers: [4, 3],
                marker_m: 0.04,
                separation_m: 0.01,
                dictionary: "DICT_6X6_250".into(),
                first_id: 0,
            },
            Target::Multimarker {
                config: "mm.dat".into(),
                dictionary: "ARTOOLKIT".into(),
            },
        ];
        for t in targets {
            let v = serde_json::to_value(&t).unwrap();
            assert_eq!(v["kind"], t.kind());
            assert!(TARGET_KINDS.contains(&t.kind()));
        }
    }
}
