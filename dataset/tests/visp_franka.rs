//! The real ViSP Franka eye-in-hand dataset in `shared/datasets/` loads as its files say.

use std::path::PathBuf;

use b2b_dataset::{Dataset, Target, load_ground_truth, load_reference};
use nalgebra::Vector3;

fn visp_dir() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/datasets/visp-franka-eye-in-hand");
    assert!(
        dir.join("dataset.json").is_file(),
        "the shared example dataset is missing: expected {} (shared/ must sit beside the \
         repository checkout); this test does not skip",
        dir.display()
    );
    dir
}

#[test]
fn loads_eight_captures_with_exact_first_row() {
    let dir = visp_dir();
    let ds = Dataset::load(&dir).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(ds.manifest.name, "visp-franka-eye-in-hand");
    assert_eq!(
        ds.manifest.target,
        Target::Checkerboard {
            inner_corners: [9, 6],
            square_m: 0.0236
        }
    );
    assert_eq!(ds.robots.len(), 1);
    let robot = ds.robot("robot1").expect("robot1");
    assert_eq!(robot.captures.len(), 8);
    assert!(ds.touch_points.is_none());

    // images/001.png,,0.335091,-0.0321497,0.30857,-0.9878004419,0.007764549715,-0.1480074146,0.04778916154
    let first = &robot.captures[0];
    assert_eq!(first.row, 1);
    assert_eq!(
        first.image.as_deref(),
        Some(std::path::Path::new("images/001.png"))
    );
    assert_eq!(first.depth, None);
    assert_eq!(first.camera_from_target, None);
    let t = first.base_from_flange.translation.vector;
    assert_eq!(
        t,
        Vector3::new(0.335091, -0.0321497, 0.30857),
        "translation is read exactly"
    );
    let q = first.base_from_flange.rotation.quaternion();
    let written = [-0.9878004419, 0.007764549715, -0.1480074146, 0.04778916154];
    let read = [q.i, q.j, q.k, q.w];
    for (r, w) in read.iter().zip(written) {
        // Ten printed digits: the quaternion is normalised, which moves it by < 1e-9.
        assert!(
            (r - w).abs() < 1e-9,
            "quaternion {read:?} vs written {written:?}"
        );
    }
    assert!((q.norm() - 1.0).abs() < 1e-15);

    // The same values, straight from the file, so the literals above cannot drift.
    let csv = std::fs::read_to_string(dir.join("robot1/captures.csv")).unwrap();
    let row: Vec<&str> = csv.lines().nth(1).unwrap().split(',').collect();
    assert_eq!(row[0], "images/001.png");
    let nums: Vec<f64> = row[2..].iter().map(|s| s.parse().unwrap()).collect();
    assert_eq!([t.x, t.y, t.z], [nums[0], nums[1], nums[2]]);
    assert_eq!(&nums[3..], &written);

    let last = robot.captures.last().unwrap();
    assert_eq!(last.row, 8);
    assert_eq!(
        ds.image_path("robot1", last),
        Some(ds.root.join("robot1/images/008.png"))
    );
    assert!(ds.image_path("robot1", last).unwrap().is_absolute());

    let camera = ds.manifest.robots[0].camera.as_ref().expect("intrinsics");
    assert_eq!(
        (camera.width, camera.height, camera.fx),
        (640, 480, 607.5931)
    );
    assert_eq!(camera.dist, vec![0.0; 5]);
}

#[test]
fn reference_is_separate_and_exact() {
    let dir = visp_dir();
    assert!(load_ground_truth(&dir).unwrap().is_none());
    let reference = load_reference(&dir).unwrap().expect("reference.json");
    assert!(reference.source.starts_with("ViSP documentation"));
    let x = reference.flange_from_camera["robot1"];
    assert_eq!(
        x.translation.vector,
        Vector3::new(0.05771480338, -0.03392606387, -0.04227445451)
    );
    assert!(reference.base1_from_base2.is_none());
}
