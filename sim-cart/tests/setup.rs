//! The simulated cart's binary: the setup it derives for an agent, and its errors.

use std::path::{Path, PathBuf};
use std::process::Command;

fn scene(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../datasets")
        .join(name)
        .join("scene.json")
}

fn setup(scene: &Path, robot: &str, dir: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_b2b-sim-cart"))
        .args(["setup", "--robot", robot, "--scene"])
        .arg(scene)
        .arg("--dir")
        .arg(dir)
        .output()
        .unwrap()
}

#[test]
fn the_derived_setup_is_near_the_truth_but_never_it() {
    let dir = tempfile::tempdir().unwrap();
    let out = setup(&scene("sim-checkerboard-2x12"), "robot2", dir.path());
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let answer: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let file = PathBuf::from(answer["setup"].as_str().unwrap());
    assert_eq!(file, dir.path().join("setup-robot2.json"));
    assert_eq!(answer["depth"], serde_json::Value::Bool(false));
    let setup = b2b_services::setup::CellSetup::load(&file).unwrap();
    setup.target_spec().unwrap();
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
    let out = setup(&scene("sim-checkerboard-2x12"), "robot9", dir.path());
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("robot 'robot9' is not in") && stderr.contains("scene.json"),
        "{stderr}"
    );
}
