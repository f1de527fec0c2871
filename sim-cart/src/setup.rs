//! The cell setup an agent is given for a simulated cart: derived from the scene
//! with the board position and the mount deliberately off by a setup sheet's and a
//! drawing's error, so the agent never plans with the truth.

use std::path::Path;

use anyhow::Context;
use b2b_protocol::Pose;
use b2b_services::setup::{CellSetup, default_margin, default_speed};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// The setup of `robot` in a simulator scene, with the board position off by
/// 2 cm / 4 deg and the mount by 5 mm / 2 deg (what a setup sheet and a drawing
/// give), so that nothing the agent plans with is the truth. The target's files
/// (a multimarker's ARToolKit file) are written into `dir`, and the setup
/// stands for `dir/setup-ROBOT.json`.
pub fn cell_setup(scene_file: &Path, robot: &str, dir: &Path) -> anyhow::Result<CellSetup> {
    let scene = b2b_sim::scene::Scene::load(scene_file)?;
    let r = scene
        .robots
        .iter()
        .position(|s| s.id == robot)
        .with_context(|| format!("robot '{robot}' is not in {}", scene_file.display()))?;
    let spec = &scene.robots[r];
    let (model, base1_from_target) = scene.target_model(scene_file)?;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    for (name, text) in &model.files {
        let path = dir.join(name);
        std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))?;
    }
    let base1_from_base = scene.base1_from_base(r, scene_file)?;
    let off = |t: [f64; 3], axis: [f64; 3], deg: f64| {
        Isometry3::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_scaled_axis(Vector3::from(axis).normalize() * deg.to_radians()),
        )
    };
    let board = base1_from_base.inverse()
        * base1_from_target
        * off([0.015, -0.012, 0.004], [0.3, 1.0, 0.2], 4.0);
    let mount = spec
        .flange_from_camera
        .to_iso(scene_file, &format!("robots[{r}].flange_from_camera"))?
        * off([0.003, -0.003, 0.002], [1.0, -0.4, 0.3], 2.0);
    let setup = CellSetup {
        model: spec.model,
        target: model.manifest,
        base_from_target_approx: Pose::from_isometry(&board),
        flange_from_camera_approx: Pose::from_isometry(&mount),
        workspace_min: [-0.3, -0.9, 0.12],
        workspace_max: [1.1, 0.9, 1.3],
        joint_margin_rad: default_margin(),
        speed_fraction: default_speed(),
        depth: scene.depth.is_some(),
        source: dir.join(format!("setup-{robot}.json")),
    };
    setup.check()?;
    Ok(setup)
}
