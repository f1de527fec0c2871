//! The committed datasets under `datasets/` regenerate byte for byte, load with the
//! `b2b-dataset` validator, and fit the 25 MB budget.
//!
//! Every dataset is regenerated whole (every image) into a temporary folder, one test
//! per dataset so that they run in parallel; the marker-target sets are in
//! `datasets_markers.rs`. Each binary takes 20-40 s in the dev profile (the simulator is
//! built with opt-level 2 there), depending on the machine's load.

mod common;

use std::path::Path;

use b2b_calib::camera::CameraModel;
use b2b_dataset::{Target, load_ground_truth};
use b2b_sim::generate::{GenerateOptions, generate_scene};
use b2b_sim::scene::Scene;
use b2b_vision::{CheckerboardSpec, detect_checkerboard};
use common::{datasets_dir, files, regenerate};

/// The budget for everything under `datasets/`.
const MAX_TOTAL_BYTES: u64 = 25_000_000;

#[test]
fn checkerboard_set_regenerates() {
    let ds = regenerate("sim-checkerboard-2x12");
    assert!(matches!(ds.manifest.target, Target::Checkerboard { .. }));
}

/// Three carts: every pair of robots has its touches, the third base is in the truth,
/// and the truth agrees with the data (touches meet in `base1`, the board is detected
/// where the reported poses and the true hand-eye and board put it).
#[test]
fn three_robot_checkerboard_set_regenerates() {
    let ds = regenerate("sim-checkerboard-3x12");
    assert!(matches!(ds.manifest.target, Target::Checkerboard { .. }));
    let ids: Vec<&str> = ds.robots.iter().map(|r| r.id.as_str()).collect();
    assert_eq!(ids, ["robot1", "robot2", "robot3"]);
    assert!(ds.robots.iter().all(|r| r.captures.len() == 12));
    let pairs: Vec<(&str, &str)> = ds
        .pair_touch_points
        .keys()
        .map(|(a, b)| (a.as_str(), b.as_str()))
        .collect();
    assert_eq!(pairs, [("robot1", "robot3"), ("robot2", "robot3")]);
    for f in [
        "touch_points_robot1_robot3.csv",
        "touch_points_robot2_robot3.csv",
    ] {
        assert!(
            datasets_dir()
                .join("sim-checkerboard-3x12")
                .join(f)
                .is_file()
        );
    }
    let truth = load_ground_truth(&datasets_dir().join("sim-checkerboard-3x12"))
        .unwrap()
        .unwrap();
    let scene = Scene::load(&datasets_dir().join("sim-checkerboard-3x12/scene.json")).unwrap();
    let base1_from_base3 = truth.base1_from_base_n[&3];
    assert_eq!(
        base1_from_base3,
        scene.base1_from_base(2, Path::new("scene.json")).unwrap()
    );
    // About 1 m from each of the other two carts.
    for k in [1, 2] {
        let d = (base1_from_base3.translation.vector
            - truth.base1_from_base(k).unwrap().translation.vector)
            .norm();
        assert!((0.9..1.15).contains(&d), "robot3 to robot{k}: {d} m");
    }

    // Each pair's touches are one physical point: within robot error, tip noise and
    // repeatability (a few tenths of a millimetre) in base1.
    for (a, b) in [(0, 1), (0, 2), (1, 2)] {
        let touches = ds.touches_between(ids[a], ids[b]).unwrap();
        assert_eq!(touches.len(), 25, "{a} {b}");
        let (base1_from_a, base1_from_b) = (
            truth.base1_from_base(a + 1).unwrap(),
            truth.base1_from_base(b + 1).unwrap(),
        );
        for t in touches {
            let gap = (base1_from_a * t.tip1_in_base1 - base1_from_b * t.tip2_in_base2).norm();
            assert!(
                gap < 2e-3,
                "{} + {}: row {}: {gap} m",
                ids[a],
                ids[b],
                t.row
            );
        }
    }

    // Every image shows the whole board where the truth says it is.
    let spec = CheckerboardSpec {
        cols: 9,
        rows: 6,
        square_m: 0.025,
    };
    for (r, robot) in ds.robots.iter().enumerate() {
        let c = ds.manifest.robots[r].camera.clone().unwrap();
        let camera =
            CameraModel::new(c.width, c.height, [c.fx, c.fy, c.cx, c.cy], &c.dist).unwrap();
        let flange_from_camera = truth.flange_from_camera[&robot.id];
        let base_from_target = truth.base_from_target[&robot.id];
        for cap in &robot.captures {
            let image = ds.image_path(&robot.id, cap).unwrap();
            let det = detect_checkerboard(&b2b_vision::load_gray(&image).unwrap(), &spec)
                .unwrap_or_else(|e| panic!("{}: {e}", image.display()));
            assert_eq!(det.pixels.len(), 54, "{}", image.display());
            let camera_from_target =
                (cap.base_from_flange * flange_from_camera).inverse() * base_from_target;
            let worst = det
                .target_points
                .iter()
                .zip(&det.pixels)
                .map(|(p, uv)| (camera.project(&(camera_from_target * p)).unwrap() - uv).norm())
                .fold(0.0, f64::max);
            assert!(worst < 3.0, "{}: {worst} px", image.display());
        }
    }
}

