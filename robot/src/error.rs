//! The crate's one error type.

/// Everything that can go wrong in the robot model. Each variant names what was wrong
/// (which joint, which value, which limit), so a log line is enough to find the fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum RobotError {
    /// No joint configuration inside the limits reaches the requested flange pose.
    #[error(
        "flange pose unreachable: best solution is {position_error_m:.3e} m / {rotation_error_rad:.3e} rad away"
    )]
    Unreachable {
        /// Position distance of the best configuration found, m.
        position_error_m: f64,
        /// Rotation distance of the best configuration found, rad.
        rotation_error_rad: f64,
    },
    /// A parameter that cannot describe anything real (an empty box, a negative limit).
    #[error("{what}: invalid value {value}")]
    InvalidValue {
        /// Which value.
        what: &'static str,
        /// The value as text.
        value: String,
    },
    /// A NaN or infinite value where a finite one is needed.
    #[error("{what}: non-finite value at joint {joint}")]
    NonFinite {
        /// Where it was found.
        what: &'static str,
        /// Joint index (0-based; A1 is 0).
        joint: usize,
    },
    /// A joint position outside the joint limits (shrunk by the margin in force).
    #[error("joint A{} position {value:.4} rad outside [{min:.4}, {max:.4}]", joint + 1)]
    JointLimit {
        /// Joint index (0-based).
        joint: usize,
        /// The position (rad).
        value: f64,
        /// Lower limit (rad).
        min: f64,
        /// Upper limit (rad).
        max: f64,
    },
    /// A step that implies a joint velocity above the limit.
    #[error("joint A{} velocity {velocity:.4} rad/s exceeds limit {limit:.4} rad/s", joint + 1)]
    VelocityLimit {
        /// Joint index (0-based).
        joint: usize,
        /// Implied velocity magnitude (rad/s).
        velocity: f64,
        /// Limit (rad/s).
        limit: f64,
    },
    /// The flange would leave the configured Cartesian workspace box.
    #[error("flange position [{:.4}, {:.4}, {:.4}] m outside the workspace box", position[0], position[1], position[2])]
    Workspace {
        /// Flange position in the robot base frame (m).
        position: [f64; 3],
    },
}
