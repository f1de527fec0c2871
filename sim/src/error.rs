//! The crate's one error type.

use std::path::PathBuf;

/// Everything that can go wrong in the simulator. Messages say what was wrong and,
/// for files, which file and which field.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    /// A scene file that is not valid JSON or does not have the expected shape.
    #[error("{}: line {line}, column {column}{}: {message}", file.display(),
        if field.is_empty() { String::new() } else { format!(", field `{field}`") })]
    SceneJson {
        file: PathBuf,
        field: String,
        line: usize,
        column: usize,
        message: String,
    },

    /// A scene value out of range.
    #[error("{}: field `{field}`: {reason}", file.display())]
    SceneValue {
        file: PathBuf,
        field: String,
        reason: String,
    },

    /// A parameter passed to a library function that cannot describe anything real.
    #[error("invalid {what}: {reason}")]
    InvalidParameter { what: &'static str, reason: String },

    /// The planner could not find enough viewpoints or touches that satisfy every
    /// constraint (reachable, board fully in view, inside the limits).
    #[error("{what}: found only {found} of {wanted} after {attempts} attempts")]
    PlanningFailed {
        what: String,
        found: usize,
        wanted: usize,
        attempts: usize,
    },

    /// A file could not be read or written.
    #[error("{}", file.display())]
    Io {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// PNG encoding failed.
    #[error("{}: PNG encoding failed: {message}", file.display())]
    Png { file: PathBuf, message: String },

    /// The dataset writer rejected what the simulator produced.
    #[error(transparent)]
    Dataset(#[from] b2b_dataset::DatasetError),

    /// The camera model rejected the scene's intrinsics.
    #[error("camera")]
    Camera(#[from] b2b_calib::CalibError),
}

impl SimError {
    pub(crate) fn io(file: impl Into<PathBuf>, source: std::io::Error) -> Self {
        SimError::Io {
            file: file.into(),
            source,
        }
    }

    pub(crate) fn invalid(what: &'static str, reason: impl Into<String>) -> Self {
        SimError::InvalidParameter {
            what,
            reason: reason.into(),
        }
    }
}

pub(crate) use b2b_errors::chain;

#[cfg(test)]
mod tests {
    use super::*;

    use b2b_errors::assert_cause_once;

    #[test]
    fn every_wrapped_error_prints_its_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "missing for the test");
        assert_cause_once(&SimError::io("/scenes/s.json", io));
        let camera = b2b_calib::CalibError::TooFewCaptures { got: 0, need: 3 };
        let e = SimError::from(camera);
        assert_cause_once(&e);
        assert_eq!(chain(&e), "camera: too few captures: 0, need at least 3");
    }
}
