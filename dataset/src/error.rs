//! The crate's one error type.
//!
//! Every problem a dataset can have is its own variant, so that callers (and tests) can
//! match on *what* went wrong, while the `Display` text always says *where*: the full
//! path of the file, the 1-based data row and the file's line number for CSV files, and
//! the column or JSON field. A person fixing a recording by hand should be able to go
//! straight to the cell from the message alone.

use std::fmt;
use std::path::PathBuf;

/// Where in a dataset a problem is: a file, and optionally a row, a line and a field.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Location {
    /// The file, as a full path when the dataset was opened through this crate.
    pub file: PathBuf,
    /// 1-based data row of a CSV file (the header is not a row).
    pub row: Option<usize>,
    /// 1-based line of the file (for CSV files; a row spans more than one line only when
    /// a quoted field holds a line break).
    pub line: Option<u64>,
    /// The CSV column or the JSON field, e.g. `qx..qw` or `robots[0].camera.fx`.
    pub field: Option<String>,
}

impl Location {
    /// A whole file.
    pub fn file(file: impl Into<PathBuf>) -> Self {
        Location {
            file: file.into(),
            row: None,
            line: None,
            field: None,
        }
    }

    /// A field of a JSON file.
    pub fn field(file: impl Into<PathBuf>, field: impl Into<String>) -> Self {
        Location {
            file: file.into(),
            row: None,
            line: None,
            field: Some(field.into()),
        }
    }

    /// A cell of a CSV file; `line` is `None` for data that is about to be written.
    pub fn cell(
        file: impl Into<PathBuf>,
        row: usize,
        line: Option<u64>,
        field: impl Into<String>,
    ) -> Self {
        Location {
            file: file.into(),
            row: Some(row),
            line,
            field: Some(field.into()),
        }
    }

    /// Sets the line.
    pub fn at_line(mut self, line: u64) -> Self {
        self.line = Some(line);
        self
    }
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        match (self.row, self.line) {
            (Some(row), Some(line)) => write!(f, ": row {row} (line {line})")?,
            (Some(row), None) => write!(f, ": row {row}")?,
            (None, Some(line)) => write!(f, ": line {line}")?,
            (None, None) => {}
        }
        if let Some(field) = &self.field {
            write!(f, ", field `{field}`")?;
        }
        Ok(())
    }
}

