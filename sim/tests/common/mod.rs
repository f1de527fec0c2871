//! Shared by the dataset regeneration tests (two binaries, so that each stays well
//! under a minute in the dev profile on a loaded CI machine).

#![allow(dead_code)]

use std::path::{Path, PathBuf};

use b2b_sim::generate::{GenerateOptions, generate_scene};
use b2b_sim::scene::Scene;

pub fn datasets_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets")
}

pub fn files(root: &Path) -> Vec<PathBuf> {
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

/// Regenerates `name` (seed 1, as in datasets/README.md) and compares every file;
/// then loads the committed set with the validator and returns it.
pub fn regenerate(name: &str) -> b2b_dataset::Dataset {
    let committed = datasets_dir().join(name);
    let scene_file = committed.join("scene.json");
    let scene = Scene::load(&scene_file).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    generate_scene(
        &scene,
        &scene_file,
        1,
        tmp.path(),
        &GenerateOptions::default(),
    )
    .unwrap();
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
    let mut expected = files(&committed);
    expected.retain(|f| f != Path::new("scene.json"));
    assert_eq!(fresh, expected, "{name}: the committed set has other files");
    // What was written is a valid dataset with its truth, and names itself.
    let loaded = b2b_dataset::Dataset::load(&committed).unwrap();
    assert_eq!(loaded.manifest.name, name);
    let n = loaded.robots.len();
    assert!(n >= 2, "{name}: {n} robots");
    assert!(loaded.robots.iter().all(|r| r.captures.len() >= 5));
    let truth = b2b_dataset::load_ground_truth(&committed).unwrap().unwrap();
    assert!((1..=n).all(|k| truth.base1_from_base(k).is_some()));
    assert_eq!(truth.base1_from_base_n.len(), n - 2);
    assert_eq!(truth.flange_from_camera.len(), n);
    assert_eq!(truth.base_from_target.len(), n);
    assert!(loaded.touch_points.as_ref().is_some_and(|t| t.len() >= 10));
    loaded
}
