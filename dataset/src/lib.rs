//! Reads, validates and writes the `b2b-dataset/1` interchange format
//! (`shared/dataset-format.md`).
//!
//! This format is the contract with the outside world: real recordings, public datasets
//! and independently generated test data all arrive in it, and every tool of the project
//! reads it through this crate. The design follows from that:
//!
//! * **Validate everything at the door.** [`Dataset::load`] checks every file, row and
//!   value it reads, so the solvers downstream can trust their input and never have to
//!   guess whether a strange result comes from the data. Millimetres where metres are
//!   expected, a quaternion in `w, x, y, z` order, a renamed image: all of these produce
//!   plausible-looking but wrong calibrations if they get through, so they are errors here.
//! * **Errors say where.** Every problem is a variant of [`DatasetError`] whose message
//!   names the full path of the file, the 1-based data row and line, and the column or
//!   field. Loading stops at the first problem. No input makes the loader panic.
//! * **The answer is kept apart.** [`Dataset`] holds what a calibration may see. The
//!   ground truth and other tools' results are read only by [`load_ground_truth`] and
//!   [`load_reference`], which a calibration has no reason to call.
//! * **Bit-for-bit round trips.** Numbers are written in Rust's shortest round-trip form
//!   and read back exactly; unit quaternions are kept as written (see [`pose`]'s policy).
//!   A dataset written by [`Dataset::write`] and loaded again is equal to the original,
//!   which makes recorded data, generated data and their reproductions comparable.
//! * **The writer applies the reader's rules** (except that files exist, since images
//!   are copied by the caller), so the project cannot produce a dataset it would reject.
//!
//! Poses are `nalgebra::Isometry3<f64>` named `a_from_b` for the format's `T_a_b`.

mod captures;
mod error;
pub mod import;
mod manifest;
pub mod pose;
mod table;
mod truth;

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

pub use b2b_protocol::messages::Intrinsics;
pub use captures::{
    CAMERA_POSE_COLUMNS, CAPTURE_COLUMNS, Capture, IMAGE_EXTENSIONS, LOCATION_COLUMN, RobotData,
    TOUCH_COLUMNS, TouchPair, read_touch_points,
};
pub use error::{DatasetError, Location};
pub use manifest::{
    DIST_LENGTHS, MODELLED_DIST_TERMS, Manifest, RobotManifest, TARGET_KINDS, Target, camera_model,
    dictionary_size, intrinsics_of, modelled_dist, validate_camera,
};
pub use truth::{
    GroundTruth, Reference, load_ground_truth, load_reference, write_ground_truth, write_reference,
};

/// The `format` value of `dataset.json`.
pub const FORMAT: &str = "b2b-dataset/1";
/// The manifest's file name.
pub const MANIFEST_FILE: &str = "dataset.json";
/// Each robot folder's capture list.
pub const CAPTURES_FILE: &str = "captures.csv";
/// The optional touch-point list.
pub const TOUCH_POINTS_FILE: &str = "touch_points.csv";
/// The optional ground truth.
pub const GROUND_TRUTH_FILE: &str = "ground_truth.json";
/// The optional published result of another tool.
pub const REFERENCE_FILE: &str = "reference.json";
/// Largest coordinate, in metres, that is accepted as metres. A robot cell is a few
/// metres across; a larger number is almost certainly millimetres.
pub const MAX_COORDINATE_M: f64 = 10.0;

// Every input is bounded, so that no file makes a command run out of memory or
// time: a file over a limit is refused at the door, with the limit in the
// message, before the work it would cause. The limits are far above any real
// calibration (20 to 200 captures of 2 to 4 robots, 10 to 100 touches).

