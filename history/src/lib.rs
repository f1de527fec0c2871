//! What the platform has seen: every result and every hand-eye the coordinator
//! computed, in an SQLite database in its state folder (`history.sqlite`).
//!
//! Why a database and not a folder of RESULT.json files: the history is asked two
//! questions, "what was this cart's hand-eye before" (every calibration, one
//! indexed row per robot) and "list what happened" (`coordinator history`, 10,000
//! results in well under 50 ms: `cargo bench -p b2b-services --bench history`),
//! and several processes read it while one writes. SQLite in WAL mode gives
//! readers that never wait for the writer, a busy timeout for two writers, and
//! one file to back up.
//!
//! The result files stay the record of a calibration: they are written first, and
//! the database only remembers them. A database that cannot be read or written
//! (corrupt, locked, from a newer coordinator) costs the hand-eye check or the
//! history entry, never the result; the coordinator says so on stderr.
//!
//! The mount check ([`History::mount_checks`]): a camera mount that moved on its
//! flange looks, to the estimator, exactly like a new hand-eye. Each new
//! `T_flange_camera` is compared with the most recent earlier one of the same robot
//! that has a covariance, χ² = dᵀ (C_new + C_old)⁻¹ d over their left difference
//! `d` ([`b2b_calib::pose::left_difference`]); above χ²(6) at 99.9%
//! ([`MOUNT_CHI2_LIMIT`]) the two are not the same mount within what both
//! estimates allow, and the result carries [`MOUNT_WARNING`].
//!
//! Schema version 1 (`PRAGMA user_version`; `PRAGMA application_id` marks the file
//! as this history). A file of a newer version is refused by name, never altered.
//!
//! | table | one row per | columns |
//! |---|---|---|
//! | `results` | recorded result | `id`, `recorded_at_ms` (Unix ms), `command` (calibrate, run), `method`, `robots` (JSON array, robot 1 first), `T_base1_base2` as `tx ty tz qx qy qz qw`, `predicted_mean_m`, `predicted_p95_m`, `result_file` (absolute path), `warnings` (JSON array or NULL) |
//! | `result_covariances` | recorded result | `result_id`, `covariance` of `T_base1_base2` (36 little-endian f64, row-major) |
//! | `result_robots` | robot of a result | `robot`, `result_id` (the key of `--robot`) |
//! | `hand_eyes` | robot of a result with a hand-eye | `robot`, `recorded_at_ms`, `result_id` (the key: one robot's rows together, in time order), `T_flange_camera` as `tx ty tz qx qy qz qw`, `has_covariance` |
//! | `hand_eye_covariances` | hand-eye with a covariance | `robot`, `result_id`, `covariance` (as above) |
//!
//! The covariances (288 bytes each) have tables of their own so that a listing
//! reads only small rows.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use b2b_calib::Iso3;
use b2b_calib::pose::{left_difference, pose_distance};
use b2b_calib::refine::mahalanobis2;
use b2b_protocol::{CalibrationResult, Covariance6, Pose, PredictedError};
use nalgebra::Matrix6;
use rusqlite::{Connection, OpenFlags, OptionalExtension, TransactionBehavior, params};
use serde::Serialize;

/// The database's file name in the coordinator's state folder.
pub const DB_FILE: &str = "history.sqlite";

/// The schema this coordinator writes and reads (`PRAGMA user_version`).
pub const SCHEMA_VERSION: i64 = 1;

/// `PRAGMA application_id` of the history: "b2bh".
const APPLICATION_ID: i64 = 0x6232_6268;

/// How long a writer waits for another before the database counts as locked.
pub const BUSY_TIMEOUT: Duration = Duration::from_secs(2);

/// χ² with 6 degrees of freedom at 99.9%: a new hand-eye further than this from
/// its robot's last one (under both covariances) is flagged.
pub const MOUNT_CHI2_LIMIT: f64 = 22.46;

/// How every mount warning starts.
pub const MOUNT_WARNING: &str = "camera mount moved? re-check before surgery";

/// The history database in a state folder.
pub fn db_path(state_dir: &Path) -> PathBuf {
    state_dir.join(DB_FILE)
}

