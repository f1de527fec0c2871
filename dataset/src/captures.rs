//! `captures.csv` and `touch_points.csv`: the rows, and the rules for them.
//!
//! The rules that concern only the values ([`CaptureChecker`], [`check_touch`]) are
//! shared by the reader and the writer, so the writer refuses to produce a file the
//! reader would reject. The rules that concern the file system (images and depth images
//! exist) are applied only when reading: a recorder writes the rows while, or before, it
//! copies the images.

use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};

use nalgebra::{Isometry3, Point3};

use crate::error::{DatasetError, Location};
use crate::manifest::{RobotManifest, Target};
use crate::pose::{self, PoseFields};
use crate::table::{self, Row, Table};
use std::collections::BTreeMap;

/// The columns of `captures.csv`, in the order they are written.
pub const CAPTURE_COLUMNS: [&str; 9] = ["image", "depth", "tx", "ty", "tz", "qx", "qy", "qz", "qw"];
/// The optional board-pose block of `captures.csv` (`T_camera_target`).
pub const CAMERA_POSE_COLUMNS: [&str; 7] = ["ctx", "cty", "ctz", "cqx", "cqy", "cqz", "cqw"];
/// The optional column of `captures.csv` naming the target a capture saw (an id
/// of the manifest's `targets`; empty: the manifest's `target`).
pub const TARGET_COLUMN: &str = "target";
/// The optional first column of `touch_points.csv`: which physical location a touch
/// touched.
pub const LOCATION_COLUMN: &str = "location";

/// The columns of `touch_points.csv`.
pub const TOUCH_COLUMNS: [&str; 6] = ["x1", "y1", "z1", "x2", "y2", "z2"];

const FLANGE_FIELDS: PoseFields<'static> = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"];
const CAMERA_FIELDS: PoseFields<'static> = CAMERA_POSE_COLUMNS;

/// Image file extensions the format allows (compared case-insensitively).
pub const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// One row of `captures.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct Capture {
    /// 1-based data row. On writing, rows are numbered by position instead.
    pub row: usize,
    /// Relative to the robot's folder, as written in the file.
    pub image: Option<PathBuf>,
    /// Relative to the robot's folder, as written in the file.
    pub depth: Option<PathBuf>,
    /// `T_base_flange`, columns `tx..qw`.
    pub base_from_flange: Isometry3<f64>,
    /// `T_camera_target`, columns `ctx..cqw`, when the row gives the board pose directly.
    pub camera_from_target: Option<Isometry3<f64>>,
    /// The id (in the manifest's `targets`) of the target the capture saw;
    /// `None` for the manifest's `target`. Column `target`.
    pub target: Option<String>,
}

/// One robot's captures.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotData {
    pub id: String,
    pub captures: Vec<Capture>,
}

/// One row of `touch_points.csv`: the same physical point touched by both robots' tips.
#[derive(Debug, Clone, PartialEq)]
pub struct TouchPair {
    /// 1-based data row.
    pub row: usize,
    /// The optional `location` column: touches with the same text touched the same
    /// physical location (repeated touches give ISO 9283 AP and RP in `verify`).
    pub location: Option<String>,
    pub tip1_in_base1: Point3<f64>,
    pub tip2_in_base2: Point3<f64>,
}

/// The row limit of `captures.csv`.
const CAPTURE_LIMIT: table::RowLimit = table::RowLimit {
    max: crate::MAX_CAPTURES_PER_ROBOT,
    what: "pose rows",
    constant: "MAX_CAPTURES_PER_ROBOT",
    advice: "a hand-eye needs tens of captures: keep a subset, or split the recording",
};

/// The row limit of a touch file.
const TOUCH_LIMIT: table::RowLimit = table::RowLimit {
    max: crate::MAX_TOUCHES,
    what: "touches",
    constant: "MAX_TOUCHES",
    advice: "a verification takes tens to hundreds of touches: keep a subset",
};

