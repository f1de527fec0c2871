//! Pose-only datasets: rows that give `T_camera_target` instead of an image
//! (dataset-format.md), written from a [`b2b_calib::synth`] problem. They
//! exercise the solvers and the dataset reader without rendering; the pixel
//! noise of the synthetic views is hidden inside each board pose.

use std::collections::BTreeMap;
use std::path::Path;

use b2b_calib::synth::{SynthConfig, TwoTargets, two_targets};
use b2b_dataset::{Capture, Dataset, Manifest, RobotData, RobotManifest, Target};

use crate::SimError;

/// The id of the second target in [`write_two_targets`]'s `targets`.
pub const SIDE_TARGET: &str = "side";

/// [`b2b_calib::synth::two_targets`] for `seed` written to `dir` as a
/// three-robot dataset: robot 1 sees the manifest's `target`, robot 3 only
/// `targets.side`, robot 2 both (with `linked` false, only the first, so that
/// robot 3 is cut off). Both targets are the synthetic 9x6 checkerboard with
/// 25 mm squares. Returns the truth.
pub fn write_two_targets(dir: &Path, seed: u64, linked: bool) -> Result<TwoTargets, SimError> {
    let cfg = SynthConfig::default();
    let two = two_targets(seed, &cfg, linked)?;
    let board = Target::Checkerboard {
        inner_corners: [cfg.board_cols as u32, cfg.board_rows as u32],
        square_m: cfg.square_m,
    };
    let camera = b2b_dataset::intrinsics_of(&cfg.camera, 5);
    let ids = ["robot1", "robot2", "robot3"];
    let mut manifest = Manifest::new(
        "synth-two-targets",
        board.clone(),
        ids.iter()
            .map(|id| RobotManifest {
                camera: Some(camera.clone()),
                ..RobotManifest::new(*id)
            })
            .collect(),
    );
    manifest.source = format!(
        "b2b_sim::pose_only::write_two_targets, seed {seed}: pose-only rows of b2b_calib::synth::two_targets"
    );
    manifest.targets.insert(SIDE_TARGET.to_owned(), board);
    let robots = ids
        .iter()
        .enumerate()
        .map(|(r, id)| RobotData {
            id: (*id).to_owned(),
            captures: two
                .views
                .iter()
                .filter(|(robot, _, _)| *robot == r)
                .flat_map(|(_, t, seen)| {
                    seen.base_from_flange
                        .iter()
                        .zip(&seen.camera_from_target)
                        .map(move |(b, c)| (*t, *b, *c))
                })
                .enumerate()
                .map(|(i, (t, b, c))| Capture {
                    row: i + 1,
                    image: None,
                    depth: None,
                    base_from_flange: b,
                    camera_from_target: Some(c),
                    target: (t == 1).then(|| SIDE_TARGET.to_owned()),
                })
                .collect(),
        })
        .collect();
    Dataset {
        root: dir.to_owned(),
        manifest,
        robots,
        touch_points: None,
        pair_touch_points: BTreeMap::new(),
    }
    .write(dir)?;
    Ok(two)
}