/// What went wrong with the history. Each names the database file.
#[derive(Debug, thiserror::Error)]
pub enum HistoryError {
    #[error("{path}: corrupt (not a readable SQLite database)")]
    Corrupt { path: PathBuf, source: SqliteCause },
    #[error("{path}: locked by another process (waited {} s)", BUSY_TIMEOUT.as_secs())]
    Locked { path: PathBuf, source: SqliteCause },
    #[error(
        "{path}: schema version {found} is newer than this coordinator's ({supported}); \
         use a newer coordinator (the file is left as it is)"
    )]
    NewerSchema {
        path: PathBuf,
        found: i64,
        supported: i64,
    },
    #[error("{path}: an SQLite database, but not the coordinator's history ({reason})")]
    NotHistory { path: PathBuf, reason: String },
    #[error("{path}: {what}")]
    Sqlite {
        path: PathBuf,
        what: &'static str,
        source: SqliteCause,
    },
    #[error("{path}: {table}, {row}: {reason}")]
    BadRow {
        path: PathBuf,
        table: &'static str,
        row: String,
        reason: String,
    },
    #[error("cannot create state folder {path}")]
    CreateDir {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// SQLite's own words for a failure, e.g. "file is not a database" (rusqlite's
/// error repeats them in its own source, which would print them twice).
#[derive(Debug)]
pub struct SqliteCause(String);

impl std::fmt::Display for SqliteCause {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for SqliteCause {}

/// Sorts an SQLite error into corrupt, locked or another failure of `what`.
fn classify(path: &Path, what: &'static str, error: rusqlite::Error) -> HistoryError {
    use rusqlite::ErrorCode as C;
    let path = path.to_owned();
    let code = error.sqlite_error_code();
    let source = SqliteCause(match error {
        rusqlite::Error::SqliteFailure(_, Some(message)) => message,
        other => other.to_string(),
    });
    match code {
        Some(C::NotADatabase | C::DatabaseCorrupt) => HistoryError::Corrupt { path, source },
        Some(C::DatabaseBusy | C::DatabaseLocked) => HistoryError::Locked { path, source },
        _ => HistoryError::Sqlite { path, what, source },
    }
}

/// Milliseconds since the Unix epoch, now.
pub fn now_unix_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// (year, month, day, hour, minute, second, millisecond) of a Unix time in UTC
/// (Howard Hinnant's `civil_from_days`).
fn civil(unix_ms: i64) -> (i64, i64, i64, i64, i64, i64, i64) {
    let (secs, ms) = (unix_ms.div_euclid(1000), unix_ms.rem_euclid(1000));
    let (days, sod) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d, sod / 3600, sod % 3600 / 60, sod % 60, ms)
}

/// `2025-06-01 12:00:03 UTC`: how the history prints a time.
pub fn format_utc(unix_ms: i64) -> String {
    let (y, mo, d, h, mi, s, _) = civil(unix_ms);
    format!("{y:04}-{mo:02}-{d:02} {h:02}:{mi:02}:{s:02} UTC")
}

/// `2025-06-01T12:00:03.123Z` (RFC 3339): the time in `history --json`.
pub fn format_rfc3339(unix_ms: i64) -> String {
    Rfc3339(unix_ms).to_string()
}

fn covariance_blob(c: &Covariance6) -> Vec<u8> {
    c.iter().flatten().flat_map(|v| v.to_le_bytes()).collect()
}

fn covariance_from_blob(bytes: &[u8]) -> Result<Covariance6, String> {
    if bytes.len() != 36 * 8 {
        return Err(format!(
            "covariance has {} bytes, not 288 (36 f64)",
            bytes.len()
        ));
    }
    let mut c = [[0.0; 6]; 6];
    for (k, chunk) in bytes.chunks_exact(8).enumerate() {
        let mut b = [0u8; 8];
        b.copy_from_slice(chunk);
        c[k / 6][k % 6] = f64::from_le_bytes(b);
    }
    b2b_protocol::validate_covariance("covariance", &c).map_err(|e| e.to_string())?;
    Ok(c)
}

fn matrix(c: &Covariance6) -> Matrix6<f64> {
    Matrix6::from_fn(|i, j| c[i][j])
}

/// What a calibration leaves in the history.
#[derive(Debug, Clone, Copy)]
pub struct Record<'a> {
    /// When it was computed (Unix ms; [`now_unix_ms`]).
    pub recorded_at_unix_ms: i64,
    /// The command that computed it: `calibrate` or `run`.
    pub command: &'a str,
    pub result: &'a CalibrationResult,
    /// Where its RESULT.json was written (stored as given: pass it absolute).
    pub result_file: &'a Path,
    /// Its robots, robot 1 (the reference) first.
    pub robots: &'a [String],
}

/// The robots of a result in order when no one said: the reference first, then
/// the others by id.
pub fn robots_of(result: &CalibrationResult) -> Vec<String> {
    let mut ids: Vec<String> = result
        .hand_eye
        .keys()
        .chain(result.captures.used.keys())
        .chain(result.bases.keys())
        .cloned()
        .collect();
    ids.sort();
    ids.dedup();
    if let Some(reference) = &result.reference
        && let Some(i) = ids.iter().position(|r| r == reference)
    {
        let r = ids.remove(i);
        ids.insert(0, r);
    }
    ids
}

/// A Unix time (ms) written as RFC 3339 UTC, e.g. `2025-06-01T12:00:03.123Z`
/// (`history --json`'s `recorded_at`); formatted only when written, so a
/// listing of ten thousand rows formats none it does not print.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rfc3339(pub i64);

impl std::fmt::Display for Rfc3339 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (y, mo, d, h, mi, s, ms) = civil(self.0);
        write!(f, "{y:04}-{mo:02}-{d:02}T{h:02}:{mi:02}:{s:02}.{ms:03}Z")
    }
}

impl Serialize for Rfc3339 {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

/// One recorded result, as `coordinator history` lists it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ResultRow {
    pub id: i64,
    pub recorded_at: Rfc3339,
    pub recorded_at_unix_ms: i64,
    pub command: String,
    pub method: String,
    /// Robot 1 first.
    pub robots: Vec<String>,
    #[serde(rename = "T_base1_base2")]
    pub base1_from_base2: Pose,
    pub predicted_touch_error_m: PredictedError,
    pub result_file: String,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// One robot's hand-eye from one recorded result.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HandEyeRow {
    pub result_id: i64,
    pub robot: String,
    pub recorded_at: Rfc3339,
    pub recorded_at_unix_ms: i64,
    #[serde(rename = "T_flange_camera")]
    pub flange_from_camera: Pose,
    /// Whether the result gave its covariance (the mount check needs one).
    pub has_covariance: bool,
}