/// Most rows of one robot's `captures.csv` (pose rows per robot). A hand-eye
/// needs 10 to 50 captures. The closed-form hand-eyes and the motion checks
/// compare every pair of captures, so their work grows with the square of
/// this (1,000 rows of two robots: 32 s and 220 MB in a debug build).
pub const MAX_CAPTURES_PER_ROBOT: usize = 1_000;
/// Most captures of all robots of one dataset (two robots at
/// [`MAX_CAPTURES_PER_ROBOT`] each). The joint fit of every base adds each
/// capture's small block to its normal equations and takes each
/// leave-one-out step by a low-rank update, so its work grows with the
/// captures, not with the robots (`cargo bench -p b2b-calib --bench refine
/// robots`); what the limit bounds is the detection of every image and the
/// per-robot pairwise checks.
pub const MAX_CAPTURES_TOTAL: usize = 2_000;
/// Most robots in one `dataset.json`: a platform has 2 to 4 arms. The joint
/// fit grows linearly with the robots at a fixed number of captures each;
/// the normal matrix itself (21 unknowns per robot) stays small.
pub const MAX_ROBOTS: usize = 12;
/// Most rows of one touch file (`touch_points.csv` and the pair files).
pub const MAX_TOUCHES: usize = 10_000;
/// Most samples `coordinator import` takes from another tool's file: they
/// become one robot's captures, so [`MAX_CAPTURES_PER_ROBOT`].
pub const MAX_IMPORT_SAMPLES: usize = MAX_CAPTURES_PER_ROBOT;
/// Largest text file (CSV, JSON) that is read at all (256 MiB): a file within
/// the row limits is a few megabytes.
pub const MAX_TEXT_FILE_BYTES: u64 = 256 << 20;
/// Largest YAML samples file `coordinator import` reads (32 MiB; a sample is a
/// few hundred bytes, and the YAML parser holds the whole document).
pub const MAX_SAMPLES_FILE_BYTES: u64 = 32 << 20;

/// A loaded dataset: everything a calibration may see.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// The dataset folder (absolute after [`Dataset::load`]).
    pub root: PathBuf,
    pub manifest: Manifest,
    /// One entry per robot of the manifest, in the manifest's order.
    pub robots: Vec<RobotData>,
    /// `touch_points.csv`, when the dataset has one: the touches of the first two robots.
    pub touch_points: Option<Vec<TouchPair>>,
    /// The `touch_points_<a>_<b>.csv` files, keyed by the robot ids `(a, b)`: in each
    /// [`TouchPair`], `tip1_in_base1` is robot `a`'s tip in `a`'s base and
    /// `tip2_in_base2` robot `b`'s in `b`'s. See [`Dataset::touches_between`].
    pub pair_touch_points: BTreeMap<(String, String), Vec<TouchPair>>,
}

/// The file of the touches of robots `a` and `b` (in that order) other than
/// `touch_points.csv`: `touch_points_<a>_<b>.csv`.
pub fn pair_touch_file_name(a: &str, b: &str) -> String {
    format!("touch_points_{a}_{b}.csv")
}

/// Every ordered pair of distinct robot ids with the file name of its touches. Robot ids
/// may contain `_`, so one name can stand for two pairs (`a` + `b_c` and `a_b` + `c`):
/// such a name is found twice here.
fn pair_files(ids: &[&str]) -> Vec<((String, String), String)> {
    let mut out = vec![];
    for a in ids {
        for b in ids {
            if a != b {
                out.push((
                    ((*a).to_owned(), (*b).to_owned()),
                    pair_touch_file_name(a, b),
                ));
            }
        }
    }
    out
}

/// The error for a pair file whose name stands for more than one pair of robots.
fn ambiguous_pair_file(
    root: &Path,
    name: &str,
    pairs: &[((String, String), String)],
) -> Option<DatasetError> {
    let meanings: Vec<String> = pairs
        .iter()
        .filter(|(_, n)| n == name)
        .map(|((a, b), _)| format!("`{a}` with `{b}`"))
        .collect();
    (meanings.len() > 1).then(|| DatasetError::AmbiguousTouchFile {
        file: root.join(name),
        reason: format!(
            "the name stands for the touches of {}; rename a robot so that              touch_points_<a>_<b>.csv names one pair",
            meanings.join(" and of ")
        ),
    })
}

