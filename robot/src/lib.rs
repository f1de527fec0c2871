//! The robot model, once: what an LBR iiwa 7 R800 or 14 R820 is, where its flange is for
//! given joint angles, which joint angles put the flange somewhere, and which commands
//! are safe to send.
//!
//! Before this crate the simulator, the FRI crate and the planner each held a piece of
//! it (two typings of the joint limits, the wrist geometry written into the planner).
//! Now every user takes the same numbers from here:
//!
//! | module | owns |
//! |---|---|
//! | [`catalogue`] | [`IiwaModel`]: the two arms' standard-DH tables, limits and wrist geometry (shared/facts.md §2) |
//! | [`limits`] | [`JointLimits`]: position, velocity (and a planning acceleration), checks, clamping, scaling |
//! | [`kinematics`] | [`Dh`], [`Arm`]: forward kinematics, the geometric Jacobian, IK with the redundancy resolved towards a posture |
//! | [`safety`] | [`WorkspaceBox`], [`ForwardKinematics`], [`SafetyEnvelope`]: the predicate every command must pass |
//!
//! The crate is pure nalgebra: no I/O, no clock, no OpenCV, zenoh, tokio or rerun, and
//! it depends neither on the simulator nor on kuka-fri (both depend on it; the FRI
//! session applies [`SafetyEnvelope`] through its `SafetyGuard` to every command, the
//! simulator perturbs [`Dh`] tables for its robot error model). `scripts/check-deps`
//! keeps it that way.
//!
//! ```
//! use b2b_robot::{Arm, IiwaModel, IkOptions, SafetyEnvelope, WorkspaceBox};
//! let arm = Arm::new(IiwaModel::Iiwa14R820);
//! let base_from_flange = arm.fk(&Arm::comfortable());
//! let q = arm.ik(&base_from_flange, &Arm::comfortable(), &IkOptions::default())?;
//! let envelope = SafetyEnvelope::new(arm.limits, WorkspaceBox::new([0.0, -1.0, 0.1], [1.0, 1.0, 1.5])?)?
//!     .with_position_margin(2f64.to_radians())?;
//! envelope.check_pose(&q, &arm)?;
//! # Ok::<(), b2b_robot::RobotError>(())
//! ```

pub mod catalogue;
pub mod kinematics;
pub mod limits;
pub mod safety;

mod error;

pub use catalogue::IiwaModel;
pub use error::RobotError;
pub use kinematics::{Arm, Dh, IkOptions, Jacobian, pose_error_norms};
pub use limits::JointLimits;
pub use safety::{ForwardKinematics, SafetyEnvelope, WorkspaceBox};

/// Number of joints of the arms this crate knows (both iiwa models have seven).
pub const N_JOINTS: usize = 7;

/// A joint vector: positions (rad), velocities (rad/s) or accelerations (rad/s²).
pub type Joints = [f64; N_JOINTS];
