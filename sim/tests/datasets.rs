//! The committed datasets under `datasets/` regenerate byte for byte, load with the
//! `b2b-dataset` validator, and fit the 25 MB budget.
//!
//! Every dataset is regenerated whole (every image) into a temporary folder, one test
//! per dataset so that they run in parallel; the marker-target sets are in
//! `datasets_markers.rs`. Each binary takes 20-40 s in the dev profile (the simulator is
//! built with opt-level 2 there), depending on the machine's load.

mod common;

use std::path::Path;

use b2b_dataset::Target;
use b2b_sim::generate::{GenerateOptions, generate_scene};
use b2b_sim::scene::Scene;
use common::{datasets_dir, files, regenerate};

/// The budget for everything under `datasets/`.
const MAX_TOTAL_BYTES: u64 = 25_000_000;

#[test]
fn checkerboard_set_regenerates() {
    let ds = regenerate("sim-checkerboard-2x12");
    assert!(matches!(ds.manifest.target, Target::Checkerboard { .. }));
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