/// Reads one robot's `captures.csv` and checks it, including that its files exist.
pub(crate) fn read_captures(
    file: &Path,
    robot: &RobotManifest,
    targets: &BTreeMap<String, Target>,
    files: FilesAt<'_>,
) -> Result<Vec<Capture>, DatasetError> {
    let bytes = crate::read_bytes(file, "each robot folder must contain captures.csv")?;
    let table = table::parse_table_limited(&bytes, file, Some(CAPTURE_LIMIT))?;
    parse_captures(&table, robot, targets, Some(files))
}

/// Where a robot's files are: its folder, and the dataset folder with every
/// symlink resolved, which no file may leave.
#[derive(Debug, Clone, Copy)]
pub(crate) struct FilesAt<'a> {
    pub robot_dir: &'a Path,
    pub real_root: &'a Path,
}

/// Parses and checks the rows of a captures table. With `files`, also checks that
/// the named files exist inside the dataset folder.
pub(crate) fn parse_captures(
    table: &Table,
    robot: &RobotManifest,
    targets: &BTreeMap<String, Target>,
    files: Option<FilesAt<'_>>,
) -> Result<Vec<Capture>, DatasetError> {
    let file = table.file.as_path();
    let columns = table::map_columns_optional(
        table,
        &CAPTURE_COLUMNS,
        &CAMERA_POSE_COLUMNS,
        &[TARGET_COLUMN],
    )?;
    let mut checker = CaptureChecker::new(file, robot, targets);
    let mut captures = Vec::with_capacity(table.rows.len());
    for row in &table.rows {
        table::check_field_count(table, row)?;
        let c = &columns.required;
        let path = |i: usize| {
            let text = &row.fields[c[i]];
            (!text.is_empty()).then(|| PathBuf::from(text))
        };
        let image = path(0);
        let depth = path(1);
        let flange_idx = [c[2], c[3], c[4], c[5], c[6], c[7], c[8]];
        let base_from_flange = parse_pose(file, row, &flange_idx, &FLANGE_FIELDS)?;
        let camera_from_target = match &columns.block {
            None => None,
            Some(idx) => {
                let empty: Vec<bool> = idx.iter().map(|&i| row.fields[i].is_empty()).collect();
                if empty.iter().all(|e| *e) {
                    None
                } else if let Some(k) = empty.iter().position(|e| *e) {
                    return Err(DatasetError::PartialCameraPose {
                        at: row.at(file, CAMERA_POSE_COLUMNS[k]),
                    });
                } else {
                    let idx = [idx[0], idx[1], idx[2], idx[3], idx[4], idx[5], idx[6]];
                    Some(parse_pose(file, row, &idx, &CAMERA_FIELDS)?)
                }
            }
        };
        let target = columns.optional[0]
            .map(|i| row.fields[i].trim())
            .filter(|t| !t.is_empty())
            .map(str::to_owned);
        let capture = Capture {
            row: row.row,
            image,
            depth,
            base_from_flange,
            camera_from_target,
            target,
        };
        checker.check(row.row, Some(row.line), &capture)?;
        if let Some(files) = files {
            check_files(file, files, row, &capture)?;
        }
        captures.push(capture);
    }
    Ok(captures)
}

fn parse_pose(
    file: &Path,
    row: &Row,
    idx: &[usize; 7],
    fields: &PoseFields<'_>,
) -> Result<Isometry3<f64>, DatasetError> {
    let mut v = [0.0; 7];
    for k in 0..7 {
        v[k] = table::number(file, row, idx[k], fields[k])?;
    }
    pose::isometry_from_numbers(v, fields, |f| row.at(file, &f))
}

