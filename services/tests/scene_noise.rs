//! The scene watch's noise as rendered frames give it: one still cart, its
//! camera rendering the textured RGB-D scene again and again (independent
//! sensor and depth noise each time), each frame matched to the first as the
//! watch matches it (near the prediction, RANSAC + Umeyama), and the shift of
//! the scene at its centre fed to the watch's sequential test, through the
//! coordinator's `Watcher` with a result calibrated on the bundled set. Then
//! 40 hours of watching in virtual time, drawing those frames' shifts at
//! random (the same computation outside the `Watcher`, checked to give its
//! decisions).

use std::path::Path;

use std::time::{Duration, Instant};

use b2b_calib::drift::{DriftEvent, DriftOptions, PairWatch, innovation};
use b2b_calib::refine::RefineOptions;
use b2b_calib::{Iso3, pose::pose_distance};
use b2b_dataset::Dataset;
use b2b_pipeline::B2bMethod;
use b2b_pipeline::rgbd::{
    NEAR_GATE, RgbdOptions, fit_camera_pair, load_views, match_views, match_views_near,
};
use b2b_protocol::Pose;
use b2b_protocol::messages::{Capture, Intrinsics};
use b2b_services::watch::{WatchEvent, Watcher};
use nalgebra::{Matrix6, Point3, Vector3, Vector6};
use rand::{Rng, SeedableRng};

/// Frames rendered of the still scene.
const FRAMES: usize = 60;

/// Observations at 5 Hz in 40 hours.
const FORTY_HOURS: usize = 40 * 3600 * 5;

