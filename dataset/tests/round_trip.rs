//! Writing a dataset and reading it back gives the same dataset, bit for bit.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

use b2b_dataset::{
    Capture, Dataset, DatasetError, GroundTruth, Intrinsics, Manifest, Reference, RobotData,
    RobotManifest, Target, TouchPair, load_ground_truth, load_reference, write_ground_truth,
    write_reference,
};
use nalgebra::{Isometry3, Point3, Vector3};

fn iso(k: f64) -> Isometry3<f64> {
    Isometry3::new(
        Vector3::new(0.1 + 0.01 * k, -0.2 / (k + 3.0), 1.0 / 3.0 + k * 1e-7),
        Vector3::new(0.3 * k, -1.1 + k / 7.0, 2.0 - k / 11.0),
    )
}

fn targets() -> Vec<Target> {
    vec![
        Target::Checkerboard {
            inner_corners: [9, 6],
            square_m: 0.0236,
        },
        Target::Charuco {
            squares: [5, 7],
            square_m: 0.03,
            marker_m: 0.022,
            dictionary: "DICT_5X5_100".into(),
        },
        Target::ArucoGrid {
            markers: [4, 3],
            marker_m: 0.04,
            separation_m: 0.008,
            dictionary: "DICT_APRILTAG_36h11".into(),
            first_id: 7,
        },
        Target::Multimarker {
            config: "target/multi,marker.dat".into(),
            dictionary: "ARTOOLKIT".into(),
        },
    ]
}

fn dataset(target: Target) -> Dataset {
    let mut robot1 = RobotManifest::new("robot1");
    robot1.camera = Some(Intrinsics {
        width: 1280,
        height: 720,
        fx: 910.123456789,
        fy: 909.87654321,
        cx: 640.5,
        cy: 359.25,
        dist: vec![0.1, -0.25, 1e-4, -2e-5, 0.0125, 0.0, -0.0, 3e-300],
        estimated: false,
    });
    robot1.depth_unit_m = Some(0.001);
    let mut manifest = Manifest::new(
        "round-trip",
        target,
        vec![robot1, RobotManifest::new("robot 2")],
    );
    manifest.source = "tests/round_trip.rs, with \"quotes\" and unicode: µm".into();
    manifest.license = "CC0-1.0".into();
    let captures1 = (0..5)
        .map(|i| Capture {
            row: i + 1,
            image: Some(PathBuf::from(format!("images/{i:03}.png"))),
            depth: (i % 2 == 0).then(|| PathBuf::from(format!("depth/{i:03}.png"))),
            base_from_flange: iso(i as f64),
            camera_from_target: (i == 3).then(|| iso(40.0)),
            target: None,
        })
        .collect();
    let captures2 = (0..4)
        .map(|i| Capture {
            row: i + 1,
            image: (i == 0).then(|| PathBuf::from("images/with, comma.JPG")),
            depth: None,
            base_from_flange: iso(10.0 + i as f64),
            camera_from_target: (i > 0).then(|| iso(20.0 + i as f64)),
            target: None,
        })
        .collect();
    Dataset {
        root: PathBuf::from("unused"),
        manifest,
        robots: vec![
            RobotData {
                id: "robot1".into(),
                captures: captures1,
            },
            RobotData {
                id: "robot 2".into(),
                captures: captures2,
            },
        ],
        touch_points: Some(vec![
            TouchPair {
                location: Some("tip A".into()),
                row: 1,
                tip1_in_base1: Point3::new(0.612, 0.034, 0.081),
                tip2_in_base2: Point3::new(0.402, -0.221, 0.079),
            },
            TouchPair {
                location: Some("tip A".into()),
                row: 2,
                tip1_in_base1: Point3::new(1.0 / 3.0, -0.0, 5e-324),
                tip2_in_base2: Point3::new(-9.999_999_999_999_998, 2.0 / 7.0, 0.1 + 0.2),
            },
        ]),
        pair_touch_points: BTreeMap::new(),
    }
}