/// What `coordinator history` prints (`--json`: this as JSON).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Listing {
    /// The database file.
    pub database: String,
    /// Its schema version; 0 for a database with nothing recorded yet.
    pub schema_version: i64,
    /// `--robot`, when given.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot: Option<String>,
    /// Oldest first.
    pub results: Vec<ResultRow>,
    /// By robot, oldest first.
    pub hand_eyes: BTreeMap<String, Vec<HandEyeRow>>,
}

impl Listing {
    /// The listing of a database that does not exist or has nothing recorded.
    pub fn empty(database: &Path, robot: Option<&str>) -> Listing {
        Listing {
            database: database.display().to_string(),
            schema_version: 0,
            robot: robot.map(str::to_owned),
            results: Vec::new(),
            hand_eyes: BTreeMap::new(),
        }
    }
}

/// A new hand-eye against its robot's most recent earlier one with a covariance.
#[derive(Debug, Clone, PartialEq)]
pub struct MountCheck {
    pub robot: String,
    /// dᵀ (C_new + C_old)⁻¹ d.
    pub chi2: f64,
    /// [`MOUNT_CHI2_LIMIT`].
    pub limit: f64,
    /// How far the camera's origin moved in the flange (m).
    pub translation_m: f64,
    /// How far it turned (rad).
    pub rotation_rad: f64,
    /// When the earlier hand-eye was recorded (Unix ms).
    pub earlier_unix_ms: i64,
    /// Its result's id in the history.
    pub earlier_result_id: i64,
}

impl MountCheck {
    /// Whether the two hand-eyes differ by more than both covariances explain.
    pub fn moved(&self) -> bool {
        self.chi2 > self.limit
    }

    /// The warning the result, the report and the printout carry.
    pub fn warning(&self) -> String {
        format!(
            "{MOUNT_WARNING}: {}'s hand-eye (T_flange_camera) differs from the one recorded \
             {} (history result #{}) by {:.2} mm and {:.2} deg: chi-square {:.1} > {:.2} \
             (the 99.9% limit for 6 dof, under both estimates' covariances)",
            self.robot,
            format_utc(self.earlier_unix_ms),
            self.earlier_result_id,
            self.translation_m * 1e3,
            self.rotation_rad.to_degrees(),
            self.chi2,
            self.limit
        )
    }
}

/// χ² of two estimates of one hand-eye under both covariances: the left
/// difference `d` of `new` from `old`, `dᵀ (C_new + C_old)⁻¹ d`. `None` when the
/// summed covariance is singular.
pub fn mount_chi2(
    new: &Iso3,
    new_covariance: &Covariance6,
    old: &Iso3,
    old_covariance: &Covariance6,
) -> Option<f64> {
    let d = left_difference(new, old);
    mahalanobis2(&d, &(matrix(new_covariance) + matrix(old_covariance)))
}

/// How a database file looked when opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Schema {
    /// No tables: nothing recorded yet.
    Fresh,
    Current,
}

/// The history database, open.
#[derive(Debug)]
pub struct History {
    conn: Connection,
    path: PathBuf,
    schema: Schema,
}

const RESULT_COLUMNS: &str = "id, recorded_at_ms, command, method, robots, tx, ty, tz, qx, qy, \
                              qz, qw, predicted_mean_m, predicted_p95_m, result_file, warnings";
const HAND_EYE_COLUMNS: &str =
    "result_id, robot, recorded_at_ms, tx, ty, tz, qx, qy, qz, qw, has_covariance";

const CREATE: &str = "
CREATE TABLE results (
    id INTEGER PRIMARY KEY,
    recorded_at_ms INTEGER NOT NULL,
    command TEXT NOT NULL,
    method TEXT NOT NULL,
    robots TEXT NOT NULL,
    tx REAL NOT NULL, ty REAL NOT NULL, tz REAL NOT NULL,
    qx REAL NOT NULL, qy REAL NOT NULL, qz REAL NOT NULL, qw REAL NOT NULL,
    predicted_mean_m REAL NOT NULL,
    predicted_p95_m REAL NOT NULL,
    result_file TEXT NOT NULL,
    warnings TEXT
);
CREATE TABLE result_covariances (
    result_id INTEGER PRIMARY KEY REFERENCES results (id),
    covariance BLOB NOT NULL
);
CREATE TABLE result_robots (
    robot TEXT NOT NULL,
    result_id INTEGER NOT NULL REFERENCES results (id),
    PRIMARY KEY (robot, result_id)
) WITHOUT ROWID;
CREATE TABLE hand_eyes (
    robot TEXT NOT NULL,
    recorded_at_ms INTEGER NOT NULL,
    result_id INTEGER NOT NULL REFERENCES results (id),
    tx REAL NOT NULL, ty REAL NOT NULL, tz REAL NOT NULL,
    qx REAL NOT NULL, qy REAL NOT NULL, qz REAL NOT NULL, qw REAL NOT NULL,
    has_covariance INTEGER NOT NULL,
    PRIMARY KEY (robot, recorded_at_ms, result_id)
) WITHOUT ROWID;
CREATE TABLE hand_eye_covariances (
    robot TEXT NOT NULL,
    result_id INTEGER NOT NULL REFERENCES results (id),
    covariance BLOB NOT NULL,
    PRIMARY KEY (robot, result_id)
);
";