/// Everything that can be wrong with a dataset, on reading or on writing.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DatasetError {
    /// A file the format requires is not there.
    #[error("{}: file not found; {what}", file.display())]
    MissingFile { file: PathBuf, what: &'static str },

    /// An input path that is a named pipe, a device, a directory or a socket:
    /// refused from its metadata, never opened (a pipe would block).
    #[error("{}: is {kind}, not a regular file; give the path of a file", file.display())]
    NotARegularFile { file: PathBuf, kind: &'static str },

    /// An input file larger than [`crate::MAX_TEXT_FILE_BYTES`].
    #[error(
        "{}: {bytes} bytes; files over {limit} bytes (MAX_TEXT_FILE_BYTES) are not read",
        file.display()
    )]
    FileTooLarge {
        file: PathBuf,
        bytes: u64,
        limit: u64,
    },

    /// A file with more rows (captures, touches, samples) than its limit; reading
    /// stops there.
    #[error("{}: more than {limit} {what} (the limit, {constant}); {advice}", file.display())]
    TooManyRows {
        file: PathBuf,
        /// What a row is, e.g. `pose rows`.
        what: &'static str,
        limit: usize,
        /// The constant that sets the limit, e.g. `MAX_CAPTURES_PER_ROBOT`.
        constant: &'static str,
        advice: &'static str,
    },

    /// A file exists but could not be read or written.
    #[error("{}", file.display())]
    Io {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// A JSON file that is not valid JSON, or does not have the expected shape.
    /// `field` is the path of the offending value (e.g. `robots[0].camera.width`), empty
    /// for a syntax error.
    #[error(
        "{}: line {line}, column {column}{}: invalid JSON",
        file.display(),
        if field.is_empty() { String::new() } else { format!(", field `{field}`") }
    )]
    Json {
        file: PathBuf,
        line: usize,
        column: usize,
        field: String,
        #[source]
        source: serde_json::Error,
    },

    /// A YAML file (another tool's saved samples) that is not valid YAML, or does
    /// not have the expected shape; the message says where.
    #[error("{}: not the expected YAML", file.display())]
    Yaml {
        file: PathBuf,
        #[source]
        source: serde_yaml::Error,
    },

    /// Another tool's file that says something this project cannot import.
    #[error("{at}: {reason}")]
    Unsupported { at: Location, reason: String },

    /// `dataset.json` declares a format other than `b2b-dataset/1`.
    #[error("{at}: format is `{found}`, expected `{expected}`", expected = crate::FORMAT)]
    WrongFormat { at: Location, found: String },

    /// `target.kind` is not one of the kinds the format defines.
    #[error(
        "{at}: unknown target kind `{kind}`; expected one of checkerboard, charuco, aruco_grid, multimarker"
    )]
    UnknownTargetKind { at: Location, kind: String },

    /// A target parameter that cannot describe a real board.
    #[error("{at}: invalid target: {reason}")]
    InvalidTarget { at: Location, reason: String },

    /// Camera intrinsics that cannot describe a real camera.
    #[error("{at}: invalid camera intrinsics: {reason}")]
    InvalidCamera { at: Location, reason: String },

    /// Any other manifest value that is out of range (name, robot id, depth unit, ...).
    #[error("{at}: {reason}")]
    InvalidManifest { at: Location, reason: String },

    /// Two robots in the manifest share an id.
    #[error("{at}: robot id `{id}` is listed twice (first as robots[{first}])")]
    DuplicateRobot {
        at: Location,
        id: String,
        first: usize,
    },

    /// A robot of the manifest has no folder next to `dataset.json` (the folder's name
    /// is the robot id).
    #[error("{at}: the robot's folder {} does not exist", folder.display())]
    MissingRobotFolder { at: Location, folder: PathBuf },

    /// The data of a dataset being written does not match its manifest.
    #[error("{at}: {reason}")]
    RobotMismatch { at: Location, reason: String },

    /// A CSV file the CSV reader itself rejects (e.g. invalid UTF-8).
    #[error("{at}: {message}")]
    Csv { at: Location, message: String },

    /// A CSV header with missing, misnamed, duplicated or incomplete columns.
    #[error("{at}: bad header: {reason}")]
    BadHeader { at: Location, reason: String },

    /// A CSV row with a different number of fields than its header.
    #[error("{at}: {found} fields, but the header has {expected}")]
    FieldCount {
        at: Location,
        expected: usize,
        found: usize,
    },

    /// A cell that should hold a number does not.
    #[error("{at}: expected a number, found {found}")]
    BadNumber { at: Location, found: String },

    /// A number that is NaN or infinite.
    #[error("{at}: value {value} is not finite")]
    NonFinite { at: Location, value: f64 },

    /// A quaternion whose norm is too far from 1 to be a rotation.
    #[error(
        "{at}: quaternion norm {norm} is not 1 (tolerance {tolerance})",
        tolerance = b2b_protocol::QUATERNION_NORM_TOLERANCE
    )]
    NotUnitQuaternion { at: Location, norm: f64 },

    /// A coordinate too large to be metres.
    #[error(
        "{at}: {value} looks like millimetres; the format is in metres (|value| must not exceed {max} m)",
        max = crate::MAX_COORDINATE_M
    )]
    LooksLikeMillimetres { at: Location, value: f64 },

    /// One image named by two captures of the same robot.
    #[error("{at}: image {} is already used by row {first_row}", image.display())]
    DuplicateImage {
        at: Location,
        image: PathBuf,
        first_row: usize,
    },

    /// A file of the dataset that resolves (through a symlink) outside the
    /// dataset folder: refused, never read.
    #[error("{at}: {reason}")]
    OutsideDataset { at: Location, reason: String },

    /// An image named in `captures.csv` that does not exist.
    #[error("{at}: image file {} does not exist", missing.display())]
    MissingImage { at: Location, missing: PathBuf },

    /// A depth image named in `captures.csv` that does not exist.
    #[error("{at}: depth file {} does not exist", missing.display())]
    MissingDepth { at: Location, missing: PathBuf },

    /// A capture with neither an image nor a board pose: nothing to calibrate from.
    #[error(
        "{at}: the location is empty; give every touch of one physical location the same \
         text, or leave the column out"
    )]
    EmptyLocation { at: Location },
    #[error("{at}: the row has neither an image nor the board pose columns ctx..cqw")]
    NoObservation { at: Location },

    /// Some, but not all, of the seven board pose cells of a row are filled.
    #[error("{at}: the board pose ctx..cqw is partly empty; give all seven values or none")]
    PartialCameraPose { at: Location },

    /// A depth image for a robot whose manifest entry has no `depth_unit_m`.
    #[error("{at}: robot `{robot}` has depth images but no depth_unit_m in dataset.json")]
    DepthWithoutUnit { at: Location, robot: String },

    /// A path that the format does not allow (absolute, wrong extension, ...).
    /// `problem` quotes the path and says what is wrong with it.
    #[error("{at}: {problem}")]
    BadPath { at: Location, problem: String },

    /// `touch_points.csv` in a dataset with fewer than two robots.
    #[error("{}: touch points pair robot 1 with robot 2, but the manifest lists {robots} robot(s)", file.display())]
    TouchPointsNeedTwoRobots { file: PathBuf, robots: usize },

    /// `ground_truth.json` or `reference.json` names a robot that the manifest does not list.
    #[error("{at}: robot `{robot}` is not in dataset.json")]
    UnknownRobot { at: Location, robot: String },

    /// A capture names a target that dataset.json's `targets` does not list;
    /// `reason` quotes it and the ids that are listed.
    #[error("{at}: {reason}")]
    UnknownTarget { at: Location, reason: String },

    /// A key of `ground_truth.json` or `reference.json` that starts like a robot's base
    /// (`T_base1_base`) but is not `T_base1_base2` or `T_base1_base<n>` for a further
    /// robot `n` (3 up to the number of robots in dataset.json); `reason` quotes the key.
    #[error("{at}: {reason}")]
    UnknownBaseKey { at: Location, reason: String },

    /// A `touch_points_<a>_<b>.csv` whose name does not pick one pair of robots.
    #[error("{}: {reason}", file.display())]
    AmbiguousTouchFile { file: PathBuf, reason: String },
}

