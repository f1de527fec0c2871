//! Real one-arm recordings made into two-robot problems with an exact answer.
//!
//! A real arm's captures are split into two pseudo robots (even and odd rows);
//! the second one's base is moved by a chosen transform `base1_from_base2`
//! (applied to its `base_from_flange` poses: `base2_from_flange =
//! base1_from_base2⁻¹ · base1_from_flange`). The images and the arm's own errors
//! stay real, and `base1_from_base2` is known exactly. The split is written as
//! a `b2b-dataset/1` folder in a temporary directory (the images copied there,
//! never into the repository), so it goes through the same path as
//! `coordinator calibrate`.

use std::path::Path;

use b2b_calib::Iso3;
use b2b_calib::handeye::{self, HandEyeMethod, RobotWorldMethod};
use b2b_dataset::{Dataset, RobotData};
use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};

use super::shared_dataset;

/// The transform the second pseudo robot's base is moved by: two carts facing
/// each other about 1.3 m apart, the second turned by 160° about the vertical
/// (the bases stay upright, so a symmetric board's labelling between the robots
/// is decided by gravity).
pub fn chosen_base1_from_base2() -> Iso3 {
    Iso3::from_parts(
        Translation3::new(1.2, 0.45, 0.03),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 160f64.to_radians()),
    )
}

/// The second base moved about the first one's vertical axis only (turned
/// 160°, raised 3 cm): the pseudo robot's base frame then stays on the arm's
/// first joint axis, as a real robot's does, so noise shapes tied to the base's
/// z axis keep their meaning for both robots.
pub fn on_axis_base1_from_base2() -> Iso3 {
    Iso3::from_parts(
        Translation3::new(0.0, 0.0, 0.03),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 160f64.to_radians()),
    )
}

/// A split of a real recording: the temporary dataset and its exact answer.
pub struct Split {
    pub dir: tempfile::TempDir,
    pub dataset: Dataset,
    pub base1_from_base2: Iso3,
}

/// How a recording's captures are dealt to the two pseudo robots.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Deal {
    /// Even rows to the first, odd rows to the second: both see the whole
    /// working volume, so what the arm and camera get wrong alike at nearby
    /// configurations is alike in both and cancels in `base1_from_base2`.
    Alternate,
    /// The first half of the recording to the first, the rest to the second:
    /// the halves see the working volume along different parts of the path,
    /// so less of that cancels (closer to two arms, which share nothing).
    Halves,
}

/// Splits the shared dataset `name` (one robot) into two pseudo robots, the
/// second moved by `base1_from_base2`, even and odd rows ([`Deal::Alternate`]).
pub fn split(name: &str, base1_from_base2: &Iso3) -> Split {
    split_by(name, base1_from_base2, Deal::Alternate)
}

/// [`split`] with the captures dealt by `deal`.
pub fn split_by(name: &str, base1_from_base2: &Iso3, deal: Deal) -> Split {
    let src = shared_dataset(name);
    let original = Dataset::load(&src).unwrap();
    assert_eq!(original.robots.len(), 1, "{name}: one robot expected");
    let tmp = tempfile::tempdir().unwrap();
    let mut manifest = original.manifest.clone();
    let robot = manifest.robots[0].clone();
    manifest.robots = ["robot1", "robot2"]
        .iter()
        .map(|id| {
            let mut r = robot.clone();
            r.id = (*id).to_owned();
            r
        })
        .collect();
    manifest.name = format!("{}-split", original.manifest.name);
    let base2_from_base1 = base1_from_base2.inverse();
    let mut robots = vec![
        RobotData {
            id: "robot1".into(),
            captures: vec![],
        },
        RobotData {
            id: "robot2".into(),
            captures: vec![],
        },
    ];
    let n = original.robots[0].captures.len();
    for (i, c) in original.robots[0].captures.iter().enumerate() {
        let k = match deal {
            Deal::Alternate => i % 2,
            Deal::Halves => usize::from(2 * i >= n),
        };
        let mut c = c.clone();
        if k == 1 {
            c.base_from_flange = base2_from_base1 * c.base_from_flange;
        }
        if let Some(image) = &c.image {
            let from = src.join(&robot.id).join(image);
            let to = tmp.path().join(&robots[k].id).join(image);
            std::fs::create_dir_all(to.parent().unwrap()).unwrap();
            std::fs::copy(&from, &to).unwrap();
        }
        robots[k].captures.push(c);
    }
    let ds = Dataset {
        root: tmp.path().to_owned(),
        manifest,
        robots,
        touch_points: None,
        pair_touch_points: Default::default(),
    };
    ds.write(tmp.path()).unwrap();
    write_ground_truth(tmp.path(), base1_from_base2);
    let dataset = Dataset::load(tmp.path()).unwrap();
    Split {
        dir: tmp,
        dataset,
        base1_from_base2: *base1_from_base2,
    }
}

