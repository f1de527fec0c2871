//! The capture-source port: what a source delivers and what it is told.

use std::sync::atomic::AtomicBool;

use b2b_pipeline::Observation;
use b2b_protocol::messages::HandEyeUpdate;

use crate::Result;

/// What the agent knows so far, handed to the source before each capture (the
/// automatic routine stops when the hand-eye is good enough).
#[derive(Debug, Clone, Default)]
pub struct Progress {
    pub good: usize,
    pub rejected: usize,
    /// The newest hand-eye estimate and its covariance.
    pub hand_eye: Option<HandEyeUpdate>,
    /// Flange poses of the good captures so far.
    pub good_poses: Vec<nalgebra::Isometry3<f64>>,
    /// `base_from_target` of each good capture with the hand-eye of its time.
    pub base_from_target: Vec<nalgebra::Isometry3<f64>>,
}

/// One capture as a source delivers it.
#[derive(Debug, Clone)]
pub struct SourceCapture {
    /// Stable index (a replay's row order; a live source's capture count).
    pub index: u64,
    pub image: Option<String>,
    pub base_from_flange: nalgebra::Isometry3<f64>,
    pub controller_time_s: Option<f64>,
    pub camera: b2b_calib::camera::CameraModel,
    /// The camera gave no intrinsics: `camera` is the agent's provisional
    /// estimate ([`b2b_protocol::messages::Intrinsics::estimated`]).
    pub intrinsics_estimated: bool,
    pub observed: Result<Observation, b2b_protocol::RejectedCapture>,
    /// The grey image, when the source has it in memory (for the recording).
    pub pixels: Option<Vec<u8>>,
    /// Local features lifted with the aligned depth (RGB-D method), when the
    /// source has depth and was asked for them.
    pub features: Option<b2b_protocol::messages::FeatureSet>,
    /// The centre of the whole target in its frame (all its model points).
    pub target_centre: nalgebra::Point3<f64>,
    /// Which of the dataset's further `targets` the capture is of (`None`:
    /// the main target; live sources observe that one).
    pub target: Option<String>,
}

/// Where captures come from: a dataset replay, the simulated cart, or a real arm.
/// Everything after the source is the same code.
pub trait CaptureSource {
    /// One line for the status message.
    fn describe(&self) -> String;
    /// How many captures to expect, when known (for the progress bar).
    fn expected(&self) -> Option<u64>;
    /// The next capture, or `None` when the source is done.
    fn next(&mut self, progress: &Progress, stop: &AtomicBool) -> Result<Option<SourceCapture>>;
    /// A closing line (timings, plan coverage), printed when the run ends.
    fn summary(&self) -> Option<String> {
        None
    }
    /// The agent's newest estimate of a camera that gave no intrinsics, for the
    /// source's next detections (sources whose camera has intrinsics ignore it).
    fn use_camera(&mut self, _camera: &b2b_calib::camera::CameraModel) {}
}
