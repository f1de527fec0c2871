//! The committed datasets under `datasets/` regenerate byte for byte, and generated
//! datasets load with the `b2b-dataset` reader.
//!
//! In the dev profile rendering is slow (the crate is built without optimisation), so
//! the default test renders two captures per robot and checks every other file whole
//! (poses, CSV, JSON: every capture draws its noise from its own stream, so skipping a
//! render changes nothing else). `cargo test -p b2b-sim --release -- --ignored`
//! regenerates everything.

use std::path::{Path, PathBuf};

use b2b_sim::generate::{GenerateOptions, generate_scene};
use b2b_sim::scene::Scene;

/// Each committed dataset and its seed (as in datasets/README.md).
const DATASETS: [(&str, u64); 1] = [("sim-checkerboard-2x12", 1)];

fn datasets_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets")
}

fn files(root: &Path) -> Vec<PathBuf> {
    let mut out = vec![];
    let mut stack = vec![root.to_owned()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p.strip_prefix(root).unwrap().to_owned());
            }
        }
    }
    out.sort();
    out
}

fn regenerate(render_only: Option<Vec<usize>>) {
    for (name, seed) in DATASETS {
        let committed = datasets_dir().join(name);
        let scene_file = committed.join("scene.json");
        let scene = Scene::load(&scene_file).unwrap();
        let tmp = tempfile::tempdir().unwrap();
        let options = GenerateOptions {
            render_only: render_only.clone(),
        };
        generate_scene(&scene, &scene_file, seed, tmp.path(), &options).unwrap();
        let fresh = files(tmp.path());
        assert!(fresh.len() > 5, "{fresh:?}");
        for f in &fresh {
            let a = std::fs::read(tmp.path().join(f)).unwrap();
            let b = std::fs::read(committed.join(f))
                .unwrap_or_else(|e| panic!("{name}/{}: {e}", f.display()));
            assert!(
                a == b,
                "{name}/{} differs from the regenerated file",
                f.display()
            );
        }
        if render_only.is_none() {
            let mut expected = files(&committed);
            expected.retain(|f| f != Path::new("scene.json"));
            assert_eq!(fresh, expected, "{name}: the committed set has other files");
        }
        // What was written is a valid dataset with its truth.
        let loaded = b2b_dataset::Dataset::load(&committed).unwrap();
        assert_eq!(loaded.robots.len(), 2);
        assert!(
            b2b_dataset::load_ground_truth(&committed)
                .unwrap()
                .is_some()
        );
    }
}

#[test]
fn committed_datasets_regenerate_byte_identically_in_part() {
    regenerate(Some(vec![5]));
}

#[test]
#[ignore = "renders every image: run with --release -- --ignored"]
fn committed_datasets_regenerate_byte_identically() {
    regenerate(None);
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