/// What the caller does besides `write`: put the images (and target file) in place.
fn create_files(ds: &Dataset, dir: &Path) {
    for robot in &ds.robots {
        for c in &robot.captures {
            for p in c.image.iter().chain(c.depth.iter()) {
                let full = dir.join(&robot.id).join(p);
                fs::create_dir_all(full.parent().unwrap()).unwrap();
                fs::write(full, b"image").unwrap();
            }
        }
    }
    if let Target::Multimarker { config, .. } = &ds.manifest.target {
        let full = dir.join(config);
        fs::create_dir_all(full.parent().unwrap()).unwrap();
        fs::write(full, "1\n").unwrap();
    }
}

fn bits(iso: &Isometry3<f64>) -> [u64; 7] {
    let t = iso.translation.vector;
    let q = iso.rotation.quaternion();
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w].map(f64::to_bits)
}

fn assert_same(a: &Dataset, b: &Dataset) {
    assert_eq!(a.manifest, b.manifest);
    assert_eq!(a.robots, b.robots);
    assert_eq!(a.touch_points, b.touch_points);
    assert_eq!(a.pair_touch_points, b.pair_touch_points);
    for (ra, rb) in a.robots.iter().zip(&b.robots) {
        for (ca, cb) in ra.captures.iter().zip(&rb.captures) {
            assert_eq!(bits(&ca.base_from_flange), bits(&cb.base_from_flange));
            assert_eq!(
                ca.camera_from_target.as_ref().map(bits),
                cb.camera_from_target.as_ref().map(bits)
            );
        }
    }
    for (pa, pb) in a
        .touch_points
        .iter()
        .flatten()
        .zip(b.touch_points.iter().flatten())
    {
        let f = |p: &TouchPair| {
            [p.tip1_in_base1.coords, p.tip2_in_base2.coords].map(|v| v.map(f64::to_bits))
        };
        assert_eq!(f(pa), f(pb));
    }
    let dist_bits = |d: &Dataset| {
        d.manifest.robots[0]
            .camera
            .as_ref()
            .unwrap()
            .dist
            .iter()
            .map(|v| v.to_bits())
            .collect::<Vec<_>>()
    };
    assert_eq!(dist_bits(a), dist_bits(b));
}

fn truth() -> GroundTruth {
    GroundTruth {
        base1_from_base2: Some(iso(100.0)),
        base1_from_base_n: BTreeMap::new(),
        flange_from_camera: BTreeMap::from([
            ("robot1".into(), iso(101.0)),
            ("robot 2".into(), iso(102.0)),
        ]),
        base_from_target: BTreeMap::from([("robot1".into(), iso(103.0))]),
    }
}

