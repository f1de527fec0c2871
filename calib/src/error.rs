/// Everything that can go wrong in the math core. Each variant says what was
/// wrong with the input, never just that a number came out bad.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum CalibError {
    /// Fewer captures (or points) than the method needs.
    #[error("too few captures: {got}, need at least {need}")]
    TooFewCaptures { got: usize, need: usize },
    /// Inputs that do not belong together (different lengths, ...).
    #[error("inconsistent input: {0}")]
    Inconsistent(String),
    /// The relative rotations all turn about (nearly) one axis: the hand-eye
    /// translation along that axis cannot be observed.
    #[error(
        "rotation axes are (nearly) parallel: the largest angle between motion axes is {max_angle_deg:.2} deg (need >= {min_angle_deg:.1} deg)"
    )]
    ParallelRotationAxes {
        max_angle_deg: f64,
        min_angle_deg: f64,
    },
    /// The robot (nearly) only translated: rotation of the hand-eye is unobservable.
    #[error(
        "motion is (nearly) pure translation: largest relative rotation {max_rotation_deg:.3} deg (need >= {min_rotation_deg:.1} deg)"
    )]
    PureTranslation {
        max_rotation_deg: f64,
        min_rotation_deg: f64,
    },
    /// The rotations are too small for a well-conditioned solution.
    #[error(
        "rotations too small: only {count} relative rotations exceed {min_rotation_deg:.1} deg (need {need})"
    )]
    RotationsTooSmall {
        count: usize,
        need: usize,
        min_rotation_deg: f64,
    },
    /// A number that must be finite is not.
    #[error("non-finite value in {0}")]
    NonFinite(String),
    /// Points that do not span enough dimensions (collinear for Procrustes...).
    #[error("degenerate point set: {0}")]
    DegeneratePoints(String),
    /// RANSAC found no model with enough inliers.
    #[error("RANSAC found no consensus: best model has {best} inliers of {total} (need {need})")]
    NoConsensus {
        best: usize,
        total: usize,
        need: usize,
    },
    /// The optimiser failed or diverged.
    #[error("optimisation failed: {0}")]
    Optimisation(String),
    /// After outlier rejection too little data is left.
    #[error("too few inliers after outlier rejection: {0}")]
    TooFewInliers(String),
    /// A target symmetry that is not a group of labellings of the target's points.
    #[error("invalid target symmetry, element {element}: {reason}")]
    InvalidSymmetry { element: usize, reason: String },
}
