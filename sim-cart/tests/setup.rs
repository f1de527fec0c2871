//! The simulated cart's binary: the setup it derives for an agent, and its errors.

use std::path::{Path, PathBuf};

use b2b_services::sim_cart::derive_setup;

fn scene(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../datasets")
        .join(name)
        .join("scene.json")
}

fn setup(scene: &Path, robot: &str, dir: &Path) -> anyhow::Result<PathBuf> {
    Ok(derive_setup(
        Path::new(env!("CARGO_BIN_EXE_b2b-sim-cart")),
        scene,
        robot,
        dir,
    )?)
}

#[test]
fn the_derived_setup_is_near_the_truth_but_never_it() {
    let dir = tempfile::tempdir().unwrap();
    let file = setup(&scene("sim-checkerboard-2x12"), "robot2", dir.path()).unwrap();
    assert_eq!(file, dir.path().join("setup-robot2.json"));
    let setup = b2b_services::setup::CellSetup::load(&file).unwrap();
    // This scene renders no depth, and the setup says so.
    assert!(!setup.depth);
    setup.read_target().unwrap();
    setup.guard().unwrap();
    // The board is off by a setup sheet's error: about 2 cm and 4°, not zero.
    let s = b2b_sim::scene::Scene::load(&scene("sim-checkerboard-2x12")).unwrap();
    let (_, base1_from_target) = s.target_model(&scene("sim-checkerboard-2x12")).unwrap();
    let base1_from_base2 = s
        .base1_from_base2
        .to_iso(Path::new("scene"), "base1_from_base2")
        .unwrap();
    let truth = base1_from_base2.inverse() * base1_from_target;
    let approx = setup.base_from_target_approx.to_isometry("board").unwrap();
    let d = truth.inverse() * approx;
    let (t, r) = (d.translation.vector.norm(), d.rotation.angle().to_degrees());
    assert!((0.01..0.03).contains(&t), "board off by {t} m");
    assert!((2.0..6.0).contains(&r), "board off by {r} deg");
}

#[test]
fn a_robot_not_in_the_scene_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let err = setup(&scene("sim-checkerboard-2x12"), "robot9", dir.path()).unwrap_err();
    let message = format!("{err:#}");
    assert!(
        message.contains("robot 'robot9' is not in") && message.contains("scene.json"),
        "{message}"
    );
}