impl Dataset {
    /// Reads `dataset.json`, every robot's `captures.csv`, `touch_points.csv` and the
    /// `touch_points_<a>_<b>.csv` of every ordered pair of manifest robots from `dir`, and
    /// validates all of it, including that every named image exists. Never reads
    /// `ground_truth.json` or `reference.json`.
    pub fn load(dir: &Path) -> Result<Dataset, DatasetError> {
        Self::load_with(dir, true)
    }

    /// [`Dataset::load`] without the touch files (neither read nor checked:
    /// [`Dataset::touch_points`] and [`Dataset::pair_touch_points`] are empty),
    /// for a command that does not use them, such as one robot's hand-eye.
    pub fn load_without_touches(dir: &Path) -> Result<Dataset, DatasetError> {
        Self::load_with(dir, false)
    }

    fn load_with(dir: &Path, touches: bool) -> Result<Dataset, DatasetError> {
        let root = absolute(dir);
        let manifest = Manifest::load(&root)?;
        let manifest_file = root.join(MANIFEST_FILE);
        // Every file read below must resolve inside this folder: a dataset is
        // handed around, and a symlink must not make it read the machine's files.
        let real_root = root
            .canonicalize()
            .map_err(|e| DatasetError::io(&root, e))?;
        let all_targets = std::iter::once(("target".to_owned(), &manifest.target)).chain(
            manifest
                .targets
                .iter()
                .map(|(id, t)| (format!("targets.{id}"), t)),
        );
        for (at, target) in all_targets {
            let Target::Multimarker { config, .. } = target else {
                continue;
            };
            let full = root.join(config);
            if !full.is_file() {
                return Err(DatasetError::InvalidTarget {
                    at: Location::field(&manifest_file, format!("{at}.config")),
                    reason: format!("multimarker file {} does not exist", full.display()),
                });
            }
            inside(&real_root, &full, || {
                Location::field(&manifest_file, format!("{at}.config"))
            })?;
        }
        let mut robots = Vec::with_capacity(manifest.robots.len());
        let mut total_captures = 0;
        for (i, robot) in manifest.robots.iter().enumerate() {
            let folder = root.join(&robot.id);
            if !folder.is_dir() {
                return Err(DatasetError::MissingRobotFolder {
                    at: Location::field(&manifest_file, format!("robots[{i}].id")),
                    folder,
                });
            }
            let robot_at = || Location::field(&manifest_file, format!("robots[{i}].id"));
            inside(&real_root, &folder, robot_at)?;
            let captures_file = folder.join(CAPTURES_FILE);
            if captures_file.exists() {
                inside(&real_root, &captures_file, || {
                    Location::file(&captures_file)
                })?;
            }
            let captures = captures::read_captures(
                &captures_file,
                robot,
                &manifest.targets,
                captures::FilesAt {
                    robot_dir: &folder,
                    real_root: &real_root,
                },
            )?;
            total_captures += captures.len();
            let limit = MAX_CAPTURES_TOTAL;
            if total_captures > limit {
                return Err(DatasetError::TooManyRows {
                    file: captures_file,
                    what: "captures in this and the earlier robots' captures.csv",
                    limit,
                    constant: "MAX_CAPTURES_TOTAL",
                    advice: "every image is detected and every robot's captures compared: \
                             keep a subset of each robot's captures",
                });
            }
            robots.push(RobotData {
                id: robot.id.clone(),
                captures,
            });
        }
        if !touches {
            return Ok(Dataset {
                root,
                manifest,
                robots,
                touch_points: None,
                pair_touch_points: BTreeMap::new(),
            });
        }
        let touch_file = root.join(TOUCH_POINTS_FILE);
        let touch_points = if touch_file.exists() {
            if manifest.robots.len() < 2 {
                return Err(DatasetError::TouchPointsNeedTwoRobots {
                    file: touch_file,
                    robots: manifest.robots.len(),
                });
            }
            inside(&real_root, &touch_file, || Location::file(&touch_file))?;
            Some(captures::read_touch_points(&touch_file)?)
        } else {
            None
        };
        let ids: Vec<&str> = manifest.robots.iter().map(|r| r.id.as_str()).collect();
        let pairs = pair_files(&ids);
        let mut pair_touch_points = BTreeMap::new();
        for (pair, name) in &pairs {
            let file = root.join(name);
            if !file.exists() {
                continue;
            }
            if let Some(e) = ambiguous_pair_file(&root, name, &pairs) {
                return Err(e);
            }
            inside(&real_root, &file, || Location::file(&file))?;
            pair_touch_points.insert(pair.clone(), captures::read_touch_points(&file)?);
        }
        Ok(Dataset {
            root,
            manifest,
            robots,
            touch_points,
            pair_touch_points,
        })
    }

