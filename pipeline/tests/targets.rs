//! Every dataset target kind through the same pipeline: the simulator's committed
//! datasets (ChArUco with occlusions, ArUco grid, single AprilTag, the planar 4x3
//! multimarker and the three-face corner), against their ground truth.

use b2b_calib::pose::pose_distance;
use b2b_calib::refine::RefineOptions;
use b2b_dataset::{Dataset, load_ground_truth};
use b2b_pipeline::{
    B2bMethod, PipelineError, base_to_base, observe_robot, target_from_manifest, target_of,
};

mod common;
use common::*;

/// (folder, default method, least captures used per robot, mm, deg)
const CASES: [(&str, B2bMethod, usize, f64, f64); 5] = [
    ("sim-charuco-occluded-2x10", B2bMethod::Board, 8, 2.0, 0.2),
    ("sim-aruco-grid-2x5", B2bMethod::Board, 5, 2.0, 0.2),
    ("sim-single-marker-2x5", B2bMethod::Multimarker, 5, 3.0, 0.3),
    (
        "sim-multimarker-4x3-2x10",
        B2bMethod::Multimarker,
        9,
        2.0,
        0.2,
    ),
    (
        "sim-multimarker-corner-2x10",
        B2bMethod::Multimarker,
        9,
        2.0,
        0.2,
    ),
];

#[test]
fn every_target_kind_calibrates_base_to_base_within_its_bound() {
    for (name, method, min_used, mm, deg) in CASES {
        let dir = bundled(name);
        let ds = Dataset::load(&dir).unwrap();
        assert_eq!(
            B2bMethod::default_for(&ds.manifest.target),
            method,
            "{name}"
        );
        for robot in ["robot1", "robot2"] {
            let obs = observe_robot(&ds, robot).unwrap();
            let rms: Vec<String> = obs
                .observations
                .iter()
                .map(|o| format!("{:.2}", o.pnp_rms_px))
                .collect();
            eprintln!(
                "{name} {robot}: {} used (PnP RMS px {}), rejected {:?}",
                obs.observations.len(),
                rms.join(" "),
                obs.rejected.iter().map(|r| &r.reason).collect::<Vec<_>>()
            );
            assert!(obs.observations.len() >= min_used, "{name} {robot}");
        }
        let truth = load_ground_truth(&dir)
            .unwrap()
            .unwrap()
            .base1_from_base2
            .unwrap();
        let result = base_to_base(&ds, method, &RefineOptions::default()).unwrap();
        result.validate().unwrap();
        assert_eq!(result.method, method.name());
        let est = result.base1_from_base2.to_isometry("T").unwrap();
        let (dt, da) = pose_distance(&est, &truth);
        eprintln!(
            "{name}: base1_from_base2 {:.3} mm, {:.4} deg from the truth (predicted touch mean {:.3} mm)",
            dt * 1e3,
            da.to_degrees(),
            result.predicted_touch_error_m.mean * 1e3
        );
        assert!(
            dt < mm * 1e-3 && da.to_degrees() < deg,
            "{name}: {dt} m {da} rad"
        );
    }
}

#[test]
fn methods_must_match_the_target() {
    let board = Dataset::load(&bundled("sim-aruco-grid-2x5")).unwrap();
    let err = base_to_base(&board, B2bMethod::Multimarker, &RefineOptions::default()).unwrap_err();
    assert!(
        matches!(err, PipelineError::MethodTargetMismatch { .. }),
        "{err}"
    );
    assert!(err.to_string().contains("--method board"), "{err}");
    let mm = Dataset::load(&bundled("sim-multimarker-4x3-2x10")).unwrap();
    let err = base_to_base(&mm, B2bMethod::Board, &RefineOptions::default()).unwrap_err();
    assert!(err.to_string().contains("--method multimarker"), "{err}");
    // The RGB-D method needs depth images, which this dataset does not have.
    let err = base_to_base(&mm, B2bMethod::Rgbd, &RefineOptions::default()).unwrap_err();
    assert!(err.to_string().contains("depth"), "{err}");
    assert!(err.to_string().contains("dataset.json"), "{err}");
}

#[test]
fn a_missing_or_malformed_multimarker_file_is_named() {
    let src = bundled("sim-multimarker-4x3-2x10");
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    std::fs::create_dir(&dir).unwrap();
    std::fs::copy(src.join("dataset.json"), dir.join("dataset.json")).unwrap();
    for robot in ["robot1", "robot2"] {
        copy_dir(&src.join(robot), &dir.join(robot));
    }
    std::fs::write(dir.join("multimarker.dat"), "12\n00\n40\n1 0 0 0\n").unwrap();
    let ds = Dataset::load(&dir).unwrap();
    let msg = target_of(&ds).unwrap_err().to_string();
    assert!(msg.contains("multimarker.dat:4:"), "{msg}");
    let msg = observe_robot(&ds, "robot1").unwrap_err().to_string();
    assert!(msg.contains("multimarker.dat:4:"), "{msg}");
    std::fs::remove_file(dir.join("multimarker.dat")).unwrap();
    match Dataset::load(&dir) {
        // The dataset validator may refuse a missing file itself.
        Err(e) => assert!(e.to_string().contains("multimarker.dat"), "{e}"),
        Ok(ds) => {
            let msg = target_of(&ds).unwrap_err().to_string();
            assert!(msg.contains("multimarker.dat"), "{msg}");
        }
    }
}

/// The simulator plans its views from its own renderable (`b2b_sim::target::TargetModel`,
/// which links no OpenCV); the target it writes into `dataset.json`, read into the one
/// `b2b_vision::Target`, must have the same centre and view axis, for every committed
/// scene.
#[test]
fn the_simulators_target_agrees_with_the_one_target_model() {
    let datasets = bundled("");
    let mut scenes: Vec<_> = std::fs::read_dir(&datasets)
        .unwrap()
        .filter_map(|e| Some(e.ok()?.path().join("scene.json")))
        .filter(|f| f.is_file())
        .collect();
    scenes.sort();
    assert!(scenes.len() >= 5, "{scenes:?}");
    for file in scenes {
        let scene = b2b_sim::scene::Scene::load(&file).unwrap();
        let (model, _) = scene.target_model(&file).unwrap();
        let dir = tempfile::tempdir().unwrap();
        for (path, text) in &model.files {
            std::fs::write(dir.path().join(path), text).unwrap();
        }
        let target =
            target_from_manifest(&model.manifest, &dir.path().join("dataset.json")).unwrap();
        let name = file.display();
        assert_eq!(target.kind(), model.manifest.kind(), "{name}");
        let centre = (target.centre() - model.centre).norm();
        assert!(centre < 1e-6, "{name}: centres {centre} m apart");
        let axis = (target.view_axis() - model.view_axis).norm();
        assert!(axis < 1e-9, "{name}: view axes {axis} apart");
    }
}
