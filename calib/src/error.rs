/// Everything that can go wrong in the math core. Each variant says what was
/// wrong with the input, never just that a number came out bad.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum CalibError {
    /// Fewer captures (or points) than the method needs.
    #[error("too few captures: {got}, need at least {need}")]
    TooFewCaptures { got: usize, need: usize },
    /// A joint problem over robots with fewer robots than it needs.
    #[error("too few robots: {got}, need at least {need}")]
    TooFewRobots { got: usize, need: usize },
    /// Robots (indices; 0 is the reference) that no chain of shared targets
    /// links to the reference robot: a target links the robots that see it.
    #[error(
        "robot(s) {} share no target with robot 0, directly or through other robots: \
         each target links only the robots that see it, so their bases cannot be found in robot 0's",
        cut_off.iter().map(|r| r.to_string()).collect::<Vec<_>>().join(", ")
    )]
    Disconnected { cut_off: Vec<usize> },
    /// A target index of a capture with no target in the problem to match it.
    #[error(
        "capture {capture} of robot {robot} saw target {target}, but the problem has {targets} target(s)"
    )]
    UnknownTarget {
        robot: usize,
        capture: usize,
        target: usize,
        targets: usize,
    },
    /// A target in the problem that no capture saw.
    #[error("target {target} is seen by no capture")]
    UnseenTarget { target: usize },
    /// A one-robot fit given captures of several targets.
    #[error("captures of {targets} targets: a hand-eye fit takes the captures of one target")]
    SeveralTargets { targets: usize },
    /// Fewer touch pairs (or touches of one location) than a check needs.
    #[error("too few touch pairs: {got}, need at least {need}")]
    TooFewTouches { got: usize, need: usize },
    /// Two inputs that need one entry each per capture (or point) differ in length.
    #[error("inconsistent input: {len_a} {what_a} but {len_b} {what_b}")]
    MismatchedLengths {
        len_a: usize,
        what_a: &'static str,
        len_b: usize,
        what_b: &'static str,
    },
    /// A capture whose corner pixels and target points are not paired one to one.
    #[error(
        "inconsistent input: capture {capture}: {pixels} pixels but {target_points} target points"
    )]
    CornerCountMismatch {
        capture: usize,
        pixels: usize,
        target_points: usize,
    },
    /// A 4x4 matrix whose last row is not `0 0 0 1`.
    #[error(
        "last row of a homogeneous matrix must be 0 0 0 1, found {} {} {} {}",
        last_row[0], last_row[1], last_row[2], last_row[3]
    )]
    NotHomogeneous { last_row: [f64; 4] },
    /// A rotation block that is not orthonormal.
    #[error("rotation matrix is not orthonormal (|R^T R - I| = {deviation:.3e})")]
    NotOrthonormal { deviation: f64 },
    /// A rotation block with determinant -1.
    #[error("rotation matrix has determinant -1 (a reflection)")]
    Reflection,
    /// A weight that is negative or not finite.
    #[error("weight {index} is {value}: weights must be finite and >= 0")]
    BadWeight { index: usize, value: f64 },
    /// Weights that are all zero.
    #[error("weights sum to zero")]
    ZeroWeightSum,
    /// More distortion coefficients than the camera model has.
    #[error(
        "{count} distortion coefficients given; only k1 k2 p1 p2 [k3 [k4 k5 k6]] are supported"
    )]
    DistortionTerms { count: usize },
    /// A focal length that is zero or negative.
    #[error("focal lengths must be positive, got fx={fx} fy={fy}")]
    NonPositiveFocalLength { fx: f64, fy: f64 },
    /// A method name that is not one of the methods of its kind.
    #[error("unknown {kind} method '{name}': expected one of {expected}")]
    UnknownMethod {
        /// `hand-eye` or `robot-world`.
        kind: &'static str,
        name: String,
        /// The accepted names, comma-separated.
        expected: String,
    },
    /// A closed form's linear system does not determine its solution.
    #[error(
        "the {what} least-squares system is rank deficient: the motions do not determine the solution"
    )]
    RankDeficient { what: String },
    /// A closed form's linear solution whose rotation block is singular.
    #[error("the {what} linear solution has a singular rotation block (det = {det:.3e})")]
    SingularRotationBlock { what: String, det: f64 },
    /// A closed form whose decomposition broke down on these motions.
    #[error("{method}: {reason}")]
    SolverBreakdown {
        method: &'static str,
        reason: &'static str,
    },
    /// A synthetic test problem that could not be built with this configuration.
    #[error("synthetic problem: {reason}")]
    Synthesis { reason: &'static str },
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

/// Why the solver stopped, in words an operator can act on (the solver's own
/// reasons, such as `User("residuals")`, name its internals).
pub(crate) fn solver_stopped(reason: &levenberg_marquardt::TerminationReason) -> String {
    use levenberg_marquardt::TerminationReason as T;
    match reason {
        T::User(_) => "the reprojection model could not be evaluated at a step of the solver: \
                       a board corner fell behind its camera, or the captures do not determine \
                       every unknown; check that the flange poses and board poses belong \
                       together and that the captures view the board from varied poses"
            .to_owned(),
        T::Numerical(what) => format!(
            "a number became NaN or infinite in the solver ({what}): the captures hold extreme \
             values or the starting estimate is far off"
        ),
        T::NoImprovementPossible(what) => format!(
            "the solver could not improve the fit any further ({what} at machine precision) \
             before it converged"
        ),
        T::NoParameters => "there are no unknowns to fit".to_owned(),
        T::NoResiduals => "there are no corner residuals to fit (no corners left)".to_owned(),
        T::WrongDimensions(what) => {
            format!("internal error: the {what} has the wrong shape for the solver")
        }
        other => format!("the solver stopped without converging ({other:?})"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use levenberg_marquardt::TerminationReason;

    /// Operators saw "optimisation failed: User(\"residuals\")".
    #[test]
    fn solver_failures_are_told_in_words() {
        for reason in [
            TerminationReason::User("residuals"),
            TerminationReason::User("jacobian"),
            TerminationReason::Numerical("jacobian"),
            TerminationReason::NoImprovementPossible("ftol"),
            TerminationReason::NoResiduals,
        ] {
            let e = CalibError::Optimisation(solver_stopped(&reason));
            let text = e.to_string();
            assert!(text.starts_with("optimisation failed: "), "{text}");
            assert!(
                !text.contains("User(") && !text.contains("Numerical("),
                "{text}"
            );
            assert!(text.len() > 50, "{text}");
        }
    }
}
