//! No input makes the loaders panic: random bytes and random CSV lines in every file.

mod common;

use std::fs;
use std::path::PathBuf;

use b2b_dataset::{
    Capture, Dataset, RobotData, load_ground_truth, load_reference, write_ground_truth,
};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use proptest::prelude::*;

use common::Fixture;

/// A cell as it might appear in a hand-edited or corrupt CSV.
fn cell() -> impl Strategy<Value = String> {
    prop_oneof![
        Just(String::new()),
        any::<f64>().prop_map(|v| v.to_string()),
        (-2.0f64..2.0).prop_map(|v| format!("{v:?}")),
        prop::sample::select(vec![
            "NaN",
            "inf",
            "-inf",
            "1e400",
            "-0",
            "0x10",
            "1,5",
            "\"",
            "\"a,b\"",
            " ",
            "images/000.png",
            "images/001.png",
            "depth/000.png",
            "/abs.png",
            "../x.png",
            "images/a.jpg",
            "tx",
            "cqw",
            "image",
            "depth",
            "\u{feff}",
            "é",
            "\r",
            "1e-400",
        ])
        .prop_map(str::to_owned),
        "[ -~]{0,12}",
    ]
}

fn line() -> impl Strategy<Value = String> {
    prop::collection::vec(cell(), 0..20).prop_map(|cells| cells.join(","))
}

fn header() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("image,depth,tx,ty,tz,qx,qy,qz,qw".to_owned()),
        Just("image,depth,tx,ty,tz,qx,qy,qz,qw,ctx,cty,ctz,cqx,cqy,cqz,cqw".to_owned()),
        Just("x1,y1,z1,x2,y2,z2".to_owned()),
        line(),
    ]
}

fn csv_text() -> impl Strategy<Value = String> {
    (
        header(),
        prop::collection::vec(line(), 0..8),
        prop::sample::select(vec!["\n", "\r\n", "\n\n"]),
    )
        .prop_map(|(h, lines, nl)| {
            let mut s = h;
            for l in lines {
                s.push_str(nl);
                s.push_str(&l);
            }
            s
        })
}

fn load_everything(fx: &Fixture) {
    let _ = fx.load();
    let _ = load_ground_truth(fx.root());
    let _ = load_reference(fx.root());
}

proptest! {
    // CI's short campaign; PROPTEST_CASES=100000 runs a long one.
    #![proptest_config(ProptestConfig { cases: cases(200), ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_in_any_file_never_panic(
        bytes in prop::collection::vec(any::<u8>(), 0..400),
        which in 0usize..6,
    ) {
        let fx = Fixture::new();
        let file = ["dataset.json", "robot1/captures.csv", "robot2/captures.csv",
                    "touch_points.csv", "ground_truth.json", "reference.json"][which];
        fs::write(fx.path(file), &bytes).unwrap();
        load_everything(&fx);
    }

    #[test]
    fn random_csv_lines_never_panic(text in csv_text(), which in 0usize..3) {
        let fx = Fixture::new();
        let file = ["robot1/captures.csv", "robot2/captures.csv", "touch_points.csv"][which];
        fs::write(fx.path(file), text).unwrap();
        load_everything(&fx);
    }

    #[test]
    fn random_json_values_never_panic(
        value in prop::sample::select(vec![
            "null", "[]", "{}", "1e999", "-1", "4294967296", "\"DICT_4X4_50\"", "\"\"",
            "{\"kind\": 1}", "{\"kind\": \"charuco\"}", "[1, 2, 3]", "0.0", "true", "\"../x\"",
        ]),
        key in prop::sample::select(vec![
            "\"format\"", "\"target\"", "\"inner_corners\"", "\"square_m\"", "\"robots\"",
            "\"camera\"", "\"dist\"", "\"width\"", "\"id\"", "\"depth_unit_m\"", "\"kind\"",
        ]),
    ) {
        let fx = Fixture::new();
        let text = fs::read_to_string(fx.path("dataset.json")).unwrap();
        // Replace the value after the first occurrence of the key, crudely.
        if let Some(at) = text.find(key) {
            let start = at + key.len() + 1;
            let end = text[start..].find([',', '}', '\n']).map_or(text.len(), |e| start + e);
            let mutated = format!("{} {}{}", &text[..start], value, &text[end..]);
            fs::write(fx.path("dataset.json"), mutated).unwrap();
        }
        load_everything(&fx);
    }

    #[test]
    fn any_valid_pose_round_trips_bit_for_bit(
        t in prop::array::uniform3(-5.0f64..5.0),
        axis_angle in prop::array::uniform3(-4.0f64..4.0),
        flip in any::<bool>(),
    ) {
        let mut rotation = UnitQuaternion::from_scaled_axis(Vector3::from(axis_angle));
        if flip {
            rotation = UnitQuaternion::new_unchecked(-*rotation.quaternion());
        }
        let pose = Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), rotation);
        let fx = Fixture::new();
        let mut ds = fx.load().unwrap();
        ds.robots[1] = RobotData {
            id: "robot2".into(),
            captures: vec![Capture {
                row: 1,
                image: None,
                depth: None,
                base_from_flange: pose,
                camera_from_target: Some(pose.inverse()),
                target: None,
            }],
        };
        let out = tempfile::tempdir().unwrap();
        ds.write(out.path()).unwrap();
        for f in ["robot1/images/000.png", "robot1/images/001.png", "robot1/depth/000.png"] {
            let p: PathBuf = out.path().join(f);
            fs::create_dir_all(p.parent().unwrap()).unwrap();
            fs::write(p, b"x").unwrap();
        }
        let back = Dataset::load(out.path()).unwrap();
        let c = &back.robots[1].captures[0];
        let bits = |i: &Isometry3<f64>| {
            let q = i.rotation.quaternion();
            let v = i.translation.vector;
            [v.x, v.y, v.z, q.i, q.j, q.k, q.w].map(f64::to_bits)
        };
        prop_assert_eq!(bits(&c.base_from_flange), bits(&pose));
        prop_assert_eq!(bits(&c.camera_from_target.unwrap()), bits(&pose.inverse()));

        let gt = b2b_dataset::GroundTruth { base1_from_base2: Some(pose), ..Default::default() };
        write_ground_truth(out.path(), &gt).unwrap();
        let gt_back = load_ground_truth(out.path()).unwrap().unwrap();
        prop_assert_eq!(bits(&gt_back.base1_from_base2.unwrap()), bits(&pose));
    }
}

/// `PROPTEST_CASES` when set, else `default` (CI's short campaign).
fn cases(default: u32) -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}