/// `ground_truth.json` with `T_base1_base2` (for a by-hand `coordinator
/// calibrate` on a kept copy; calibration never reads it).
fn write_ground_truth(dir: &Path, t: &Iso3) {
    let q = t.rotation.coords;
    let v = t.translation.vector;
    let json = serde_json::json!({
        "T_base1_base2": {"t": [v.x, v.y, v.z], "q": [q.x, q.y, q.z, q.w]}
    });
    std::fs::write(
        dir.join("ground_truth.json"),
        serde_json::to_string_pretty(&json).unwrap(),
    )
    .unwrap();
}

/// 25 touch locations spread over the working volume: the box the flanges of
/// robot 1's captures span (in base1), sampled by the first 25 points of a
/// Halton sequence (bases 2, 3, 5).
pub fn touch_locations(flanges_in_base1: &[Point3<f64>]) -> Vec<Point3<f64>> {
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    for p in flanges_in_base1 {
        lo = lo.inf(&p.coords);
        hi = hi.sup(&p.coords);
    }
    let halton = |mut i: usize, b: usize| {
        let (mut f, mut r) = (1.0, 0.0);
        while i > 0 {
            f /= b as f64;
            r += f * (i % b) as f64;
            i /= b;
        }
        r
    };
    (1..=25)
        .map(|i| {
            let u = Vector3::new(halton(i, 2), halton(i, 3), halton(i, 5));
            Point3::from(lo + (hi - lo).component_mul(&u))
        })
        .collect()
}

/// Per touch location, |estimate - truth| (each maps base2 points into base1).
pub fn touch_errors(estimate: &Iso3, truth: &Iso3, points: &[Point3<f64>]) -> Vec<f64> {
    let d = estimate * truth.inverse();
    points.iter().map(|p| (d * p - p).norm()).collect()
}

pub fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// The 95th percentile (nearest rank).
pub fn p95(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * 0.95).round() as usize]
}

/// The closed forms a user of OpenCV can pick: five hand-eye methods (then the
/// board's pose in the base by least squares) and two robot-world ones.
pub const CLOSED_FORMS: [&str; 7] = [
    "tsai",
    "park",
    "horaud",
    "andreff",
    "daniilidis",
    "shah",
    "li",
];

/// `base_from_target` of one robot by closed form `k` of [`CLOSED_FORMS`].
pub fn closed_form_board(b: &[Iso3], c: &[Iso3], k: usize) -> Option<Iso3> {
    let methods = [
        HandEyeMethod::Tsai,
        HandEyeMethod::Park,
        HandEyeMethod::Horaud,
        HandEyeMethod::Andreff,
        HandEyeMethod::Daniilidis,
    ];
    if k < 5 {
        let x = handeye::hand_eye(b, c, methods[k]).ok()?;
        handeye::base_from_target_given(&x, b, c).ok()
    } else {
        let m = if k == 5 {
            RobotWorldMethod::Shah
        } else {
            RobotWorldMethod::Li
        };
        handeye::robot_world(b, c, m)
            .ok()
            .map(|rw| rw.base_from_target)
    }
}

/// `base1_from_base2` of closed form `k`, each robot on all its observations.
pub fn closed_form_base1_from_base2(
    robots: &[b2b_pipeline::RobotObservations],
    k: usize,
) -> Option<Iso3> {
    let board = |o: &b2b_pipeline::RobotObservations| {
        let b: Vec<Iso3> = o
            .observations
            .iter()
            .map(|x| x.board.base_from_flange)
            .collect();
        let c: Vec<Iso3> = o
            .observations
            .iter()
            .map(|x| x.camera_from_target)
            .collect();
        closed_form_board(&b, &c, k)
    };
    Some(board(&robots[0])? * board(&robots[1])?.inverse())
}