#[test]
fn every_target_kind_round_trips_exactly() {
    for target in targets() {
        let ds = dataset(target);
        let tmp = tempfile::tempdir().unwrap();
        ds.write(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
        create_files(&ds, tmp.path());
        let back = Dataset::load(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(back.root, tmp.path());
        assert_same(&ds, &back);

        // Writing what was read gives the same bytes.
        let tmp2 = tempfile::tempdir().unwrap();
        back.write(tmp2.path()).unwrap();
        for f in [
            "dataset.json",
            "touch_points.csv",
            "robot1/captures.csv",
            "robot 2/captures.csv",
        ] {
            assert_eq!(
                fs::read(tmp.path().join(f)).unwrap(),
                fs::read(tmp2.path().join(f)).unwrap(),
                "{f}"
            );
        }
    }
}

#[test]
fn header_has_camera_pose_block_only_when_needed() {
    let ds = dataset(targets().remove(0));
    let tmp = tempfile::tempdir().unwrap();
    ds.write(tmp.path()).unwrap();
    let c1 = fs::read_to_string(tmp.path().join("robot1/captures.csv")).unwrap();
    assert!(c1.starts_with("image,depth,tx,ty,tz,qx,qy,qz,qw,ctx,cty,ctz,cqx,cqy,cqz,cqw\n"));
    let mut only_images = ds.clone();
    for c in &mut only_images.robots[0].captures {
        c.camera_from_target = None;
    }
    only_images.write(tmp.path()).unwrap();
    let c1 = fs::read_to_string(tmp.path().join("robot1/captures.csv")).unwrap();
    assert!(
        c1.starts_with("image,depth,tx,ty,tz,qx,qy,qz,qw\nimages/000.png,depth/000.png,"),
        "{c1}"
    );
}

#[test]
fn ground_truth_and_reference_round_trip_exactly() {
    let ds = dataset(targets().remove(0));
    let tmp = tempfile::tempdir().unwrap();
    ds.write(tmp.path()).unwrap();
    let gt = truth();
    write_ground_truth(tmp.path(), &gt).unwrap();
    let reference = Reference {
        source: "another tool, v1.2".into(),
        base1_from_base2: Some(iso(200.0)),
        base1_from_base_n: BTreeMap::new(),
        flange_from_camera: BTreeMap::from([("robot1".into(), iso(201.0))]),
        base_from_target: BTreeMap::new(),
    };
    write_reference(tmp.path(), &reference).unwrap();
    let gt_back = load_ground_truth(tmp.path()).unwrap().unwrap();
    assert_eq!(gt_back, gt);
    assert_eq!(
        bits(&gt_back.base1_from_base2.unwrap()),
        bits(&gt.base1_from_base2.unwrap())
    );
    for (k, v) in &gt.flange_from_camera {
        assert_eq!(bits(&gt_back.flange_from_camera[k]), bits(v));
    }
    let ref_back = load_reference(tmp.path()).unwrap().unwrap();
    assert_eq!(ref_back, reference);
    // The keys are the format's.
    let text = fs::read_to_string(tmp.path().join("ground_truth.json")).unwrap();
    for key in [
        "\"T_base1_base2\"",
        "\"T_flange_camera\"",
        "\"T_base_target\"",
        "\"t\"",
        "\"q\"",
    ] {
        assert!(text.contains(key), "{key} in {text}");
    }
}

#[test]
fn quaternion_with_negative_w_is_kept_as_given() {
    let mut ds = dataset(targets().remove(0));
    let c = &mut ds.robots[0].captures[0];
    let q = -*c.base_from_flange.rotation.quaternion();
    c.base_from_flange.rotation = nalgebra::UnitQuaternion::new_unchecked(q);
    let tmp = tempfile::tempdir().unwrap();
    ds.write(tmp.path()).unwrap();
    create_files(&ds, tmp.path());
    let back = Dataset::load(tmp.path()).unwrap();
    assert_same(&ds, &back);
}

#[test]
fn writer_refuses_what_the_reader_would_reject_and_writes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let mut ds = dataset(targets().remove(0));
    ds.robots[1].captures[2]
        .base_from_flange
        .translation
        .vector
        .y = f64::NAN;
    let e = ds.write(tmp.path()).unwrap_err();
    assert!(matches!(e, DatasetError::NonFinite { .. }), "{e}");
    let msg = e.to_string();
    assert!(
        msg.contains(
            &tmp.path()
                .join("robot 2/captures.csv")
                .display()
                .to_string()
        ),
        "{msg}"
    );
    assert!(msg.contains("row 3, field `ty`"), "{msg}");
    assert_eq!(
        fs::read_dir(tmp.path()).unwrap().count(),
        0,
        "nothing is written"
    );

    let mut ds = dataset(targets().remove(0));
    ds.robots[0].captures[1]
        .base_from_flange
        .translation
        .vector
        .x = 512.0;
    assert!(matches!(
        ds.write(tmp.path()),
        Err(DatasetError::LooksLikeMillimetres { .. })
    ));

    let mut ds = dataset(targets().remove(0));
    ds.robots[0].captures[4].image = ds.robots[0].captures[0].image.clone();
    assert!(matches!(
        ds.write(tmp.path()),
        Err(DatasetError::DuplicateImage { .. })
    ));

    let mut ds = dataset(targets().remove(0));
    ds.robots[1].captures[1].camera_from_target = None;
    assert!(matches!(
        ds.write(tmp.path()),
        Err(DatasetError::NoObservation { .. })
    ));

    let mut ds = dataset(targets().remove(0));
    ds.manifest.robots[0].depth_unit_m = None;
    assert!(matches!(
        ds.write(tmp.path()),
        Err(DatasetError::DepthWithoutUnit { .. })
    ));

    let mut ds = dataset(targets().remove(0));
    ds.robots.swap(0, 1);
    assert!(matches!(
        ds.write(tmp.path()),
        Err(DatasetError::RobotMismatch { .. })
    ));

    let mut ds = dataset(targets().remove(0));
    ds.manifest.target = Target::Checkerboard {
        inner_corners: [1, 6],
        square_m: 0.02,
    };
    assert!(matches!(
        ds.write(tmp.path()),
        Err(DatasetError::InvalidTarget { .. })
    ));

    let mut gt = truth();
    gt.base_from_target.insert(
        "robot1".into(),
        Isometry3::translation(f64::INFINITY, 0.0, 0.0),
    );
    let e = write_ground_truth(tmp.path(), &gt).unwrap_err();
    assert!(e.to_string().contains("T_base_target.robot1.t[0]"), "{e}");
    assert_eq!(
        fs::read_dir(tmp.path()).unwrap().count(),
        0,
        "nothing is written"
    );
}

#[test]
fn rewriting_without_touch_points_removes_the_stale_file() {
    let tmp = tempfile::tempdir().unwrap();
    let mut ds = dataset(targets().remove(0));
    ds.write(tmp.path()).unwrap();
    assert!(tmp.path().join("touch_points.csv").is_file());
    ds.touch_points = None;
    ds.write(tmp.path()).unwrap();
    assert!(!tmp.path().join("touch_points.csv").exists());
    create_files(&ds, tmp.path());
    assert_eq!(Dataset::load(tmp.path()).unwrap().touch_points, None);
}

/// Three robots (one id with `_` and one with a space): a touch file per further pair
/// and the third robot's base in the truth, all read back bit for bit.
fn three_robots() -> Dataset {
    let mut ds = dataset(targets().remove(0));
    ds.manifest.robots.push(RobotManifest::new("robot_3"));
    ds.robots.push(RobotData {
        id: "robot_3".into(),
        captures: (0..3)
            .map(|i| Capture {
                row: i + 1,
                image: Some(PathBuf::from(format!("images/{i:03}.png"))),
                depth: None,
                base_from_flange: iso(50.0 + i as f64),
                camera_from_target: None,
                target: None,
            })
            .collect(),
    });
    let touch = |k: f64| TouchPair {
        location: None,
        row: 1,
        tip1_in_base1: Point3::new(0.5 + k / 3.0, -0.1, 0.2),
        tip2_in_base2: Point3::new(0.3, 0.1 * k, 1.0 / 7.0),
    };
    ds.pair_touch_points = BTreeMap::from([
        (("robot1".into(), "robot_3".into()), vec![touch(1.0)]),
        (
            ("robot 2".into(), "robot_3".into()),
            vec![
                touch(2.0),
                TouchPair {
                    row: 2,
                    ..touch(3.0)
                },
            ],
        ),
    ]);
    ds
}

#[test]
fn three_robots_with_pair_touch_files_round_trip_exactly() {
    let ds = three_robots();
    let tmp = tempfile::tempdir().unwrap();
    ds.write(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
    create_files(&ds, tmp.path());
    for f in [
        "touch_points.csv",
        "touch_points_robot1_robot_3.csv",
        "touch_points_robot 2_robot_3.csv",
    ] {
        assert!(tmp.path().join(f).is_file(), "{f}");
    }
    let back = Dataset::load(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
    assert_same(&ds, &back);
    for ((a, b), pairs) in &ds.pair_touch_points {
        let read = back.touches_between(a, b).unwrap();
        for (p, q) in pairs.iter().zip(read) {
            assert_eq!(
                p.tip1_in_base1.coords.map(f64::to_bits),
                q.tip1_in_base1.coords.map(f64::to_bits)
            );
            assert_eq!(
                p.tip2_in_base2.coords.map(f64::to_bits),
                q.tip2_in_base2.coords.map(f64::to_bits)
            );
        }
    }
    // The first two robots' touches are touch_points.csv; other orders have none.
    assert_eq!(
        back.touches_between("robot1", "robot 2"),
        ds.touch_points.as_deref()
    );
    assert_eq!(back.touches_between("robot 2", "robot1"), None);
    assert_eq!(back.touches_between("robot_3", "robot1"), None);

    let mut gt = truth();
    gt.flange_from_camera.insert("robot_3".into(), iso(104.0));
    gt.base1_from_base_n.insert(3, iso(105.0));
    write_ground_truth(tmp.path(), &gt).unwrap();
    let text = fs::read_to_string(tmp.path().join("ground_truth.json")).unwrap();
    let b2 = text.find("\"T_base1_base2\"").unwrap();
    let b3 = text.find("\"T_base1_base3\"").unwrap();
    let fc = text.find("\"T_flange_camera\"").unwrap();
    assert!(b2 < b3 && b3 < fc, "{text}");
    let gt_back = load_ground_truth(tmp.path()).unwrap().unwrap();
    assert_eq!(gt_back, gt);
    assert_eq!(
        bits(&gt_back.base1_from_base(3).unwrap()),
        bits(&iso(105.0))
    );
    assert_eq!(gt_back.base1_from_base(1), Some(Isometry3::identity()));
    assert_eq!(
        gt_back.base1_from_base(2).as_ref().map(bits),
        Some(bits(&iso(100.0)))
    );
    let reference = Reference {
        source: "another tool".into(),
        base1_from_base_n: BTreeMap::from([(3, iso(106.0))]),
        ..Reference::default()
    };
    write_reference(tmp.path(), &reference).unwrap();
    assert_eq!(load_reference(tmp.path()).unwrap().unwrap(), reference);

    // Writing what was read gives the same bytes.
    let tmp2 = tempfile::tempdir().unwrap();
    back.write(tmp2.path()).unwrap();
    for f in [
        "dataset.json",
        "touch_points_robot1_robot_3.csv",
        "touch_points_robot 2_robot_3.csv",
        "robot_3/captures.csv",
    ] {
        assert_eq!(
            fs::read(tmp.path().join(f)).unwrap(),
            fs::read(tmp2.path().join(f)).unwrap(),
            "{f}"
        );
    }

    // A pair dropped from the dataset loses its file.
    let mut fewer = ds.clone();
    fewer
        .pair_touch_points
        .remove(&("robot1".to_owned(), "robot_3".to_owned()));
    fewer.write(tmp.path()).unwrap();
    assert!(!tmp.path().join("touch_points_robot1_robot_3.csv").exists());
    assert!(
        tmp.path()
            .join("touch_points_robot 2_robot_3.csv")
            .is_file()
    );
    assert_eq!(
        Dataset::load(tmp.path()).unwrap().pair_touch_points.len(),
        1
    );
}

#[test]
fn writer_refuses_bad_pair_touch_files_and_base_keys() {
    let tmp = tempfile::tempdir().unwrap();
    let mut ds = three_robots();
    ds.pair_touch_points
        .insert(("robot1".into(), "robot9".into()), vec![]);
    let e = ds.write(tmp.path()).unwrap_err();
    assert!(matches!(e, DatasetError::UnknownRobot { .. }), "{e}");
    assert!(
        e.to_string().contains("touch_points_robot1_robot9.csv"),
        "{e}"
    );

    let mut ds = three_robots();
    ds.pair_touch_points
        .insert(("robot1".into(), "robot1".into()), vec![]);
    assert!(matches!(
        ds.write(tmp.path()),
        Err(DatasetError::RobotMismatch { .. })
    ));

    // `robot1` + `2_x` and `robot1_2` + `x` would both be touch_points_robot1_2_x.csv.
    let mut ds = three_robots();
    ds.manifest.robots = ["robot1", "robot1_2", "2_x", "x"]
        .map(RobotManifest::new)
        .to_vec();
    ds.robots = ds
        .manifest
        .robots
        .iter()
        .map(|r| RobotData {
            id: r.id.clone(),
            captures: ds.robots[2].captures.clone(),
        })
        .collect();
    ds.pair_touch_points = BTreeMap::from([(("robot1".into(), "2_x".into()), vec![])]);
    let e = ds.write(tmp.path()).unwrap_err();
    assert!(matches!(e, DatasetError::AmbiguousTouchFile { .. }), "{e}");
    assert!(e.to_string().contains("touch_points_robot1_2_x.csv"), "{e}");
    assert_eq!(
        fs::read_dir(tmp.path()).unwrap().count(),
        0,
        "nothing is written"
    );

    let mut gt = truth();
    gt.base1_from_base_n.insert(2, iso(1.0));
    let e = write_ground_truth(tmp.path(), &gt).unwrap_err();
    assert!(matches!(e, DatasetError::UnknownBaseKey { .. }), "{e}");
    assert!(e.to_string().contains("T_base1_base2"), "{e}");
}