    /// Writes `dataset.json`, every robot's `captures.csv`, `touch_points.csv` and the
    /// `touch_points_<a>_<b>.csv` files into `dir` (creating folders as needed;
    /// `self.root` is not used). Everything is checked first with the reader's rules, so
    /// an invalid dataset writes nothing. Capture rows are numbered by position. A
    /// touch file of this dataset's robots left in `dir` that this dataset does not have
    /// is removed, so that the folder describes exactly this dataset. Images are not
    /// written: the caller copies them to the paths the captures name.
    pub fn write(&self, dir: &Path) -> Result<(), DatasetError> {
        let root = absolute(dir);
        let manifest_file = root.join(MANIFEST_FILE);
        self.manifest.validate(&manifest_file)?;
        let ids: Vec<&str> = self.robots.iter().map(|r| r.id.as_str()).collect();
        let expected: Vec<&str> = self.manifest.robots.iter().map(|r| r.id.as_str()).collect();
        if ids != expected {
            return Err(DatasetError::RobotMismatch {
                at: Location::field(&manifest_file, "robots"),
                reason: format!(
                    "the manifest lists robots {expected:?} but the data has {ids:?}, in that order"
                ),
            });
        }
        let mut files: Vec<(PathBuf, Vec<u8>)> = vec![];
        for (robot, data) in self.manifest.robots.iter().zip(&self.robots) {
            let file = root.join(&robot.id).join(CAPTURES_FILE);
            let mut checker = captures::CaptureChecker::new(&file, robot, &self.manifest.targets);
            let with_camera = data.captures.iter().any(|c| c.camera_from_target.is_some());
            let with_target = data.captures.iter().any(|c| c.target.is_some());
            let mut header: Vec<&str> = CAPTURE_COLUMNS.to_vec();
            if with_camera {
                header.extend(CAMERA_POSE_COLUMNS);
            }
            if with_target {
                header.push(captures::TARGET_COLUMN);
            }
            let mut rows = Vec::with_capacity(data.captures.len());
            for (i, c) in data.captures.iter().enumerate() {
                checker.check(i + 1, None, c)?;
                rows.push(captures::capture_cells(
                    &file,
                    i + 1,
                    c,
                    with_camera,
                    with_target,
                )?);
            }
            let bytes = table::render(&file, &header, &rows)?;
            files.push((file, bytes));
        }
        let touch_file = root.join(TOUCH_POINTS_FILE);
        if let Some(pairs) = &self.touch_points {
            if self.manifest.robots.len() < 2 {
                return Err(DatasetError::TouchPointsNeedTwoRobots {
                    file: touch_file,
                    robots: self.manifest.robots.len(),
                });
            }
            files.push((touch_file.clone(), render_touches(&touch_file, pairs)?));
        }
        let all_pairs = pair_files(&expected);
        let mut written_pairs = vec![];
        for ((a, b), pairs) in &self.pair_touch_points {
            let name = pair_touch_file_name(a, b);
            let file = root.join(&name);
            for id in [a, b] {
                if self.manifest.robot(id).is_none() {
                    return Err(DatasetError::UnknownRobot {
                        at: Location::file(&file),
                        robot: id.clone(),
                    });
                }
            }
            if a == b {
                return Err(DatasetError::RobotMismatch {
                    at: Location::file(&file),
                    reason: format!("touches pair two robots, not `{a}` with itself"),
                });
            }
            if let Some(e) = ambiguous_pair_file(&root, &name, &all_pairs) {
                return Err(e);
            }
            files.push((file, render_touches(&root.join(&name), pairs)?));
            written_pairs.push(name);
        }
        let mut json = serde_json::to_string_pretty(&self.manifest)
            .map_err(|e| DatasetError::json(&manifest_file, e))?;
        json.push('\n');
        files.push((manifest_file, json.into_bytes()));

        for (file, bytes) in &files {
            if let Some(parent) = file.parent() {
                fs::create_dir_all(parent).map_err(|e| DatasetError::io(parent, e))?;
            }
            write_atomic(file, bytes)?;
        }
        let mut stale: Vec<PathBuf> = all_pairs
            .into_iter()
            .filter(|(_, name)| !written_pairs.contains(name))
            .map(|(_, name)| root.join(name))
            .collect();
        if self.touch_points.is_none() {
            stale.push(touch_file);
        }
        for file in stale {
            if file.is_file() {
                fs::remove_file(&file).map_err(|e| DatasetError::io(&file, e))?;
            }
        }
        Ok(())
    }