/// A pose from seven columns starting at `first`, checked.
fn pose_at(row: &rusqlite::Row<'_>, first: usize) -> rusqlite::Result<Pose> {
    Ok(Pose {
        t: [row.get(first)?, row.get(first + 1)?, row.get(first + 2)?],
        q: [
            row.get(first + 3)?,
            row.get(first + 4)?,
            row.get(first + 5)?,
            row.get(first + 6)?,
        ],
    })
}

/// Reads the schema's marks: fresh (no tables), ours at the current version, or
/// refused.
fn schema_of(conn: &Connection, path: &Path) -> Result<Schema, HistoryError> {
    let read = |sql: &str| -> Result<i64, HistoryError> {
        conn.query_row(sql, [], |r| r.get(0))
            .map_err(|e| classify(path, "cannot read the schema", e))
    };
    let application_id = read("PRAGMA application_id")?;
    let version = read("PRAGMA user_version")?;
    let tables = read("SELECT count(*) FROM sqlite_master")?;
    if application_id != APPLICATION_ID {
        if application_id == 0 && version == 0 && tables == 0 {
            return Ok(Schema::Fresh);
        }
        return Err(HistoryError::NotHistory {
            path: path.to_owned(),
            reason: format!(
                "application id {application_id:#x}, user version {version}, {tables} schema objects"
            ),
        });
    }
    match version {
        SCHEMA_VERSION => Ok(Schema::Current),
        v if v > SCHEMA_VERSION => Err(HistoryError::NewerSchema {
            path: path.to_owned(),
            found: v,
            supported: SCHEMA_VERSION,
        }),
        v => Err(HistoryError::NotHistory {
            path: path.to_owned(),
            reason: format!("schema version {v} was never written by a coordinator"),
        }),
    }
}