impl DatasetError {
    /// Where the problem is, when it can be pinned below the whole-file level.
    pub fn location(&self) -> Option<&Location> {
        use DatasetError::*;
        match self {
            MissingFile { .. }
            | Io { .. }
            | Json { .. }
            | Yaml { .. }
            | NotARegularFile { .. }
            | FileTooLarge { .. }
            | TooManyRows { .. }
            | TouchPointsNeedTwoRobots { .. }
            | AmbiguousTouchFile { .. } => None,
            WrongFormat { at, .. }
            | UnknownTargetKind { at, .. }
            | InvalidTarget { at, .. }
            | InvalidCamera { at, .. }
            | InvalidManifest { at, .. }
            | DuplicateRobot { at, .. }
            | MissingRobotFolder { at, .. }
            | RobotMismatch { at, .. }
            | Csv { at, .. }
            | BadHeader { at, .. }
            | FieldCount { at, .. }
            | BadNumber { at, .. }
            | NonFinite { at, .. }
            | NotUnitQuaternion { at, .. }
            | LooksLikeMillimetres { at, .. }
            | DuplicateImage { at, .. }
            | OutsideDataset { at, .. }
            | MissingImage { at, .. }
            | MissingDepth { at, .. }
            | NoObservation { at }
            | EmptyLocation { at }
            | PartialCameraPose { at }
            | DepthWithoutUnit { at, .. }
            | BadPath { at, .. }
            | UnknownRobot { at, .. }
            | UnknownTarget { at, .. }
            | UnknownBaseKey { at, .. }
            | Unsupported { at, .. } => Some(at),
        }
    }

    pub(crate) fn io(file: impl Into<PathBuf>, source: std::io::Error) -> Self {
        DatasetError::Io {
            file: file.into(),
            source,
        }
    }

    pub(crate) fn json(file: impl Into<PathBuf>, source: serde_json::Error) -> Self {
        Self::json_at(file, String::new(), source)
    }

    pub(crate) fn json_at(
        file: impl Into<PathBuf>,
        field: String,
        source: serde_json::Error,
    ) -> Self {
        let field = if field == "." { String::new() } else { field };
        DatasetError::Json {
            file: file.into(),
            line: source.line(),
            column: source.column(),
            field,
            source,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn location_names_file_row_line_and_field() {
        let at = Location::cell("/d/robot1/captures.csv", 3, Some(4), "qx..qw");
        assert_eq!(
            at.to_string(),
            "/d/robot1/captures.csv: row 3 (line 4), field `qx..qw`"
        );
        let at = Location::field("/d/dataset.json", "target.square_m");
        assert_eq!(at.to_string(), "/d/dataset.json, field `target.square_m`");
        let at = Location::file("/d/a.csv").at_line(1);
        assert_eq!(at.to_string(), "/d/a.csv: line 1");
    }

    use b2b_errors::assert_cause_once;

    #[test]
    fn every_wrapped_error_prints_its_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::PermissionDenied, "denied by test");
        assert_cause_once(&DatasetError::io("/d/robot1/captures.csv", io));
        let json = serde_json::from_str::<serde_json::Value>("{ nope").unwrap_err();
        let e = DatasetError::json("/d/dataset.json", json);
        assert_cause_once(&e);
        assert!(
            e.to_string().starts_with("/d/dataset.json: line 1, column"),
            "{e}"
        );
    }

    #[test]
    fn every_located_error_exposes_its_location() {
        let at = Location::cell("f.csv", 1, None, "tx");
        let e = DatasetError::NonFinite {
            at: at.clone(),
            value: f64::NAN,
        };
        assert_eq!(e.location(), Some(&at));
        assert!(
            e.to_string()
                .contains("f.csv: row 1, field `tx`: value NaN is not finite"),
            "{e}"
        );
    }
}