#[test]
fn the_scene_watch_stays_quiet_on_rendered_still_frames() {
    let set = Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-rgbd-boxes-2x5");
    let scene_file = set.join("scene.json");
    let mut scene = b2b_sim::scene::Scene::load(&scene_file).unwrap();
    // One viewpoint rendered FRAMES times, each with its own noise; at half the
    // resolution and one texture sample per pixel (as the watch's process
    // tests render it), so that it takes seconds.
    scene.viewpoints.count = 1;
    scene.lux_levels = vec![352.0; FRAMES];
    scene.lux_per_viewpoint = true;
    scene.texture_samples = Some(1);
    for robot in &mut scene.robots {
        let c = &mut robot.camera;
        c.width /= 2;
        c.height /= 2;
        c.fx /= 2.0;
        c.fy /= 2.0;
        c.cx /= 2.0;
        c.cy /= 2.0;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("still");
    let start = std::time::Instant::now();
    b2b_sim::generate::generate_scene(
        &scene,
        &scene_file,
        3,
        &dir,
        &b2b_sim::generate::GenerateOptions::default(),
    )
    .unwrap();
    eprintln!(
        "rendered {FRAMES} still frames per robot in {:.1} s",
        start.elapsed().as_secs_f64()
    );
    // The result the watch starts from: the bundled set calibrated with its board.
    let result = b2b_pipeline::base_to_base(
        &Dataset::load(&set).unwrap(),
        B2bMethod::Board,
        &RefineOptions::default(),
    )
    .unwrap();
    let ds = Dataset::load(&dir).unwrap();
    let options = RgbdOptions::default();
    let loaded = load_views(&ds, "robot2", &options).unwrap();
    let views = loaded.views;
    assert_eq!(views.len(), FRAMES);
    let flange_from_camera = result.hand_eye["robot2"].to_isometry("robot2").unwrap();

    // The frames through the coordinator's watch, as an agent publishes them.
    let mut watcher =
        Watcher::new(&result, DriftOptions::default(), Duration::from_secs(2)).unwrap();
    let c = &loaded.camera;
    let mut watched_z = Vec::new();
    for (k, view) in views.iter().enumerate() {
        let capture = Capture {
            index: k as u64,
            controller_time_s: None,
            image: None,
            base_from_flange: Pose::from_isometry(&view.base_from_flange),
            camera: Intrinsics {
                width: c.width,
                height: c.height,
                fx: c.fx,
                fy: c.fy,
                cx: c.cx,
                cy: c.cy,
                dist: c.dist[..5].to_vec(),
                estimated: false,
            },
            observation: None,
            rejected: Some("features only".into()),
            base_from_target: None,
            features: Some(view.to_feature_set().unwrap()),
        };
        for event in watcher.observe("robot2", Instant::now(), &capture) {
            match event {
                WatchEvent::Watching { z, .. } => watched_z.push(z),
                WatchEvent::Alarm(a) => panic!("frame {k}: {}", a.message),
                _ => {}
            }
        }
    }
    let matching = watcher.scene_matching("robot2").unwrap();
    assert_eq!(
        (matching.guided, matching.brute_force),
        (FRAMES as u64 - 2, 1)
    );

    // As the watch does: the first frame is the scene's reference.
    let reference = &views[0];
    let base_from_reference = reference.base_from_flange * flange_from_camera;
    let lifted: Vec<Vector3<f64>> = reference
        .points
        .iter()
        .flatten()
        .map(|p| p.coords)
        .collect();
    let centre = Point3::from(lifted.iter().sum::<Vector3<f64>>() / lifted.len() as f64);
    let mut shifts: Vec<Vector6<f64>> = Vec::new();
    let mut inliers = Vec::new();
    for (k, view) in views.iter().enumerate().skip(1) {
        let base_from_camera = view.base_from_flange * flange_from_camera;
        let now_from_reference = base_from_camera.inverse() * base_from_reference;
        // The watch's first comparison is by brute force, the rest near the prediction.
        let m = if k == 1 {
            match_views(reference, view, &options).unwrap()
        } else {
            match_views_near(reference, view, &now_from_reference, NEAR_GATE, &options).unwrap()
        };
        let fit = fit_camera_pair(&m.points1, &m.points2, &options).unwrap();
        inliers.push(fit.inliers);
        let base_from_scene = base_from_camera * fit.camera1_from_camera2.inverse();
        shifts.push(innovation(&base_from_scene, &base_from_reference, &centre));
    }
    let sd = |k: usize| {
        let mean = shifts.iter().map(|d| d[k]).sum::<f64>() / shifts.len() as f64;
        (shifts.iter().map(|d| (d[k] - mean).powi(2)).sum::<f64>() / (shifts.len() - 1) as f64)
            .sqrt()
    };
    let (turn_sd, shift_sd) = (
        Vector3::new(sd(0), sd(1), sd(2)),
        Vector3::new(sd(3), sd(4), sd(5)),
    );
    let worst = shifts
        .iter()
        .map(|d| {
            pose_distance(
                &Iso3::from_parts(
                    nalgebra::Translation3::from(d.fixed_rows::<3>(3).into_owned()),
                    nalgebra::UnitQuaternion::from_scaled_axis(d.fixed_rows::<3>(0).into_owned()),
                ),
                &Iso3::identity(),
            )
        })
        .fold((0.0f64, 0.0f64), |a, b| (a.0.max(b.0), a.1.max(b.1)));
    eprintln!(
        "{} frames against the first: {}-{} inliers; the scene's shift at its centre, sd per axis {:.4} {:.4} {:.4} mm and {:.5} {:.5} {:.5} deg, at most {:.4} mm and {:.5} deg",
        shifts.len(),
        inliers.iter().min().unwrap(),
        inliers.iter().max().unwrap(),
        shift_sd.x * 1e3,
        shift_sd.y * 1e3,
        shift_sd.z * 1e3,
        turn_sd.x.to_degrees(),
        turn_sd.y.to_degrees(),
        turn_sd.z.to_degrees(),
        worst.0 * 1e3,
        worst.1.to_degrees()
    );

    // The frames in their order, through the watch's test: it arms and stays
    // quiet.
    let drift = DriftOptions::default();
    let new_watch = || PairWatch::new(drift, &Matrix6::zeros(), &(base_from_reference * centre));
    let mut watch = new_watch();
    let mut largest_z = 0.0f64;
    let mut replica_z = Vec::new();
    for (k, d) in shifts.iter().enumerate() {
        match watch.update(d) {
            DriftEvent::Watching { z, .. } => {
                largest_z = largest_z.max(z);
                replica_z.push(z);
            }
            DriftEvent::Alarm { z, g, .. } => panic!("frame {k}: alarm (z {z}, CUSUM {g})"),
            _ => {}
        }
    }
    assert!(watch.armed());
    // The computation here is the watch's: the same decisions, frame by frame.
    assert_eq!(replica_z.len(), watched_z.len());
    assert!(!replica_z.is_empty());
    for (a, b) in replica_z.iter().zip(&watched_z) {
        assert!(
            (a - b).abs() <= 1e-9 * a.abs().max(1.0),
            "{replica_z:?} vs {watched_z:?}"
        );
    }
    // 40 hours at 5 Hz in virtual time, each observation one of the rendered
    // frames' shifts drawn at random (re-armed with a fresh baseline after an
    // alarm). What this cannot show: noise beyond what these frames hold
    // (their tails), and a scene that changes.
    let mut rng = rand::rngs::StdRng::seed_from_u64(17);
    let mut watch = new_watch();
    let (mut alarms, mut g_max) = (0, 0.0f64);
    for _ in 0..FORTY_HOURS {
        let d = shifts[rng.random_range(0..shifts.len())];
        match watch.update(&d) {
            DriftEvent::Alarm { .. } => {
                alarms += 1;
                watch = new_watch();
            }
            DriftEvent::Watching { z, g } => {
                largest_z = largest_z.max(z);
                g_max = g_max.max(g);
            }
            _ => {}
        }
    }
    eprintln!(
        "40 h at 5 Hz drawing those shifts: {alarms} false alarms; largest z {largest_z:.1} (CUSUM slack {}), largest CUSUM {g_max:.1} (alarm above {})",
        drift.k, drift.h
    );
    // The issue: at most one false alarm per 8 hours.
    assert!(alarms <= 5, "{alarms} false alarms in 40 h");
    // No frame's distance from the baseline reaches the CUSUM's slack: the
    // CUSUM never starts to climb on these frames (measured: largest z 12.0
    // against 25; their scatter is above the watch's rotation floor of 0.01°
    // per axis, so the baseline's own covariance sets the scale).
    assert!(largest_z < drift.k, "largest z {largest_z}");
    // The README's figures, each within 1.5x of what was measured: largest z
    // 12.0; scatter at most 0.064 mm and 0.024° per axis; at least 370
    // inliers per frame.
    assert!(largest_z < 18.0, "largest z {largest_z}");
    assert!(shift_sd.max() < 0.096e-3, "{shift_sd:?}");
    assert!(turn_sd.max() < 0.036f64.to_radians(), "{turn_sd:?}");
    assert!(*inliers.iter().min().unwrap() * 3 >= 370 * 2, "{inliers:?}");
}