impl History {
    /// Opens the history to record into, creating the file (and its folder) with
    /// the current schema when there is none.
    pub fn open(path: &Path) -> Result<History, HistoryError> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|source| HistoryError::CreateDir {
                path: dir.to_owned(),
                source,
            })?;
        }
        let conn =
            Connection::open(path).map_err(|e| classify(path, "cannot open the database", e))?;
        let mut history = History::configure(conn, path)?;
        if history.schema == Schema::Fresh {
            history.create()?;
        }
        Ok(history)
    }

    /// Opens an existing history to read; `Ok(None)` when there is no file.
    pub fn open_existing(path: &Path) -> Result<Option<History>, HistoryError> {
        if !path.exists() {
            return Ok(None);
        }
        // Read-write without create: a WAL reader may need to create the shared
        // memory file beside the database.
        let flags = OpenFlags::SQLITE_OPEN_READ_WRITE
            | OpenFlags::SQLITE_OPEN_NO_MUTEX
            | OpenFlags::SQLITE_OPEN_URI;
        let conn = Connection::open_with_flags(path, flags)
            .map_err(|e| classify(path, "cannot open the database", e))?;
        History::configure(conn, path).map(Some)
    }

    fn configure(conn: Connection, path: &Path) -> Result<History, HistoryError> {
        conn.busy_timeout(BUSY_TIMEOUT)
            .map_err(|e| classify(path, "cannot set the busy timeout", e))?;
        let schema = schema_of(&conn, path)?;
        // WAL: durable against a crash (not the last commits against a power
        // cut, which the result files, written first, cover).
        conn.pragma_update(None, "synchronous", "NORMAL")
            .map_err(|e| classify(path, "cannot set synchronous", e))?;
        // Reads straight from the page cache, no read call per page: a listing
        // of every result touches every page once.
        conn.pragma_update(None, "mmap_size", 256i64 << 20)
            .map_err(|e| classify(path, "cannot set mmap_size", e))?;
        Ok(History {
            conn,
            path: path.to_owned(),
            schema,
        })
    }

    /// Creates the tables of a fresh file (another process may have done so
    /// meanwhile: checked again inside the transaction).
    fn create(&mut self) -> Result<(), HistoryError> {
        let path = self.path.as_path();
        let e = |what: &'static str| move |err| classify(path, what, err);
        // Readers never wait for the writer. A journal-mode change needs the
        // file to itself, so it happens once, here.
        self.conn
            .query_row("PRAGMA journal_mode=WAL", [], |r| r.get::<_, String>(0))
            .map_err(e("cannot switch to WAL journal mode"))?;
        let tx = self
            .conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(e("cannot begin a transaction"))?;
        if schema_of(&tx, path)? == Schema::Fresh {
            tx.execute_batch(CREATE)
                .map_err(e("cannot create the tables"))?;
            tx.pragma_update(None, "application_id", APPLICATION_ID)
                .map_err(e("cannot set the application id"))?;
            tx.pragma_update(None, "user_version", SCHEMA_VERSION)
                .map_err(e("cannot set the schema version"))?;
        }
        tx.commit().map_err(e("cannot commit the schema"))?;
        self.schema = Schema::Current;
        Ok(())
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn err(&self, what: &'static str) -> impl Fn(rusqlite::Error) -> HistoryError + '_ {
        move |e| classify(&self.path, what, e)
    }

    fn bad_row(&self, table: &'static str, row: String, reason: String) -> HistoryError {
        HistoryError::BadRow {
            path: self.path.clone(),
            table,
            row,
            reason,
        }
    }

    /// Records a result and its hand-eyes in one transaction; returns its id.
    pub fn record(&mut self, rec: &Record<'_>) -> Result<i64, HistoryError> {
        if self.schema == Schema::Fresh {
            self.create()?;
        }
        let path = self.path.as_path();
        let e = |what: &'static str| move |err| classify(path, what, err);
        let r = rec.result;
        let robots = serde_json::to_string(rec.robots).unwrap_or_else(|_| "[]".into());
        let warnings = (!r.warnings.is_empty())
            .then(|| serde_json::to_string(&r.warnings).unwrap_or_else(|_| "[]".into()));
        let (t, q) = (r.base1_from_base2.t, r.base1_from_base2.q);
        let tx = self
            .conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(e("cannot begin a transaction"))?;
        tx.execute(
            "INSERT INTO results (recorded_at_ms, command, method, robots, tx, ty, tz, qx, qy, \
             qz, qw, predicted_mean_m, predicted_p95_m, result_file, warnings) \
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15)",
            params![
                rec.recorded_at_unix_ms,
                rec.command,
                r.method,
                robots,
                t[0],
                t[1],
                t[2],
                q[0],
                q[1],
                q[2],
                q[3],
                r.predicted_touch_error_m.mean,
                r.predicted_touch_error_m.p95,
                rec.result_file.display().to_string(),
                warnings,
            ],
        )
        .map_err(e("cannot insert the result"))?;
        let id = tx.last_insert_rowid();
        tx.execute(
            "INSERT INTO result_covariances (result_id, covariance) VALUES (?1, ?2)",
            params![id, covariance_blob(&r.covariance)],
        )
        .map_err(e("cannot insert the result's covariance"))?;
        {
            let mut insert = tx
                .prepare_cached(
                    "INSERT OR IGNORE INTO result_robots (robot, result_id) VALUES (?1, ?2)",
                )
                .map_err(e("cannot insert the result's robots"))?;
            for robot in rec.robots.iter().chain(r.hand_eye.keys()) {
                insert
                    .execute(params![robot, id])
                    .map_err(e("cannot insert the result's robots"))?;
            }
            let mut insert = tx
                .prepare_cached(
                    "INSERT INTO hand_eyes (result_id, robot, recorded_at_ms, tx, ty, tz, qx, \
                     qy, qz, qw, has_covariance) \
                     VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11)",
                )
                .map_err(e("cannot insert a hand-eye"))?;
            let mut insert_covariance = tx
                .prepare_cached(
                    "INSERT INTO hand_eye_covariances (robot, result_id, covariance) \
                     VALUES (?1, ?2, ?3)",
                )
                .map_err(e("cannot insert a hand-eye's covariance"))?;
            for (robot, pose) in &r.hand_eye {
                let (t, q) = (pose.t, pose.q);
                let covariance = r.hand_eye_covariance.get(robot);
                insert
                    .execute(params![
                        id,
                        robot,
                        rec.recorded_at_unix_ms,
                        t[0],
                        t[1],
                        t[2],
                        q[0],
                        q[1],
                        q[2],
                        q[3],
                        covariance.is_some(),
                    ])
                    .map_err(e("cannot insert a hand-eye"))?;
                if let Some(c) = covariance {
                    insert_covariance
                        .execute(params![robot, id, covariance_blob(c)])
                        .map_err(e("cannot insert a hand-eye's covariance"))?;
                }
            }
        }
        tx.commit().map_err(e("cannot commit the result"))?;
        Ok(id)
    }

    /// Every recorded result (of `robot`, when given) and every hand-eye (of
    /// `robot`), oldest first.
    pub fn list(&self, robot: Option<&str>) -> Result<Listing, HistoryError> {
        let mut listing = Listing::empty(&self.path, robot);
        if self.schema == Schema::Fresh {
            return Ok(listing);
        }
        listing.schema_version = SCHEMA_VERSION;
        // In id order, which is nearly time order: sorted here by time, which
        // costs less than SQLite's sort into a temporary tree.
        let sql = match robot {
            Some(_) => format!(
                "SELECT {RESULT_COLUMNS} FROM result_robots JOIN results \
                 ON results.id = result_robots.result_id WHERE result_robots.robot = ?1 \
                 ORDER BY result_robots.result_id"
            ),
            None => format!("SELECT {RESULT_COLUMNS} FROM results ORDER BY id"),
        };
        let mut stmt = self
            .conn
            .prepare_cached(&sql)
            .map_err(self.err("cannot read the results"))?;
        let map = |row: &rusqlite::Row<'_>| {
            Ok((
                row.get::<_, i64>(0)?,
                row.get::<_, i64>(1)?,
                row.get::<_, String>(2)?,
                row.get::<_, String>(3)?,
                row.get::<_, String>(4)?,
                pose_at(row, 5)?,
                PredictedError {
                    mean: row.get(12)?,
                    p95: row.get(13)?,
                },
                row.get::<_, String>(14)?,
                row.get::<_, Option<String>>(15)?,
            ))
        };
        let rows = match robot {
            Some(r) => stmt.query_map([r], map),
            None => stmt.query_map([], map),
        }
        .map_err(self.err("cannot read the results"))?;
        // Consecutive results mostly have the same robots: parsed once.
        let mut last_robots: Option<(String, Vec<String>)> = None;
        for row in rows {
            let (id, at, command, method, robots, pose, predicted, file, warnings) =
                row.map_err(self.err("cannot read the results"))?;
            let which = || format!("id {id}");
            pose.to_isometry("T_base1_base2")
                .map_err(|e| self.bad_row("results", which(), e.to_string()))?;
            let robots = match &last_robots {
                Some((text, parsed)) if *text == robots => parsed.clone(),
                _ => {
                    let parsed: Vec<String> = serde_json::from_str(&robots)
                        .map_err(|e| self.bad_row("results", which(), format!("robots: {e}")))?;
                    last_robots = Some((robots, parsed.clone()));
                    parsed
                }
            };
            let warnings: Vec<String> = match warnings {
                Some(w) => serde_json::from_str(&w)
                    .map_err(|e| self.bad_row("results", which(), format!("warnings: {e}")))?,
                None => Vec::new(),
            };
            listing.results.push(ResultRow {
                id,
                recorded_at: Rfc3339(at),
                recorded_at_unix_ms: at,
                command,
                method,
                robots,
                base1_from_base2: pose,
                predicted_touch_error_m: predicted,
                result_file: file,
                warnings,
            });
        }
        listing
            .results
            .sort_by_key(|r| (r.recorded_at_unix_ms, r.id));
        // Rows come by robot: one group per run of the same robot.
        let mut rows = self.hand_eyes(robot)?.into_iter().peekable();
        while let Some(first) = rows.next() {
            let mut group = vec![first];
            while let Some(next) = rows.next_if(|r| r.robot == group[0].robot) {
                group.push(next);
            }
            listing.hand_eyes.insert(group[0].robot.clone(), group);
        }
        Ok(listing)
    }

    /// Every recorded hand-eye (of `robot`, when given), by robot, oldest first.
    pub fn hand_eyes(&self, robot: Option<&str>) -> Result<Vec<HandEyeRow>, HistoryError> {
        if self.schema == Schema::Fresh {
            return Ok(Vec::new());
        }
        let sql = match robot {
            Some(_) => format!(
                "SELECT {HAND_EYE_COLUMNS} FROM hand_eyes WHERE robot = ?1 \
                 ORDER BY recorded_at_ms, result_id"
            ),
            None => format!(
                "SELECT {HAND_EYE_COLUMNS} FROM hand_eyes ORDER BY robot, recorded_at_ms, \
                 result_id"
            ),
        };
        let mut stmt = self
            .conn
            .prepare_cached(&sql)
            .map_err(self.err("cannot read the hand-eyes"))?;
        let map = |row: &rusqlite::Row<'_>| {
            let at = row.get(2)?;
            Ok(HandEyeRow {
                result_id: row.get(0)?,
                robot: row.get(1)?,
                recorded_at: Rfc3339(at),
                recorded_at_unix_ms: at,
                flange_from_camera: pose_at(row, 3)?,
                has_covariance: row.get(10)?,
            })
        };
        let rows = match robot {
            Some(r) => stmt.query_map([r], map),
            None => stmt.query_map([], map),
        }
        .map_err(self.err("cannot read the hand-eyes"))?;
        let mut out = Vec::new();
        for row in rows {
            let row = row.map_err(self.err("cannot read the hand-eyes"))?;
            row.flange_from_camera
                .to_isometry("T_flange_camera")
                .map_err(|e| {
                    let which = format!("{} of result {}", row.robot, row.result_id);
                    self.bad_row("hand_eyes", which, e.to_string())
                })?;
            out.push(row);
        }
        Ok(out)
    }

    /// The most recent hand-eye of `robot` that has a covariance: (result id,
    /// recorded at, pose, covariance).
    fn latest_with_covariance(
        &self,
        robot: &str,
    ) -> Result<Option<(i64, i64, Iso3, Covariance6)>, HistoryError> {
        if self.schema == Schema::Fresh {
            return Ok(None);
        }
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT h.result_id, h.recorded_at_ms, h.tx, h.ty, h.tz, h.qx, h.qy, h.qz, h.qw, \
                 c.covariance FROM hand_eyes h JOIN hand_eye_covariances c \
                 ON c.robot = h.robot AND c.result_id = h.result_id \
                 WHERE h.robot = ?1 AND h.has_covariance \
                 ORDER BY h.recorded_at_ms DESC, h.result_id DESC LIMIT 1",
            )
            .map_err(self.err("cannot read the hand-eyes"))?;
        let row = stmt
            .query_row([robot], |row| {
                Ok((
                    row.get::<_, i64>(0)?,
                    row.get::<_, i64>(1)?,
                    pose_at(row, 2)?,
                    row.get::<_, Vec<u8>>(9)?,
                ))
            })
            .optional()
            .map_err(self.err("cannot read the hand-eyes"))?;
        let Some((result_id, at, pose, blob)) = row else {
            return Ok(None);
        };
        let which = || format!("{robot} of result {result_id}");
        let iso = pose
            .to_isometry("T_flange_camera")
            .map_err(|e| self.bad_row("hand_eyes", which(), e.to_string()))?;
        let covariance = covariance_from_blob(&blob)
            .map_err(|reason| self.bad_row("hand_eye_covariances", which(), reason))?;
        Ok(Some((result_id, at, iso, covariance)))
    }

    /// Each hand-eye of `result` that has a covariance against its robot's most
    /// recent recorded one with a covariance (call before recording `result`).
    /// A robot without a covariance, or without an earlier hand-eye, is not
    /// checked (said at debug level).
    pub fn mount_checks(
        &self,
        result: &CalibrationResult,
    ) -> Result<Vec<MountCheck>, HistoryError> {
        let mut out = Vec::new();
        for (robot, pose) in &result.hand_eye {
            let Some(covariance) = result.hand_eye_covariance.get(robot) else {
                tracing::debug!(
                    "{robot}: the result has no hand-eye covariance, so no check against {}",
                    self.path.display()
                );
                continue;
            };
            let Some((earlier_result_id, earlier_unix_ms, old, old_covariance)) =
                self.latest_with_covariance(robot)?
            else {
                tracing::debug!(
                    "{robot}: no earlier hand-eye with a covariance in {}",
                    self.path.display()
                );
                continue;
            };
            let Ok(new) = pose.to_isometry("hand_eye") else {
                tracing::debug!("{robot}: the result's hand-eye is not a pose; not checked");
                continue;
            };
            let Some(chi2) = mount_chi2(&new, covariance, &old, &old_covariance) else {
                tracing::debug!("{robot}: the summed hand-eye covariance is singular; not checked");
                continue;
            };
            let (translation_m, rotation_rad) = pose_distance(&new, &old);
            let check = MountCheck {
                robot: robot.clone(),
                chi2,
                limit: MOUNT_CHI2_LIMIT,
                translation_m,
                rotation_rad,
                earlier_unix_ms,
                earlier_result_id,
            };
            tracing::debug!(
                "{robot}: hand-eye against {}: chi-square {chi2:.2} (limit {MOUNT_CHI2_LIMIT})",
                format_utc(earlier_unix_ms)
            );
            out.push(check);
        }
        Ok(out)
    }
}

