//! The dataset replay: a `b2b-dataset/1` folder's captures of one robot, as a
//! capture source (the same code after it as the live source).

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use b2b_pipeline::rgbd::{RgbdOptions, capture_view};
use b2b_pipeline::{RobotSetup, error_chain, observe_capture};
use b2b_protocol::messages::FeatureSet;

use crate::source::{CaptureSource, Progress, SourceCapture};
use crate::{LiveError, Result};

/// A `b2b-dataset/1` folder's captures of one robot.
#[derive(Debug)]
pub struct ReplaySource {
    ds: b2b_dataset::Dataset,
    setup: RobotSetup,
    data: b2b_dataset::RobotData,
    next: usize,
    dataset: PathBuf,
    /// Features for the RGB-D method (only for captures with depth).
    features: Option<RgbdOptions>,
}

impl ReplaySource {
    /// Opens `dataset` for `robot`.
    pub fn open(dataset: &Path, robot: &str) -> Result<Self> {
        let ds = b2b_pipeline::load_dataset(dataset)?;
        let setup = RobotSetup::from_dataset(&ds, robot)?;
        let data = ds
            .robot(robot)
            .ok_or_else(|| LiveError::RobotNotInDataset {
                robot: robot.to_owned(),
                dataset: dataset.to_owned(),
            })?
            .clone();
        Ok(ReplaySource {
            ds,
            setup,
            data,
            next: 0,
            dataset: dataset.to_owned(),
            features: None,
        })
    }

    /// Also detect features of this kind and lift them with the capture's depth
    /// image (captures without depth publish none).
    pub fn with_features(mut self, kind: b2b_vision::features::FeatureKind) -> Self {
        self.features = Some(RgbdOptions::with_kind(kind));
        self
    }

    /// The capture's feature set, or why there is none (logged, not fatal: the
    /// board observation still goes out, and the coordinator's RGB-D method
    /// reports the capture as having no features).
    fn feature_set(
        &self,
        cap: &b2b_dataset::Capture,
        options: &RgbdOptions,
    ) -> Result<Option<FeatureSet>, String> {
        let robot = &self.setup.robot;
        let Some(unit) = self.ds.robot_manifest(robot).and_then(|m| m.depth_unit_m) else {
            return Ok(None);
        };
        if self.ds.depth_path(robot, cap).is_none() {
            return Ok(None);
        }
        let view = capture_view(&self.ds, robot, &self.setup.camera, unit, cap, options)
            .map_err(|e| error_chain(&e))?;
        view.to_feature_set().map(Some).map_err(|e| error_chain(&e))
    }
}

impl CaptureSource for ReplaySource {
    fn describe(&self) -> String {
        format!("replaying {}", self.dataset.display())
    }

    fn expected(&self) -> Option<u64> {
        Some(self.data.captures.len() as u64)
    }

    fn next(&mut self, _progress: &Progress, _stop: &AtomicBool) -> Result<Option<SourceCapture>> {
        let Some(cap) = self.data.captures.get(self.next) else {
            return Ok(None);
        };
        let index = self.next as u64;
        self.next += 1;
        let features = match &self.features {
            Some(options) => self.feature_set(cap, options).unwrap_or_else(|reason| {
                tracing::warn!("row {}: no features: {reason}", cap.row);
                None
            }),
            None => None,
        };
        Ok(Some(SourceCapture {
            index,
            image: cap.image.as_ref().map(|p| p.display().to_string()),
            base_from_flange: cap.base_from_flange,
            controller_time_s: None,
            camera: self.setup.camera.clone(),
            intrinsics_estimated: false,
            observed: observe_capture(&self.ds, &self.setup, cap),
            pixels: None,
            features,
            target_centre: self.setup.target_at(self.ds.target_index(cap)).0.centre(),
            target: cap.target.clone(),
        }))
    }
}