    /// The touches of robots `a` and `b` (tips of `a` in `a`'s base first): their
    /// `touch_points_<a>_<b>.csv`, or `touch_points.csv` when `a` and `b` are the first
    /// two robots of the manifest, in that order. `None` when the dataset has neither.
    pub fn touches_between(&self, a: &str, b: &str) -> Option<&[TouchPair]> {
        let pair = self
            .pair_touch_points
            .iter()
            .find(|((pa, pb), _)| pa == a && pb == b)
            .map(|(_, pairs)| pairs.as_slice());
        match self.manifest.robots.as_slice() {
            [r1, r2, ..] if pair.is_none() && r1.id == a && r2.id == b => {
                self.touch_points.as_deref()
            }
            _ => pair,
        }
    }

    /// The data of robot `id`.
    pub fn robot(&self, id: &str) -> Option<&RobotData> {
        self.robots.iter().find(|r| r.id == id)
    }

    /// The manifest entry (camera, depth unit) of robot `id`.
    pub fn robot_manifest(&self, id: &str) -> Option<&RobotManifest> {
        self.manifest.robot(id)
    }

    /// The folder of robot `id`, absolute.
    pub fn robot_dir(&self, id: &str) -> PathBuf {
        absolute(&self.root.join(id))
    }

    /// The image of a capture of robot `robot`, absolute; `None` for a pose-only row.
    pub fn image_path(&self, robot: &str, capture: &Capture) -> Option<PathBuf> {
        capture
            .image
            .as_ref()
            .map(|p| self.robot_dir(robot).join(p))
    }

    /// The depth image of a capture of robot `robot`, absolute, if it has one.
    pub fn depth_path(&self, robot: &str, capture: &Capture) -> Option<PathBuf> {
        capture
            .depth
            .as_ref()
            .map(|p| self.robot_dir(robot).join(p))
    }

    /// The multimarker file of a multimarker target, absolute.
    /// Every target of the dataset: the manifest's `target` first (id `None`),
    /// then its `targets` by id. A capture's place in this list is its target's
    /// index in a joint problem ([`Dataset::target_index`]).
    pub fn all_targets(&self) -> Vec<(Option<&str>, &Target)> {
        std::iter::once((None, &self.manifest.target))
            .chain(
                self.manifest
                    .targets
                    .iter()
                    .map(|(id, t)| (Some(id.as_str()), t)),
            )
            .collect()
    }