/// The mount warnings of a fresh result from the history at `db` (none when the
/// file does not exist).
pub fn mount_warnings(db: &Path, result: &CalibrationResult) -> Result<Vec<String>, HistoryError> {
    let Some(history) = History::open_existing(db)? else {
        return Ok(Vec::new());
    };
    Ok(history
        .mount_checks(result)?
        .iter()
        .filter(|c| c.moved())
        .map(MountCheck::warning)
        .collect())
}

/// Records a result in the history at `db`, creating the file if needed.
pub fn record(db: &Path, rec: &Record<'_>) -> Result<i64, HistoryError> {
    History::open(db)?.record(rec)
}

#[cfg(test)]
mod tests {
    use super::*;
    use b2b_calib::pose::perturb_left;
    use nalgebra::{Isometry3, Vector3, Vector6};

    #[test]
    fn times_print_as_utc_calendar_dates() {
        assert_eq!(format_utc(0), "1970-01-01 00:00:00 UTC");
        assert_eq!(format_rfc3339(951_782_400_000), "2000-02-29T00:00:00.000Z");
        assert_eq!(format_utc(1_700_000_000_123), "2023-11-14 22:13:20 UTC");
        assert_eq!(
            format_rfc3339(1_700_000_000_123),
            "2023-11-14T22:13:20.123Z"
        );
        assert_eq!(format_utc(-1), "1969-12-31 23:59:59 UTC");
    }

