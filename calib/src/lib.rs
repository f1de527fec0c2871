//! The calibration math core.
//!
//! Everything here is a pure function of numbers: no files, no sockets, no OpenCV.
//! Inputs and outputs are nalgebra types named after the frames they connect
//! (`base_from_flange`, `camera_from_target`, `base1_from_base2`), so a chain of
//! compositions reads like the kinematic chain it computes.
//!
//! Layers inside the crate:
//! - [`pose`]: conversions, the left perturbation used by every covariance,
//!   rotation averaging and geodesic distances.
//! - [`camera`]: the pinhole + OpenCV distortion model and its Jacobian.
//! - [`handeye`]: closed-form AX = XB (Tsai–Lenz, Park–Martin, Horaud, Andreff,
//!   Daniilidis) and AX = ZB (Shah, Li) solvers.
//! - [`degeneracy`]: the checks every solver runs first, with reasons.
//! - [`refine`]: the joint reprojection-error refinement of one robot, seeded by a
//!   closed form, with robust loss, MAD outlier rejection and covariance.
//! - [`base_to_base`]: N robots as one problem, every base in the first robot's.
//! - [`select`]: the estimator chosen by cross-validation over captures
//!   (refined noise shapes and closed forms), and the bound scaled to the
//!   folds' scatter.
//! - [`drift`]: the drift watch during the operation (a sequential test of
//!   each observation against the result).
//! - [`causes`]: checks that name a likely cause of wrong input (flange poses
//!   inverted, a change mid-run, a board at another scale).
//! - [`sanity`]: pre-fit checks that flange and board poses belong together
//!   (quaternion order, units, mismatched rows), from invariants of AX = XB.
//! - [`procrustes`]: Umeyama / Procrustes and RANSAC over it.
//! - [`symmetry`]: targets that look the same turned (odd x odd checkerboards),
//!   and choosing each view's labelling from the robot motion.
//! - [`synth`]: synthetic problems with known truth, for tests and benchmarks.
//! - [`metrics`]: ISO 9283 accuracy and repeatability, touch-point verification.

pub mod base_to_base;
pub mod camera;
pub mod causes;
pub mod degeneracy;
pub mod drift;
pub mod estimate;
pub mod handeye;
pub mod metrics;
pub mod pose;
pub mod procrustes;
pub mod refine;
pub mod sanity;
pub mod select;
pub mod symmetry;
pub mod synth;

mod error;
pub use error::CalibError;

/// Shorthand for the isometries used everywhere in this crate.
pub type Iso3 = nalgebra::Isometry3<f64>;