    /// The index in [`Dataset::all_targets`] of the target a capture saw (a
    /// loaded dataset's captures name only listed targets; an unlisted one
    /// counts as the manifest's `target`).
    pub fn target_index(&self, capture: &Capture) -> usize {
        capture
            .target
            .as_deref()
            .and_then(|id| self.manifest.targets.keys().position(|k| k == id))
            .map_or(0, |i| i + 1)
    }

    pub fn multimarker_config_path(&self) -> Option<PathBuf> {
        match &self.manifest.target {
            Target::Multimarker { config, .. } => Some(absolute(&self.root.join(config))),
            _ => None,
        }
    }
}

/// `touch_points.csv` or a pair file, checked with the reader's rules.
fn render_touches(file: &Path, pairs: &[TouchPair]) -> Result<Vec<u8>, DatasetError> {
    let with_location = pairs.iter().any(|p| p.location.is_some());
    let mut rows = Vec::with_capacity(pairs.len());
    for (i, pair) in pairs.iter().enumerate() {
        captures::check_touch(file, i + 1, None, pair)?;
        let mut row = Vec::with_capacity(7);
        if with_location {
            match pair.location.as_deref().map(str::trim) {
                Some(l) if !l.is_empty() => row.push(l.to_owned()),
                _ => {
                    return Err(DatasetError::EmptyLocation {
                        at: Location::cell(file, i + 1, None, LOCATION_COLUMN),
                    });
                }
            }
        }
        row.extend(captures::touch_numbers(pair).map(pose::format_number));
        rows.push(row);
    }
    let header: Vec<&str> = if with_location {
        std::iter::once(LOCATION_COLUMN)
            .chain(TOUCH_COLUMNS)
            .collect()
    } else {
        TOUCH_COLUMNS.to_vec()
    };
    table::render(file, &header, &rows)
}

/// `path` made absolute without touching the file system beyond the current directory.
pub(crate) fn absolute(path: &Path) -> PathBuf {
    std::path::absolute(path).unwrap_or_else(|_| path.to_owned())
}

/// Whether relative `path`, read from a folder `depth` levels below the
/// dataset folder, climbs above the dataset folder with `..` (judged on the
/// text; symlinks are [`inside`]'s business).
pub(crate) fn climbs_out(path: &Path, depth: usize) -> bool {
    let mut depth = depth as i64;
    for c in path.components() {
        match c {
            std::path::Component::ParentDir => depth -= 1,
            std::path::Component::Normal(_) => depth += 1,
            _ => {}
        }
        if depth < 0 {
            return true;
        }
    }
    false
}

/// Refuses `path` (which exists) when it resolves, through `..` or symlinks,
/// outside `real_root` (the dataset folder with its own symlinks resolved).
pub(crate) fn inside(
    real_root: &Path,
    path: &Path,
    at: impl FnOnce() -> Location,
) -> Result<(), DatasetError> {
    let real = path.canonicalize().map_err(|e| DatasetError::io(path, e))?;
    if real.starts_with(real_root) {
        return Ok(());
    }
    Err(DatasetError::OutsideDataset {
        at: at(),
        reason: format!(
            "{} resolves to {}, outside the dataset folder {}; a dataset reads only its own files",
            path.display(),
            real.display(),
            real_root.display()
        ),
    })
}

/// What a path that is not a regular file is, in words (`a named pipe`, `a
/// directory`, ...), from its metadata (symlinks followed); `None` for a regular
/// file. Never opens the file: opening a named pipe blocks until a writer comes.
pub fn not_a_regular_file(meta: &fs::Metadata) -> Option<&'static str> {
    let kind = meta.file_type();
    if kind.is_file() {
        return None;
    }
    if kind.is_dir() {
        return Some("a directory");
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if kind.is_fifo() {
            return Some("a named pipe (FIFO)");
        }
        if kind.is_char_device() || kind.is_block_device() {
            return Some("a device");
        }
        if kind.is_socket() {
            return Some("a socket");
        }
    }
    Some("not a regular file")
}