    #[test]
    fn covariances_round_trip_and_bad_blobs_are_refused() {
        let mut c = [[0.0; 6]; 6];
        for (i, row) in c.iter_mut().enumerate() {
            row[i] = 1e-6 * (i + 1) as f64;
        }
        c[0][3] = 1e-8;
        c[3][0] = 1e-8;
        assert_eq!(covariance_from_blob(&covariance_blob(&c)).unwrap(), c);
        assert!(
            covariance_from_blob(&[0; 17])
                .unwrap_err()
                .contains("17 bytes")
        );
        c[2][2] = f64::NAN;
        assert!(covariance_from_blob(&covariance_blob(&c)).is_err());
    }

    fn diag(sigma_r: f64, sigma_t: f64) -> Covariance6 {
        let mut c = [[0.0; 6]; 6];
        for (i, row) in c.iter_mut().enumerate() {
            row[i] = if i < 3 { sigma_r } else { sigma_t }.powi(2);
        }
        c
    }

    #[test]
    fn the_mount_chi_square_is_the_mahalanobis_distance_under_both_covariances() {
        let old = Isometry3::new(Vector3::new(0.05, -0.02, 0.1), Vector3::new(0.1, 0.2, -0.3));
        // 0.1 mm / 0.01 deg in each axis, each estimate.
        let c = diag(0.01f64.to_radians(), 1e-4);
        // One sigma of the sum in each of the six axes: chi-square 6.
        let s = (2.0f64).sqrt();
        let d = Vector6::new(
            0.01f64.to_radians() * s,
            0.01f64.to_radians() * s,
            0.01f64.to_radians() * s,
            1e-4 * s,
            1e-4 * s,
            1e-4 * s,
        );
        let new = perturb_left(&d, &old);
        let chi2 = mount_chi2(&new, &c, &old, &c).unwrap();
        assert!((chi2 - 6.0).abs() < 1e-6, "{chi2}");
        // A mount moved by 3 mm and 1 degree is far outside: (1 / 0.01)^2 / 2 for
        // the rotation, (3 / 0.1)^2 / 2 for the translation.
        let moved = perturb_left(
            &Vector6::new(1f64.to_radians(), 0.0, 0.0, 0.003, 0.0, 0.0),
            &old,
        );
        let chi2 = mount_chi2(&moved, &c, &old, &c).unwrap();
        assert!((chi2 - 5450.0).abs() < 1e-6 * 5450.0, "{chi2}");
        // The same pose: zero.
        assert!(mount_chi2(&old, &c, &old, &c).unwrap() < 1e-12);
        // A singular sum: no answer rather than a number.
        assert!(mount_chi2(&moved, &[[0.0; 6]; 6], &old, &[[0.0; 6]; 6]).is_none());
    }

