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
    /// Robot and camera relative motions disagree beyond any noise (sanity checks):
    /// the flange poses and the board poses do not belong together.
    #[error(
        "robot poses and board poses do not belong together: the {what} of the robot's and the \
         camera's relative motions differ by a median {median_diff} ({score:.1} sigma of robot \
         and PnP noise, limit {limit}) over {pairs} pairs; wrong rows, another robot's or \
         another recording's poses, or poses not of a camera on this flange?"
    )]
    PosesDoNotBelong {
        what: &'static str,
        median_diff: String,
        score: f64,
        limit: f64,
        pairs: usize,
    },
    /// The relative motions agree only when the quaternions are read w, x, y, z.
    #[error(
        "quaternions look like w, x, y, z order: the {poses} read as x, y, z, w (the format's \
         order) give robot and camera motions whose pitches differ by a median \
         {:.1} mm ({score:.1} sigma); read as w, x, y, z they agree ({reread_score:.1} sigma). \
         Reorder the quaternion columns to qx, qy, qz, qw",
        median_pitch_diff_m * 1e3
    )]
    QuaternionOrder {
        poses: &'static str,
        score: f64,
        reread_score: f64,
        median_pitch_diff_m: f64,
    },
    /// The camera's lengths are a constant multiple of the robot's.
    #[error(
        "unit/scale mismatch: the camera's motions are {ratio:.4}x the robot's (pitch along \
         the screw axes, {pitch_pairs} pairs; the board is a median {median_board_distance_m:.4} m \
         from the camera): {hint}"
    )]
    ScaleMismatch {
        ratio: f64,
        median_board_distance_m: f64,
        pitch_pairs: usize,
        hint: &'static str,
    },
    /// The board poses put the board at a distance no flange camera sees it from.
    #[error(
        "board poses put the target a median {median_m:.4} m from the camera, outside \
         {min_m}..{max_m} m: are the target's dimensions (square_m, marker_m) in the wrong unit?"
    )]
    BoardDistanceImplausible {
        median_m: f64,
        min_m: f64,
        max_m: f64,
    },
    /// A target symmetry that is not a group of labellings of the target's points.
    #[error("invalid target symmetry, element {element}: {reason}")]
    InvalidSymmetry { element: usize, reason: String },
}
