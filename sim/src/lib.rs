//! The simulator: two iiwa carts, a physically rendered camera on each flange, and the
//! ground truth every accuracy claim of the project is measured against.
//!
//! Without hardware, the simulator is where accuracy is measured, so it is built to be
//! physically honest, and the truth never leaks into what the pipeline sees:
//!
//! - [`kinematics`]: the LBR iiwa 7 R800 / 14 R820 DH models, limits, FK, and IK with
//!   the 7th degree of freedom resolved towards a comfortable posture.
//! - [`robot_error`]: the flange pose the controller *reports* differs from the true
//!   one (encoder noise, repeatability, kinematic parameter errors).
//! - [`texture`]: what is printed on surfaces (procedural checkerboard, bitmaps such as
//!   marker images, random texture for feature matching).
//! - [`render`]: ray casting through the OpenCV distortion model with adaptive
//!   supersampling, thin-lens defocus, illumination, vignetting; [`sensor`] turns
//!   irradiance into 8-bit pixels (exposure, shot and read noise) and true depth into a
//!   RealSense-like 16-bit depth image.
//! - [`scene`] (the JSON scene file) and [`generate`] (viewpoint planning and the
//!   `b2b-dataset/1` writer behind `sim generate`).
//!
//! Everything is deterministic for a seed: the random generator is ChaCha8 seeded
//! explicitly, and rendering is single-threaded.

pub mod generate;
pub mod image_io;
pub mod kinematics;
pub mod render;
pub mod robot_error;
pub mod scene;
pub mod sensor;
pub mod texture;

mod error;
pub use error::SimError;

/// Shorthand for the isometries used everywhere.
pub type Iso3 = nalgebra::Isometry3<f64>;

/// The random generator used everywhere in the simulator.
pub type Rng = rand_chacha::ChaCha8Rng;