/// A pair of robots that cannot both reach the touch region is named in the error.
#[test]
fn unreachable_touches_name_the_pair() {
    let mut scene = Scene::load(&datasets_dir().join("sim-checkerboard-3x12/scene.json")).unwrap();
    for r in &mut scene.robots {
        r.camera.width = 80;
        r.camera.height = 60;
        r.camera.fx /= 4.0;
        r.camera.fy /= 4.0;
        r.camera.cx /= 4.0;
        r.camera.cy /= 4.0;
    }
    scene.viewpoints.count = 1;
    scene.viewpoints.min_margin_px = 2.0;
    // Between robot1 and robot2 on the far side of the board: 1.2 m from robot3.
    let touch = scene.touch_points.as_mut().unwrap();
    touch.count = 1;
    touch.region_min = [0.48, 0.3, 0.1];
    touch.region_max = [0.52, 0.34, 0.15];
    let tmp = tempfile::tempdir().unwrap();
    let e = generate_scene(
        &scene,
        Path::new("far.json"),
        1,
        tmp.path(),
        &GenerateOptions::default(),
    )
    .unwrap_err();
    assert!(matches!(e, b2b_sim::SimError::PlanningFailed { .. }), "{e}");
    let msg = e.to_string();
    assert!(msg.contains("robot1 and robot3"), "{msg}");
}

#[test]
fn rgbd_set_regenerates_with_depth() {
    let ds = regenerate("sim-rgbd-boxes-2x5");
    for (r, robot) in ds.robots.iter().enumerate() {
        assert_eq!(ds.manifest.robots[r].depth_unit_m, Some(0.001));
        for cap in &robot.captures {
            // Colour images.
            let image = ds.image_path(&robot.id, cap).unwrap();
            let decoder =
                png::Decoder::new(std::io::BufReader::new(std::fs::File::open(image).unwrap()));
            let reader = decoder.read_info().unwrap();
            assert_eq!(reader.info().color_type, png::ColorType::Rgb);
            assert_eq!((reader.info().width, reader.info().height), (424, 240));
            let depth = ds.depth_path(&robot.id, cap).unwrap();
            let decoder =
                png::Decoder::new(std::io::BufReader::new(std::fs::File::open(depth).unwrap()));
            let mut reader = decoder.read_info().unwrap();
            assert_eq!(reader.info().bit_depth, png::BitDepth::Sixteen);
            assert_eq!((reader.info().width, reader.info().height), (424, 240));
            let mut buf = vec![0; reader.output_buffer_size()];
            reader.next_frame(&mut buf).unwrap();
            let mm: Vec<u16> = buf
                .chunks(2)
                .map(|b| u16::from_be_bytes([b[0], b[1]]))
                .collect();
            // Mostly valid depth at a plausible range, with some holes (edges).
            let valid: Vec<u16> = mm.iter().copied().filter(|&v| v > 0).collect();
            let holes = mm.len() - valid.len();
            assert!(valid.len() > mm.len() / 2, "{} valid", valid.len());
            assert!(holes > 100, "{holes} holes");
            assert!(valid.iter().all(|&v| (200..=1500).contains(&v)));
        }
    }
}