fn check_files(
    file: &Path,
    files: FilesAt<'_>,
    row: &Row,
    capture: &Capture,
) -> Result<(), DatasetError> {
    if let Some(image) = &capture.image {
        let full = files.robot_dir.join(image);
        not_special(&full, || row.at(file, "image"))?;
        if !full.is_file() {
            return Err(DatasetError::MissingImage {
                at: row.at(file, "image"),
                missing: full,
            });
        }
        crate::inside(files.real_root, &full, || row.at(file, "image"))?;
    }
    if let Some(depth) = &capture.depth {
        let full = files.robot_dir.join(depth);
        not_special(&full, || row.at(file, "depth"))?;
        if !full.is_file() {
            return Err(DatasetError::MissingDepth {
                at: row.at(file, "depth"),
                missing: full,
            });
        }
        crate::inside(files.real_root, &full, || row.at(file, "depth"))?;
    }
    Ok(())
}

/// Refuses an image path that exists but is a named pipe, a device, a directory
/// or a socket, from its metadata (never opened).
fn not_special(full: &Path, at: impl FnOnce() -> Location) -> Result<(), DatasetError> {
    match std::fs::metadata(full) {
        Ok(meta) => match crate::not_a_regular_file(&meta) {
            Some(kind) => Err(DatasetError::BadPath {
                at: at(),
                problem: format!("{} is {kind}, not a regular file", full.display()),
            }),
            None => Ok(()),
        },
        Err(_) => Ok(()),
    }
}

/// The value rules of `captures.csv`, applied row by row.
#[derive(Debug)]
pub(crate) struct CaptureChecker<'a> {
    file: &'a Path,
    robot: &'a RobotManifest,
    /// The manifest's further targets, which a capture's `target` must name.
    targets: &'a BTreeMap<String, Target>,
    /// Normalised image path to the row that first used it.
    seen: HashMap<PathBuf, usize>,
}

impl<'a> CaptureChecker<'a> {
    pub fn new(
        file: &'a Path,
        robot: &'a RobotManifest,
        targets: &'a BTreeMap<String, Target>,
    ) -> Self {
        CaptureChecker {
            file,
            robot,
            targets,
            seen: HashMap::new(),
        }
    }

    /// Checks one capture; `row` and `line` place it in the file.
    pub fn check(
        &mut self,
        row: usize,
        line: Option<u64>,
        c: &Capture,
    ) -> Result<(), DatasetError> {
        let at = |field: &str| Location::cell(self.file, row, line, field);
        pose::check_isometry(&c.base_from_flange, &FLANGE_FIELDS, |f| at(&f))?;
        if let Some(cam) = &c.camera_from_target {
            pose::check_isometry(cam, &CAMERA_FIELDS, |f| at(&f))?;
        }
        if let Some(target) = &c.target
            && !self.targets.contains_key(target)
        {
            let known = if self.targets.is_empty() {
                "it lists none; an empty cell means `target`".to_owned()
            } else {
                self.targets.keys().cloned().collect::<Vec<_>>().join(", ")
            };
            return Err(DatasetError::UnknownTarget {
                at: at(TARGET_COLUMN),
                reason: format!("target `{target}` is not in dataset.json's `targets` ({known})"),
            });
        }
        if let Some(image) = &c.image {
            check_path(image, &IMAGE_EXTENSIONS, || at("image"))?;
        }
        if let Some(depth) = &c.depth {
            check_path(depth, &["png"], || at("depth"))?;
            if c.image.is_none() {
                return Err(DatasetError::BadPath {
                    at: at("depth"),
                    problem: format!(
                        "`{}` is given without an image; a depth image is aligned to its colour image",
                        depth.display()
                    ),
                });
            }
            if self.robot.depth_unit_m.is_none() {
                return Err(DatasetError::DepthWithoutUnit {
                    at: at("depth"),
                    robot: self.robot.id.clone(),
                });
            }
        }
        if c.image.is_none() && c.camera_from_target.is_none() {
            let mut at = Location::file(self.file);
            at.row = Some(row);
            at.line = line;
            at.field = Some("image".into());
            return Err(DatasetError::NoObservation { at });
        }
        if let Some(image) = &c.image
            && let Some(first_row) = self.seen.insert(normalise(image), row)
        {
            return Err(DatasetError::DuplicateImage {
                at: at("image"),
                image: image.clone(),
                first_row,
            });
        }
        Ok(())
    }
}