/// Checks that `file` is a regular file of at most [`MAX_TEXT_FILE_BYTES`],
/// from its metadata, without opening it (a named pipe would block, a device
/// never end).
pub fn check_input_file(file: &Path, what: &'static str) -> Result<u64, DatasetError> {
    check_input_file_max(file, what, MAX_TEXT_FILE_BYTES)
}

/// [`check_input_file`] with another size limit.
pub(crate) fn check_input_file_max(
    file: &Path,
    what: &'static str,
    max: u64,
) -> Result<u64, DatasetError> {
    let meta = match fs::metadata(file) {
        Ok(meta) => meta,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(DatasetError::MissingFile {
                file: file.to_owned(),
                what,
            });
        }
        Err(e) => return Err(DatasetError::io(file, e)),
    };
    if let Some(kind) = not_a_regular_file(&meta) {
        return Err(DatasetError::NotARegularFile {
            file: file.to_owned(),
            kind,
        });
    }
    if meta.len() > max {
        return Err(DatasetError::FileTooLarge {
            file: file.to_owned(),
            bytes: meta.len(),
            limit: max,
        });
    }
    Ok(meta.len())
}

/// Reads a whole input file after [`check_input_file`], never more than
/// [`MAX_TEXT_FILE_BYTES`] (a file that grows while read is cut there and
/// refused).
pub(crate) fn read_bytes(file: &Path, what: &'static str) -> Result<Vec<u8>, DatasetError> {
    read_bytes_max(file, what, MAX_TEXT_FILE_BYTES)
}

/// [`read_bytes`] with another size limit.
pub(crate) fn read_bytes_max(
    file: &Path,
    what: &'static str,
    max: u64,
) -> Result<Vec<u8>, DatasetError> {
    use std::io::Read;
    let len = check_input_file_max(file, what, max)?;
    let f = fs::File::open(file).map_err(|e| DatasetError::io(file, e))?;
    let mut bytes = Vec::with_capacity(usize::try_from(len).unwrap_or(0));
    f.take(max + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| DatasetError::io(file, e))?;
    if bytes.len() as u64 > max {
        return Err(DatasetError::FileTooLarge {
            file: file.to_owned(),
            bytes: bytes.len() as u64,
            limit: max,
        });
    }
    Ok(bytes)
}

pub(crate) fn read_text(file: &Path, what: &'static str) -> Result<String, DatasetError> {
    let bytes = read_bytes(file, what)?;
    String::from_utf8(bytes).map_err(|e| {
        DatasetError::io(
            file,
            std::io::Error::new(std::io::ErrorKind::InvalidData, format!("not UTF-8: {e}")),
        )
    })
}

/// Parses JSON text, naming the offending field in errors; `file` is only used in errors.
pub(crate) fn parse_json<T: serde::de::DeserializeOwned>(
    text: &str,
    file: &Path,
) -> Result<T, DatasetError> {
    let mut de = serde_json::Deserializer::from_str(text);
    let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let field = e.path().to_string();
        DatasetError::json_at(file, field, e.into_inner())
    })?;
    de.end().map_err(|e| DatasetError::json(file, e))?;
    Ok(value)
}

/// Writes through a temporary file and a rename, so a crash never leaves half a file.
pub(crate) fn write_atomic(file: &Path, bytes: &[u8]) -> Result<(), DatasetError> {
    let name = file
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = file.with_file_name(format!(".{name}.tmp"));
    fs::write(&tmp, bytes).map_err(|e| DatasetError::io(&tmp, e))?;
    fs::rename(&tmp, file).map_err(|e| DatasetError::io(file, e))
}
