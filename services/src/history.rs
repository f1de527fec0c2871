//! The coordinator's history ([`b2b_history`]: every result and hand-eye in an
//! SQLite database, and the mount check) as `coordinator calibrate`, `run` and
//! `history` use it: warnings and entries that never cost a result, and the
//! listing on stdout.

use std::path::Path;

pub use b2b_history::*;
use b2b_protocol::CalibrationResult;

// What `coordinator calibrate`, `run` and `history` do with the database.

/// Adds the history's mount warnings to a fresh result, before it is written. A
/// history that cannot be read costs the check, never the calibration.
pub fn check_before_writing(state_dir: &Path, result: &mut CalibrationResult) {
    let db = db_path(state_dir);
    match mount_warnings(&db, result) {
        Ok(warnings) => result.warnings.extend(warnings),
        Err(e) => eprintln!(
            "warning: hand-eyes not checked against the history: {}",
            b2b_pipeline::error_chain(&e)
        ),
    }
}

/// Records a written result in the history. A failure is said on stderr and
/// leaves the exit status alone: the result files are written.
pub fn record_after_writing(
    state_dir: &Path,
    command: &str,
    result: &CalibrationResult,
    out: &Path,
    robots: &[String],
) {
    let db = db_path(state_dir);
    let result_file = std::path::absolute(out).unwrap_or_else(|_| out.to_owned());
    let rec = Record {
        recorded_at_unix_ms: now_unix_ms(),
        command,
        result,
        result_file: &result_file,
        robots,
    };
    if let Err(e) = record(&db, &rec) {
        eprintln!(
            "warning: the result is not recorded in the history: {}\n\
             the result WAS written: {}",
            b2b_pipeline::error_chain(&e),
            result_file.display()
        );
    }
}

/// `coordinator history`: the listing (of one robot, or all), as text or JSON
/// on stdout; a reader that stops early (`| head`) is not an error.
pub fn print_listing(
    state_dir: &Path,
    robot: Option<&str>,
    json: bool,
) -> Result<(), crate::ServiceError> {
    use crate::ServiceError;
    use std::io::Write as _;

    if let Some(r) = &robot {
        b2b_protocol::messages::validate_robot_id(r)?;
    }
    let db = db_path(state_dir);
    let listing = match History::open_existing(&db) {
        Ok(Some(h)) => h.list(robot),
        Ok(None) => Ok(Listing::empty(&db, robot)),
        Err(e) => Err(e),
    }
    .map_err(|e| ServiceError::HistoryRead(Box::new(e)))?;
    let mut stdout = std::io::BufWriter::new(std::io::stdout().lock());
    let written = if json {
        serde_json::to_writer_pretty(&mut stdout, &listing)
            .map_err(std::io::Error::from)
            .and_then(|()| writeln!(stdout))
    } else {
        crate::outputs::write_history(&mut stdout, &listing)
    }
    .and_then(|()| stdout.flush());
    match written {
        // `history | head`: the reader has what it wanted.
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => other.map_err(ServiceError::HistoryWrite),
    }
}