#[test]
fn lighting_set_has_each_viewpoint_at_three_levels() {
    let ds = regenerate("sim-lighting-3lux-2x3");
    for robot in &ds.robots {
        assert_eq!(robot.captures.len(), 9);
        for v in robot.captures.chunks(3) {
            assert!(
                v.iter()
                    .all(|c| c.base_from_flange == v[0].base_from_flange)
            );
        }
        // The same view gets brighter from 145 to 243 to 352 lx.
        let mean = |k: usize| {
            let img = b2b_sim::image_io::read_grey(
                &ds.image_path(&robot.id, &robot.captures[k]).unwrap(),
            )
            .unwrap();
            img.data.iter().map(|&v| v as f64).sum::<f64>() / img.data.len() as f64
        };
        let (a, b, c) = (mean(0), mean(1), mean(2));
        assert!(a < b && b < c, "{a} {b} {c}");
        assert!((c / a - 352.0 / 145.0).abs() < 0.6, "{a} {c}");
    }
}

#[test]
fn every_committed_folder_is_tested_and_all_fit_in_25_mb() {
    let mut total = 0;
    let mut names = vec![];
    for e in std::fs::read_dir(datasets_dir()).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            names.push(p.file_name().unwrap().to_string_lossy().into_owned());
        }
    }
    for f in files(&datasets_dir()) {
        total += std::fs::metadata(datasets_dir().join(f)).unwrap().len();
    }
    println!("datasets/: {total} bytes");
    assert!(total <= MAX_TOTAL_BYTES, "datasets/ holds {total} bytes");
    names.sort();
    let tested = [
        "sim-aruco-grid-2x5",
        "sim-charuco-occluded-2x10",
        "sim-checkerboard-2x12",
        "sim-checkerboard-3x12",
        "sim-lighting-3lux-2x3",
        "sim-multimarker-4x3-2x10",
        "sim-multimarker-corner-2x10",
        "sim-rgbd-boxes-2x5",
        "sim-single-marker-2x5",
    ];
    assert_eq!(
        names, tested,
        "a committed dataset has no regeneration test"
    );
    // The README gives each one's regenerate command.
    let readme = std::fs::read_to_string(datasets_dir().join("README.md")).unwrap();
    for name in tested {
        assert!(
            readme.contains(&format!(
                "--scene datasets/{name}/scene.json --seed 1 --out datasets/{name}"
            )),
            "README.md has no command for {name}"
        );
    }
}

/// The RGB-D path: textured boxes, a depth image per capture, occluders.
#[test]
fn boxes_scene_writes_depth_images_that_load() {
    let text =
        std::fs::read_to_string(datasets_dir().join("sim-checkerboard-2x12/scene.json")).unwrap();
    let mut scene: Scene = serde_json::from_str(&text).unwrap();
    for r in &mut scene.robots {
        r.camera.width = 160;
        r.camera.height = 120;
        r.camera.fx /= 4.0;
        r.camera.fy /= 4.0;
        r.camera.cx /= 4.0;
        r.camera.cy /= 4.0;
    }
    scene.viewpoints.count = 2;
    scene.viewpoints.min_margin_px = 3.0;
    scene.touch_points = None;
    scene.boxes = serde_json::from_str(
        r#"[{"pose": {"t": [0.6, 0.15, 0.05], "rpy_deg": [0, 0, 20]}, "size_m": [0.12, 0.08, 0.1], "texture_seed": 1}]"#,
    )
    .unwrap();
    scene.depth = Some(b2b_sim::sensor::DepthModel::default());
    scene.occluders = Some(b2b_sim::scene::OccluderSpec {
        probability: 0.5,
        over_target: false,
        size_m: [0.01, 0.03],
        reflectance: 0.1,
    });
    let tmp = tempfile::tempdir().unwrap();
    let file = Path::new("boxes.json");
    generate_scene(&scene, file, 3, tmp.path(), &GenerateOptions::default()).unwrap();
    let ds = b2b_dataset::Dataset::load(tmp.path()).unwrap();
    let cap = &ds.robots[0].captures[0];
    let depth = ds.depth_path("robot1", cap).unwrap();
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(depth).unwrap()));
    let reader = decoder.read_info().unwrap();
    assert_eq!(reader.info().bit_depth, png::BitDepth::Sixteen);
    assert_eq!(ds.manifest.robots[0].depth_unit_m, Some(0.001));
}

#[test]
fn a_bad_scene_file_names_the_file_and_field() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("bad.json");
    let text = std::fs::read_to_string(datasets_dir().join("sim-checkerboard-2x12/scene.json"))
        .unwrap()
        .replace("\"lux\": 352.0", "\"lux\": -5.0");
    std::fs::write(&file, text).unwrap();
    let e = b2b_sim::generate::generate(&file, 1, &tmp.path().join("out")).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("bad.json") && msg.contains("lighting.lux"),
        "{msg}"
    );
}