/// `a/./b` and `./a/b` are the same file as `a/b`.
fn normalise(path: &Path) -> PathBuf {
    path.components()
        .filter(|c| !matches!(c, Component::CurDir))
        .collect()
}

fn check_path(
    path: &Path,
    extensions: &[&str],
    at: impl Fn() -> Location,
) -> Result<(), DatasetError> {
    let bad = |reason: &str| {
        Err(DatasetError::BadPath {
            at: at(),
            problem: format!("path `{}` {reason}", path.display()),
        })
    };
    let Some(text) = path.to_str() else {
        return bad("is not valid UTF-8");
    };
    if text.is_empty() {
        return bad("is empty");
    }
    if text.trim() != text {
        return bad("starts or ends with white space");
    }
    if path.is_absolute() || path.has_root() {
        return bad("is absolute; paths are relative to the robot's folder");
    }
    // The robot's folder is one level below the dataset folder.
    if crate::climbs_out(path, 1) {
        return bad(
            "climbs out of the dataset folder with `..`; a dataset reads only its own files",
        );
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    if !ext.is_some_and(|e| extensions.contains(&e.as_str())) {
        let list: Vec<String> = extensions.iter().map(|e| format!(".{e}")).collect();
        return bad(&format!("must end in {}", list.join(" or ")));
    }
    Ok(())
}

/// Reads `touch_points.csv`.
pub fn read_touch_points(file: &Path) -> Result<Vec<TouchPair>, DatasetError> {
    let bytes = crate::read_bytes(
        file,
        "expected a touch-points CSV with header x1,y1,z1,x2,y2,z2",
    )?;
    let table = table::parse_table_limited(&bytes, file, Some(TOUCH_LIMIT))?;
    let columns = table::map_columns(&table, &TOUCH_COLUMNS, &[LOCATION_COLUMN])?;
    let mut pairs = Vec::with_capacity(table.rows.len());
    for row in &table.rows {
        table::check_field_count(&table, row)?;
        let mut v = [0.0; 6];
        for k in 0..6 {
            v[k] = table::number(file, row, columns.required[k], TOUCH_COLUMNS[k])?;
        }
        let location = match &columns.block {
            Some(idx) => {
                let text = row.fields[idx[0]].trim();
                if text.is_empty() {
                    return Err(DatasetError::EmptyLocation {
                        at: row.at(file, LOCATION_COLUMN),
                    });
                }
                Some(text.to_owned())
            }
            None => None,
        };
        let pair = TouchPair {
            row: row.row,
            location,
            tip1_in_base1: Point3::new(v[0], v[1], v[2]),
            tip2_in_base2: Point3::new(v[3], v[4], v[5]),
        };
        check_touch(file, row.row, Some(row.line), &pair)?;
        pairs.push(pair);
    }
    Ok(pairs)
}

/// The value rules of `touch_points.csv`.
pub(crate) fn check_touch(
    file: &Path,
    row: usize,
    line: Option<u64>,
    pair: &TouchPair,
) -> Result<(), DatasetError> {
    let values = touch_numbers(pair);
    for (value, name) in values.iter().zip(TOUCH_COLUMNS) {
        pose::check_coordinate(*value, || Location::cell(file, row, line, name))?;
    }
    Ok(())
}

pub(crate) fn touch_numbers(pair: &TouchPair) -> [f64; 6] {
    let (a, b) = (pair.tip1_in_base1, pair.tip2_in_base2);
    [a.x, a.y, a.z, b.x, b.y, b.z]
}

/// The cells of a capture, in the order of the written header.
pub(crate) fn capture_cells(
    file: &Path,
    row: usize,
    c: &Capture,
    with_camera_pose: bool,
    with_target: bool,
) -> Result<Vec<String>, DatasetError> {
    let path_cell = |p: &Option<PathBuf>, field: &str| -> Result<String, DatasetError> {
        match p {
            None => Ok(String::new()),
            Some(p) => p
                .to_str()
                .map(str::to_owned)
                .ok_or_else(|| DatasetError::BadPath {
                    at: Location::cell(file, row, None, field),
                    problem: format!("path `{}` is not valid UTF-8", p.display()),
                }),
        }
    };
    let mut cells = vec![path_cell(&c.image, "image")?, path_cell(&c.depth, "depth")?];
    cells.extend(pose::numbers_from_isometry(&c.base_from_flange).map(pose::format_number));
    if with_camera_pose {
        match &c.camera_from_target {
            Some(cam) => cells.extend(pose::numbers_from_isometry(cam).map(pose::format_number)),
            None => cells.extend(std::iter::repeat_n(String::new(), 7)),
        }
    }
    if with_target {
        cells.push(c.target.clone().unwrap_or_default());
    }
    Ok(cells)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn robot() -> RobotManifest {
        RobotManifest::new("robot1")
    }

    fn parse(text: &str) -> Result<Vec<Capture>, DatasetError> {
        let t = table::parse_table(text.as_bytes(), Path::new("/d/robot1/captures.csv")).unwrap();
        parse_captures(&t, &robot(), &BTreeMap::new(), None)
    }

    #[test]
    fn pose_only_rows_and_reordered_columns() {
        let c = parse(
            "qw,qx,qy,qz,tx,ty,tz,image,depth,ctx,cty,ctz,cqx,cqy,cqz,cqw\n\
             1,0,0,0,0.1,0.2,0.3,,,0,0,0.5,0,0,0,1\n",
        )
        .unwrap();
        assert_eq!(c[0].base_from_flange.translation.vector.y, 0.2);
        assert_eq!(c[0].camera_from_target.unwrap().translation.vector.z, 0.5);
        assert!(c[0].image.is_none());
    }

    #[test]
    fn duplicate_detection_ignores_dot_components() {
        let e = parse(
            "image,depth,tx,ty,tz,qx,qy,qz,qw\na/1.png,,0,0,0,0,0,0,1\n./a/1.png,,0,0,0,0,0,0,1\n",
        )
        .unwrap_err();
        assert!(
            matches!(e, DatasetError::DuplicateImage { first_row: 1, .. }),
            "{e}"
        );
    }

    #[test]
    fn paths_must_be_relative_images() {
        for (p, needle) in [("/abs/1.png", "absolute"), ("images/1.bmp", ".png or .jpg")] {
            let e = parse(&format!(
                "image,depth,tx,ty,tz,qx,qy,qz,qw\n{p},,0,0,0,0,0,0,1\n"
            ))
            .unwrap_err();
            assert!(matches!(e, DatasetError::BadPath { .. }), "{e}");
            assert!(e.to_string().contains(needle), "{e}");
        }
        assert!(parse("image,depth,tx,ty,tz,qx,qy,qz,qw\nimages/A.JPG,,0,0,0,0,0,0,1\n").is_ok());
    }

    #[test]
    fn depth_without_image_is_rejected() {
        let mut r = robot();
        r.depth_unit_m = Some(0.001);
        let t = table::parse_table(
            b"image,depth,tx,ty,tz,qx,qy,qz,qw,ctx,cty,ctz,cqx,cqy,cqz,cqw\n,d/1.png,0,0,0,0,0,0,1,0,0,1,0,0,0,1\n",
            Path::new("/c.csv"),
        )
        .unwrap();
        let e = parse_captures(&t, &r, &BTreeMap::new(), None).unwrap_err();
        assert!(e.to_string().contains("without an image"), "{e}");
    }
}