    #[test]
    fn every_wrapped_error_prints_its_cause_once() {
        let path = PathBuf::from("/state/history.sqlite");
        let failure = |code, message: &str| {
            rusqlite::Error::SqliteFailure(rusqlite::ffi::Error::new(code), Some(message.into()))
        };
        let locked = classify(
            &path,
            "x",
            failure(rusqlite::ffi::SQLITE_BUSY, "database is locked"),
        );
        let corrupt = classify(
            &path,
            "x",
            failure(rusqlite::ffi::SQLITE_NOTADB, "file is not a database"),
        );
        let other = classify(
            &path,
            "cannot read the results",
            failure(rusqlite::ffi::SQLITE_IOERR, "disk I/O error"),
        );
        assert!(matches!(locked, HistoryError::Locked { .. }), "{locked:?}");
        assert!(
            matches!(corrupt, HistoryError::Corrupt { .. }),
            "{corrupt:?}"
        );
        assert!(matches!(other, HistoryError::Sqlite { .. }), "{other:?}");
        // SQLite's words once: rusqlite's own error would print them twice.
        assert_eq!(
            b2b_errors::chain(&corrupt),
            "/state/history.sqlite: corrupt (not a readable SQLite database): file is not a database"
        );
        for e in [
            locked,
            corrupt,
            other,
            HistoryError::CreateDir {
                path: path.clone(),
                source: std::io::Error::other("disk on fire"),
            },
        ] {
            b2b_errors::assert_cause_once(&e);
            assert!(b2b_errors::chain(&e).contains("/state/history.sqlite"));
        }
    }

    fn result_with(
        robot_pose: Isometry3<f64>,
        covariance: Option<Covariance6>,
    ) -> CalibrationResult {
        let text = include_str!("../../report/tests/fixtures/RESULT.json");
        let mut r: CalibrationResult = serde_json::from_str(text).unwrap();
        r.hand_eye
            .insert("robot2".into(), Pose::from_isometry(&robot_pose));
        r.hand_eye_covariance.clear();
        if let Some(c) = covariance {
            r.hand_eye_covariance.insert("robot2".into(), c);
        }
        r
    }

    #[test]
    fn a_moved_mount_is_flagged_against_the_latest_hand_eye_with_a_covariance() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("state").join(DB_FILE);
        let x = Isometry3::new(Vector3::new(0.05, -0.02, 0.1), Vector3::new(0.1, 0.2, -0.3));
        let moved = perturb_left(
            &Vector6::new(0.0, 1f64.to_radians(), 0.0, 0.003, 0.0, 0.0),
            &x,
        );
        let c = diag(0.01f64.to_radians(), 1e-4);
        let robots = vec!["robot1".to_owned(), "robot2".to_owned()];
        let rec = |r: &CalibrationResult, at| {
            record(
                &db,
                &Record {
                    recorded_at_unix_ms: at,
                    command: "calibrate",
                    result: r,
                    result_file: Path::new("/out/RESULT.json"),
                    robots: &robots,
                },
            )
            .unwrap()
        };
        // Nothing recorded yet: no file, no warning, and nothing created.
        assert!(
            mount_warnings(&db, &result_with(moved, Some(c)))
                .unwrap()
                .is_empty()
        );
        assert!(!db.exists());
        rec(&result_with(x, Some(c)), 1_700_000_000_000);
        // The latest hand-eye has no covariance: the one before it is compared.
        rec(&result_with(moved, None), 1_700_000_100_000);
        let warnings = mount_warnings(&db, &result_with(moved, Some(c))).unwrap();
        assert_eq!(warnings.len(), 1, "{warnings:?}");
        let w = &warnings[0];
        assert!(w.starts_with(MOUNT_WARNING), "{w}");
        assert!(
            w.contains("robot2") && w.contains("2023-11-14 22:13:20 UTC"),
            "{w}"
        );
        assert!(w.contains("1.00 deg") && w.contains("> 22.46"), "{w}");
        // The same hand-eye again: checked, not flagged.
        let history = History::open_existing(&db).unwrap().unwrap();
        let checks = history.mount_checks(&result_with(x, Some(c))).unwrap();
        assert_eq!(checks.len(), 1);
        assert!(!checks[0].moved() && checks[0].chi2 < 1e-9, "{checks:?}");
        // robot1 of the fixture has no covariance: not checked at all.
        assert!(checks.iter().all(|c| c.robot == "robot2"));

        let listing = history.list(Some("robot2")).unwrap();
        assert_eq!(listing.results.len(), 2);
        assert_eq!(listing.hand_eyes["robot2"].len(), 2);
        assert!(listing.hand_eyes["robot2"][0].has_covariance);
        assert!(!listing.hand_eyes["robot2"][1].has_covariance);
        assert_eq!(listing.results[0].robots, robots);
        assert!(history.list(Some("robot9")).unwrap().results.is_empty());
    }
}
