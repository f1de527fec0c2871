//! The capture sources' one error type: what stopped a capture or a source,
//! with the facts as fields; an error of another crate passed on as it is
//! prints as it did (`transparent`), and a wrapped cause stays the source.

use std::path::PathBuf;
use std::time::Duration;

/// The capture sources' result.
pub type Result<T, E = LiveError> = std::result::Result<T, E>;

/// What went wrong in a capture source.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    // The errors of the crates the sources use, passed on as they are.
    #[error(transparent)]
    Pipeline(Box<b2b_pipeline::PipelineError>),
    #[error(transparent)]
    Calib(#[from] b2b_calib::CalibError),
    #[error(transparent)]
    Vision(#[from] b2b_vision::VisionError),
    #[error(transparent)]
    Robot(#[from] b2b_robot::RobotError),
    #[error(transparent)]
    Routine(#[from] b2b_routine::RoutineError),
    #[error(transparent)]
    Fri(Box<kuka_fri::FriError>),
    #[error(transparent)]
    Frames(#[from] b2b_frames::FramesError),

    #[error("robot '{robot}' is not in {}", dataset.display())]
    RobotNotInDataset { robot: String, dataset: PathBuf },
    #[error("interrupted")]
    Interrupted,
    /// No measured joints: none within the wait (the cause), or none yet.
    #[error("no joint state from the FRI controller")]
    NoJointState {
        #[source]
        source: Option<Box<kuka_fri::FriError>>,
    },
    #[error("the FRI session is not commanding (is the robot application's overlay running?)")]
    NotCommanding(#[source] Box<kuka_fri::FriError>),
    #[error("the arm did not come to rest within {waited:?}")]
    NotAtRest { waited: Duration },
    #[error("the arm moved during the exposure of frame {frame}")]
    MovedDuringExposure { frame: u64 },
    #[error(
        "frame {frame} is {}x{}, the camera was {}x{} when its intrinsics were estimated",
        size.0,
        size.1,
        estimated.0,
        estimated.1
    )]
    FrameSizeChanged {
        frame: u64,
        size: (u32, u32),
        estimated: (u32, u32),
    },
    #[error("no viewpoint of the board is reachable safely: {dropped:?}")]
    NoSafeViewpoint {
        /// Why each candidate was dropped, and how many were.
        dropped: Vec<(String, usize)>,
    },
    #[error("no plan")]
    NoPlan,
    #[error("the plan has no viewpoint to watch from")]
    NoWatchViewpoint,
    #[error("the routine asked for a viewpoint the plan does not have")]
    UnplannedViewpoint { index: usize },
    /// The capture routine asked for a step that needs a frame before any.
    #[error("{step} without a frame")]
    NoFrame { step: &'static str },
    #[error("no camera intrinsics yet")]
    NoCamera,
    #[error("no camera frame exposed after the arm came to rest within {waited:?} ({service})")]
    NoFrameInTime { waited: Duration, service: String },
    #[error("the {service} service carries {} frames", kind.name())]
    WrongStream {
        /// "colour" or "depth".
        service: &'static str,
        kind: b2b_frames::StreamKind,
    },
    #[error("short {}frame", if *depth { "depth " } else { "" })]
    ShortFrame { depth: bool },
    #[error("depth frame {frame} has no depth unit")]
    NoDepthUnit { frame: u64 },
    #[error(
        "depth frame {frame} is {}x{} but its colour frame is {}x{}: depth must be aligned to colour",
        depth.0,
        depth.1,
        colour.0,
        colour.1
    )]
    DepthNotAligned {
        frame: u64,
        depth: (u32, u32),
        colour: (u32, u32),
    },
    #[error(
        "frame {frame} carries focal lengths {fx} and {fy}: neither positive nor both zero (none given)"
    )]
    BadFocalLengths { frame: u64, fx: f64, fy: f64 },
}

impl From<b2b_pipeline::PipelineError> for LiveError {
    fn from(e: b2b_pipeline::PipelineError) -> Self {
        LiveError::Pipeline(Box::new(e))
    }
}

impl From<kuka_fri::FriError> for LiveError {
    fn from(e: kuka_fri::FriError) -> Self {
        LiveError::Fri(Box::new(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each cause is printed once: a wrapping variant leaves its source out of
    /// its own text.
    #[test]
    fn each_cause_once() {
        let timeout = || kuka_fri::FriError::Timeout {
            what: "joints",
            waited: Duration::from_millis(5),
        };
        for e in [
            LiveError::NotCommanding(Box::new(timeout())),
            LiveError::NoJointState {
                source: Some(Box::new(timeout())),
            },
        ] {
            b2b_errors::assert_cause_once(&e);
        }
    }

    /// Errors that pass through many functions stay small (clippy's
    /// `result_large_err` warns from 128 bytes).
    #[test]
    fn the_error_is_small() {
        assert!(std::mem::size_of::<LiveError>() <= 128);
    }
}
