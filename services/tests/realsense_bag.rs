//! librealsense's own code path, without a camera: the simulator renders frames
//! as a D435 delivers them (colour 1280x720 and depth 848x480 from two sensors
//! with an extrinsic between them), librealsense's recorder writes them into a
//! `.bag` (`scripts/realsense-bag.py`), and `camera --realsense --bag` plays it
//! through librealsense into iceoryx2, depth aligned to colour by our alignment
//! (`b2b_frames::align`) with the intrinsics and extrinsic librealsense reads
//! from the recording. The RGB-D method then calibrates from played frames.
//!
//! Needs the `realsense` feature and librealsense (`scripts/setup-realsense`
//! installs it): `cargo test --workspace --features b2b-services/realsense
//! --test realsense_bag`. The gate runs it.
#![cfg(feature = "realsense")]

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use b2b_dataset::Intrinsics;
use b2b_dataset::{Dataset, load_ground_truth};
use b2b_frames::{FrameHeader, FrameSubscriber, Stream, StreamKind, service_name_in};
use b2b_sim::d435::{D435, D435Frame, Timing};
use b2b_sim::generate::{GenerateOptions, generate_scene, scene_geometry};
use b2b_sim::image_io::{write_depth, write_rgb};
use b2b_sim::render::{RenderSettings, SceneGeometry};
use b2b_sim::robot_error::RobotErrorModel;
use b2b_sim::scene::Scene;
use b2b_sim::sensor::{DepthImage, DepthModel, RgbImage};
use b2b_sim::texture::{Checkerboard, NoiseTexture, Texture, Uniform};
use nalgebra::{Isometry3, Point3, Vector3};

const FRAMES: usize = 8;

type Iso3 = Isometry3<f64>;

/// A board on a table with a box standing on it: depth edges of 15 cm.
fn scene() -> SceneGeometry {
    let mut geo = SceneGeometry::default();
    geo.add_quad(
        Iso3::translation(0.0, 0.0, -0.001),
        [-1.0, -1.0],
        [1.0, 1.0],
        Arc::new(Uniform(0.3)),
    );
    geo.add_checkerboard(
        Iso3::translation(-0.2, -0.12, 0.0),
        Checkerboard::new([9, 6], 0.04, 0.02),
    );
    let textures: [Arc<dyn Texture>; 6] = std::array::from_fn(|k| {
        Arc::new(NoiseTexture {
            seed: 7 + k as u64,
            scale_m: 0.04,
            octaves: 4,
            mean: 0.5,
            contrast: 0.35,
        }) as Arc<dyn Texture>
    });
    geo.add_box(
        Iso3::translation(0.05, 0.02, 0.075),
        [0.1, 0.12, 0.15],
        textures,
    );
    geo
}

/// Colour camera poses around the scene, 0.6-0.7 m away.
fn poses(n: usize) -> Vec<Iso3> {
    (0..n)
        .map(|k| {
            let a = k as f64 / n as f64 * std::f64::consts::TAU;
            let eye = Point3::new(0.15 * a.cos(), 0.15 * a.sin(), 0.6 + 0.01 * k as f64);
            b2b_calib::pose::look_at(&eye, &Point3::new(0.0, 0.0, 0.0), &Vector3::y(), 0.0)
                .inverse()
        })
        .collect()
}

/// Frame 1 of every recording is a lead-in, left out of the assertions:
/// librealsense's playback may drop a stream's first frame as it starts (one CI
/// run lost colour frame 1, an earlier run depth frame 1). `poses` follow it.
fn with_lead_in(poses: &[Iso3]) -> Vec<Iso3> {
    std::iter::once(poses[0])
        .chain(poses.iter().copied())
        .collect()
}

/// Records `frames` into `dir/sim.bag` through librealsense's recorder.
fn record(dir: &Path, camera: &D435, frames: &[D435Frame], timing: &Timing) -> PathBuf {
    let raw = dir.join("frames");
    b2b_sim::d435::write_recording(&raw, camera, frames, timing).unwrap();
    let bag = dir.join("sim.bag");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/realsense-bag.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(&raw)
        .arg(&bag)
        .output()
        .expect("python3");
    assert!(
        out.status.success(),
        "realsense-bag.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    bag
}

/// What one stream published, in the publisher's order: for each of the
/// frames the camera says it sent (its summary's `sent`, numbered 1..=sent by
/// [`FrameHeader::sequence`]), the frame number where this test's reader
/// received it, `None` where the reader lost it. A reader that polls a real-time
/// playback on a loaded machine can lose frames (its queue overflows: the
/// subscriber's `dropped`); that is the reader's slowness, not the camera's.
fn published(p: &Playback, stream: Stream) -> Vec<Option<u64>> {
    let (key, received): (&str, Vec<&FrameHeader>) = match stream {
        Stream::Colour => ("colour", p.colour.iter().collect()),
        Stream::Depth => ("depth", p.depth.iter().map(|(h, _)| h).collect()),
    };
    let sent = p.summary[key]["sent"].as_u64().unwrap();
    let mut out = vec![None; sent as usize];
    for h in received {
        let slot = h
            .sequence
            .checked_sub(1)
            .and_then(|i| out.get_mut(i as usize))
            .unwrap_or_else(|| {
                panic!(
                    "{key} frame {} came as number {} of the publisher's, which says it sent {sent}",
                    h.frame_number, h.sequence
                )
            });
        *slot = Some(h.frame_number);
    }
    out
}

/// Asserts that `stream` published the frames numbered `want` after the
/// lead-in (frame 1, which it may have lost: see [`with_lead_in`]), no more
/// and no other, in order. Frames this test's reader lost are known by their
/// place in the publisher's sequence: the camera's count must still be right,
/// and every frame the reader did receive must be in its place. Returns
/// whether the lead-in was published.
fn assert_published(p: &Playback, stream: Stream, want: &[u64]) -> bool {
    let published = published(p, stream);
    let lead_in = published.len() == want.len() + 1;
    let after = &published[usize::from(lead_in)..];
    let as_wanted = (!lead_in || matches!(published[0], None | Some(1)))
        && after.len() == want.len()
        && after
            .iter()
            .zip(want)
            .all(|(got, want)| got.is_none_or(|n| n == *want));
    assert!(
        as_wanted,
        "{stream:?}: the camera published the frames {published:?} (None: one this test's \
         reader lost), not {want:?} after the lead-in\n{}",
        p.stderr
    );
    lead_in
}

/// Colour frames without depth after the lead-in, by the camera's own count
/// (the lead-in may have lost its depth frame, never a later one);
/// `lead_in` says which streams published the lead-in, colour then depth.
fn unpaired_after_lead_in(p: &Playback, lead_in: [bool; 2]) -> u64 {
    let lead_in_unpaired = lead_in[0] && !lead_in[1];
    p.summary["without_depth"].as_u64().unwrap() - u64::from(lead_in_unpaired)
}

fn close(a: f64, b: f64) -> bool {
    // librealsense keeps intrinsics and extrinsics as f32.
    (a - b).abs() <= 1e-6 * b.abs().max(1.0)
}

/// What the camera published from a recording, and what it said.
struct Playback {
    colour: Vec<FrameHeader>,
    /// Each colour frame's pixels (RGB8 rows), in the order of `colour`.
    colour_data: Vec<Vec<u8>>,
    depth: Vec<(FrameHeader, Vec<u16>)>,
    summary: serde_json::Value,
    stderr: String,
}

/// Plays `bag` once through `camera --realsense` and collects every frame.
fn play(bag: &Path) -> Playback {
    b2b_frames::quiet_iceoryx2_logs();
    let prefix = format!(
        "b2b-test/{}/{}/rs",
        std::process::id(),
        b2b_frames::now_ns()
    );
    let mut subs = [Stream::Colour, Stream::Depth]
        .map(|s| FrameSubscriber::new(&service_name_in(&prefix, "rs1", s)).unwrap());
    let mut child = Command::new(env!("CARGO_BIN_EXE_camera"))
        .args([
            "--robot",
            "rs1",
            "--prefix",
            &prefix,
            "--realsense",
            "--once",
            "--bag",
        ])
        .arg(bag)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn camera");
    let (mut colour, mut colour_data) = (Vec::new(), Vec::new());
    let mut depth_bytes: Vec<(FrameHeader, Vec<u8>)> = Vec::new();
    let limit = Duration::from_secs(60);
    let deadline = Instant::now() + limit;
    loop {
        // Looked at before the queues: once the camera has exited and both are
        // empty, every frame it published that is still queued has been read.
        let exited = child.try_wait().unwrap().is_some();
        let mut idle = true;
        if let Some(f) = subs[0].next().unwrap() {
            colour.push(*f.header());
            colour_data.push(f.data().to_vec());
            idle = false;
        }
        if let Some(f) = subs[1].next().unwrap() {
            depth_bytes.push((*f.header(), f.data().to_vec()));
            idle = false;
        }
        if idle {
            if exited {
                break;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        assert!(
            Instant::now() < deadline,
            "the camera did not finish within {limit:?}"
        );
    }
    let depth: Vec<(FrameHeader, Vec<u16>)> = depth_bytes
        .into_iter()
        .map(|(h, b)| {
            let d = b
                .chunks_exact(2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]))
                .collect();
            (h, d)
        })
        .collect();
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "camera failed: {stderr}");
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).expect("summary JSON");
    // Frames the camera sent that this test's reader did not get (it read too
    // slowly): reported, not a failure; the assertions know them by sequence.
    for ((sub, key), received) in subs
        .iter()
        .zip(["colour", "depth"])
        .zip([colour.len(), depth.len()])
    {
        let sent = summary[key]["sent"].as_u64().unwrap();
        if sent > received as u64 {
            eprintln!(
                "this test's reader lost {} of the {sent} {key} frames the camera sent (it read too slowly; {:?})",
                sent - received as u64,
                sub.stats()
            );
        }
    }
    Playback {
        colour,
        colour_data,
        depth,
        summary,
        stderr,
    }
}

/// Every valid aligned pixel's depth is one the true surface takes at most
/// 1 px away (between the least and the greatest true depth of its 3x3
/// neighbourhood, give or take the depth quantisation), edges included.
fn assert_aligned(frame: u64, d: &[u16], truth: &[f32]) {
    let (w, ht) = (1280usize, 720usize);
    let (mut valid, mut off, mut edge_px, mut edge_ok) = (0, 0, 0, 0);
    for v in 1..ht - 1 {
        for u in 1..w - 1 {
            let z = f64::from(d[v * w + u]) * 0.001;
            if z == 0.0 {
                continue;
            }
            valid += 1;
            let t = |du: isize, dv: isize| {
                f64::from(truth[(v as isize + dv) as usize * w + (u as isize + du) as usize])
            };
            let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
            for dv in -1..=1 {
                for du in -1..=1 {
                    let x = t(du, dv);
                    if x > 0.0 {
                        lo = lo.min(x);
                        hi = hi.max(x);
                    }
                }
            }
            let tol = 0.002 + 0.005 * z;
            let within_1px = z >= lo - tol && z <= hi + tol;
            // A true depth edge here: neighbours 5 cm apart.
            if (t(1, 0) - t(-1, 0)).abs() > 0.05 || (t(0, 1) - t(0, -1)).abs() > 0.05 {
                edge_px += 1;
                edge_ok += usize::from(within_1px);
            }
            off += usize::from(!within_1px);
        }
    }
    let filled = valid as f64 / (w * ht) as f64;
    eprintln!(
        "frame {frame}: {:.1}% filled, {off} pixels more than 1 px from their geometry, edge pixels {edge_ok}/{edge_px}",
        100.0 * filled
    );
    assert!(
        filled > 0.95,
        "frame {frame}: only {filled} of the image has depth"
    );
    assert!(edge_px > 500, "frame {frame}: {edge_px} edge pixels");
    assert!(
        off as f64 <= 1e-4 * valid as f64,
        "frame {frame}: {off} of {valid} aligned pixels are more than 1 px from their geometry"
    );
    assert!(
        edge_ok as f64 >= 0.995 * edge_px as f64,
        "frame {frame}: {edge_ok} of {edge_px} edge pixels within 1 px"
    );
}

fn assert_in_order(p: &Playback) {
    for w in p.colour.windows(2) {
        assert!(w[1].frame_number > w[0].frame_number);
        assert!(w[1].timestamp_ns > w[0].timestamp_ns);
    }
    for w in p.depth.windows(2) {
        assert!(w[1].0.frame_number > w[0].0.frame_number);
        assert!(w[1].0.timestamp_ns >= w[0].0.timestamp_ns);
    }
}

#[test]
fn a_recorded_d435_plays_through_librealsense_with_its_intrinsics_and_aligned_depth() {
    let dir = tempfile::tempdir().unwrap();
    let camera = D435::factory();
    let truth = b2b_sim::d435::render(
        &camera,
        &scene(),
        &with_lead_in(&poses(FRAMES)),
        &RenderSettings::ideal(),
    )
    .unwrap();
    // Every third frame of a 30 fps camera kept (100 ms apart), so a loaded
    // machine plays it in real time without losing frames; depth exposed
    // 0.4 ms after colour, within the pairing window.
    let bag = record(
        dir.path(),
        &camera,
        &truth,
        &Timing::regular(FRAMES + 1, 1000.0, 100.0, 0.4),
    );
    let before = b2b_frames::now_ns();
    let p = play(&bag);
    let after = b2b_frames::now_ns();

    // What librealsense read from the recording is what was recorded.
    let rec = &p.summary["recorded"];
    for (key, model) in [("colour", &camera.colour), ("depth", &camera.depth)] {
        let r = &rec[key];
        assert_eq!(r["width"], model.width, "{key}");
        assert_eq!(r["height"], model.height, "{key}");
        for (name, want) in [
            ("fx", model.fx),
            ("fy", model.fy),
            ("cx", model.cx),
            ("cy", model.cy),
        ] {
            let got = r[name].as_f64().unwrap();
            assert!(close(got, want), "{key} {name}: {got} recorded as {want}");
        }
    }
    let e = &rec["depth_from_colour"];
    let r = camera.depth_from_colour.rotation.to_rotation_matrix();
    let t = camera.depth_from_colour.translation.vector;
    for i in 0..9 {
        let got = e["rotation"][i].as_f64().unwrap();
        assert!(close(got, r[(i / 3, i % 3)]), "rotation[{i}] {got}");
    }
    for i in 0..3 {
        let got = e["translation_m"][i].as_f64().unwrap();
        assert!((got - t[i]).abs() < 1e-7, "translation[{i}] {got}");
    }

    // Every frame was published, in order, with the colour stream's
    // intrinsics; depth is aligned to colour and carries its colour frame's
    // number. (The frames received are checked; those this test's reader lost
    // are counted in their places.)
    let all: Vec<u64> = (2..=FRAMES as u64 + 1).collect();
    let lead_in = [Stream::Colour, Stream::Depth].map(|s| assert_published(&p, s, &all));
    assert_eq!(unpaired_after_lead_in(&p, lead_in), 0, "{}", p.stderr);
    assert_in_order(&p);
    assert!(
        !p.colour.is_empty() && !p.depth.is_empty(),
        "this test's reader received no colour or no depth frame: nothing to check"
    );
    for h in &p.colour {
        assert_eq!(h.stream_kind().unwrap(), StreamKind::Rgb8);
        assert_eq!((h.width, h.height), (1280, 720));
        assert!(close(h.fx, camera.colour.fx) && close(h.cy, camera.colour.cy));
    }
    // Timestamps are on the host clock: the recorded ones moved by one offset,
    // the frame that came first stamped when the camera took it, during the
    // play; the others follow it by the recording's 100 ms steps (give or
    // take the depth's 0.4 ms lag, when a depth frame came first).
    let recorded_span_ns = FRAMES as u64 * 100_000_000 + 1_000_000;
    for h in &p.colour {
        assert!(
            (before..=after + recorded_span_ns).contains(&h.timestamp_ns),
            "colour frame {}: stamped {} ns, the play ran from {before} to {after} ns",
            h.frame_number,
            h.timestamp_ns
        );
    }
    for (h, d) in &p.depth {
        assert_eq!(h.stream_kind().unwrap(), StreamKind::Z16);
        assert_eq!((h.width, h.height), (1280, 720));
        assert!(close(h.fx, camera.colour.fx) && close(h.cx, camera.colour.cx));
        assert_eq!(h.depth_from_colour_translation_m, [0.0; 3]);
        assert!(close(h.depth_unit_m, 0.001));
        // Its colour frame, unless this test's reader lost that one.
        if let Some(c) = p.colour.iter().find(|c| c.frame_number == h.frame_number) {
            let gap = h.timestamp_ns.abs_diff(c.timestamp_ns);
            assert!(
                (300_000..500_000).contains(&gap),
                "frame {}: paired {gap} ns apart",
                h.frame_number
            );
        }
        assert_aligned(
            h.frame_number,
            d,
            &truth[h.frame_number as usize - 1].colour_depth_m,
        );
    }
}

#[test]
fn depth_on_its_own_clock_is_paired_by_time_or_not_at_all() {
    let dir = tempfile::tempdir().unwrap();
    let camera = D435::factory();
    let truth = b2b_sim::d435::render(
        &camera,
        &scene(),
        &with_lead_in(&poses(FRAMES)[..6]),
        &RenderSettings::ideal(),
    )
    .unwrap();
    // After the lead-in (frame 1): depth at twice the colour rate in frame 2
    // (a second depth frame 50 ms later), dropped in frame 3, 25 ms late in
    // frame 4 (beyond the 16.7 ms window), 3 ms early in frame 5.
    let mut timing = Timing::regular(7, 1000.0, 100.0, 0.4);
    timing.depth_ms[1].push(timing.colour_ms[1] + 50.0);
    timing.depth_ms[2].clear();
    timing.depth_ms[3] = vec![timing.colour_ms[3] + 25.0];
    timing.depth_ms[4] = vec![timing.colour_ms[4] - 3.0];
    let bag = record(dir.path(), &camera, &truth, &timing);
    let p = play(&bag);
    assert_in_order(&p);
    let lead_in = [
        assert_published(&p, Stream::Colour, &(2..=7).collect::<Vec<_>>()),
        // Depth only where it was paired.
        assert_published(&p, Stream::Depth, &[2, 5, 6, 7]),
    ];
    assert_eq!(unpaired_after_lead_in(&p, lead_in), 2, "{}", p.stderr);
    // Frame 3's nearest depth frame is frame 2's second one.
    assert!(
        p.stderr
            .contains("colour frame 3: the nearest depth frame was exposed 50.0 ms away"),
        "{}",
        p.stderr
    );
    assert!(
        p.stderr
            .contains("colour frame 4: the nearest depth frame was exposed 25.0 ms away"),
        "{}",
        p.stderr
    );
    // Each depth frame is its own capture's: aligned onto that capture's
    // geometry (another capture's depth would not be), within the window (when
    // this test's reader has its colour frame).
    assert!(
        !p.depth.is_empty(),
        "this test's reader received no depth frame: nothing to check"
    );
    for (h, d) in &p.depth {
        if let Some(c) = p.colour.iter().find(|c| c.frame_number == h.frame_number) {
            let gap = h.timestamp_ns.abs_diff(c.timestamp_ns);
            assert!(
                gap < 16_700_000,
                "frame {}: paired {gap} ns apart",
                h.frame_number
            );
        }
        assert_aligned(
            h.frame_number,
            d,
            &truth[h.frame_number as usize - 1].colour_depth_m,
        );
    }
}

#[test]
fn a_missing_recording_is_named() {
    let out = Command::new(env!("CARGO_BIN_EXE_camera"))
        .args([
            "--robot",
            "rs1",
            "--realsense",
            "--bag",
            "/nonexistent/cart.bag",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/nonexistent/cart.bag"), "{err}");
}

/// The RGB-D method on frames that went through librealsense: the bundled RGB-D
/// scene (two arms, boxes on a textured table) seen by a D435 on each flange,
/// with the D4xx's stereo depth error, dropouts and edge losses; each arm's
/// captures recorded into a `.bag`, played by `camera --realsense`, the played
/// colour and aligned depth written into the dataset, and `coordinator
/// calibrate --method rgbd` checked against the scene's truth and its touches.
#[test]
fn the_rgbd_method_calibrates_from_played_back_frames() {
    let scene_file =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-rgbd-boxes-2x5/scene.json");
    let mut scene = Scene::load(&scene_file).unwrap();
    let mut camera = D435::factory();
    camera.depth_model = DepthModel {
        focal_px: camera.depth.fx,
        ..scene.depth.expect("the scene has a depth sensor")
    };
    let c = camera.colour.clone();
    for r in &mut scene.robots {
        r.camera = Intrinsics {
            dist: vec![0.0; 5],
            ..b2b_dataset::intrinsics_of(&c, 5)
        };
        r.reported_camera = None;
        // Exact arms: the flange poses are where the cameras were, so what
        // is left is the camera path's.
        r.error = RobotErrorModel::default();
    }
    let dir = tempfile::tempdir().unwrap();
    let ds_dir = dir.path().join("dataset");
    // Poses, captures.csv, touches and truth; the images come from playback.
    let nothing = GenerateOptions {
        render_only: Some(vec![]),
    };
    let made = generate_scene(&scene, &scene_file, 1, &ds_dir, &nothing).unwrap();
    // The files the captures name (the generator's layout), until playback
    // fills them.
    for (robot, n) in made.robots.iter().zip(&made.captures) {
        for sub in ["images", "depth"] {
            let folder = ds_dir.join(robot).join(sub);
            std::fs::create_dir_all(&folder).unwrap();
            for k in 0..*n {
                std::fs::write(folder.join(format!("{k:03}.png")), b"").unwrap();
            }
        }
    }
    let ds = Dataset::load(&ds_dir).unwrap();
    let truth = load_ground_truth(&ds_dir).unwrap().unwrap();
    let (geometry, _, _) = scene_geometry(&scene, &scene_file).unwrap();
    // The scene's light; ideal optics, and few samples per pixel of the
    // textures (the render's anti-aliasing is not what this test is about,
    // and the textured table fills every pixel).
    let settings = RenderSettings {
        lighting: scene.lighting.clone(),
        edge_samples: 21,
        varying_samples: 3,
        ..RenderSettings::ideal()
    };
    for (r, robot) in ds.robots.iter().enumerate() {
        let world_from_base = truth.base1_from_base(r + 1).unwrap();
        let flange_from_camera = truth.flange_from_camera[&robot.id];
        let colour_from_world: Vec<Iso3> = robot
            .captures
            .iter()
            .map(|cap| (world_from_base * cap.base_from_flange * flange_from_camera).inverse())
            .collect();
        let frames = b2b_sim::d435::render(
            &camera,
            &geometry,
            &with_lead_in(&colour_from_world),
            &settings,
        )
        .unwrap();
        let n = colour_from_world.len() + 1;
        let recording = dir.path().join(&robot.id);
        let bag = record(
            &recording,
            &camera,
            &frames,
            &Timing::regular(n, 1000.0, 100.0, 0.4),
        );
        // Every capture needs its frames. A play may lose one: librealsense's
        // playback on a loaded machine may drop a frame at the start beyond
        // the lead-in (one CI run lost colour frame 2), and this test's reader
        // may read too slowly. The other tests here check what playback
        // delivers; this one plays the recording again, at most five times,
        // until every frame has come in one play or another (a frame's pixels
        // and its aligned depth are the same in every play).
        let mut colour: BTreeMap<u64, Vec<u8>> = BTreeMap::new();
        let mut depth: BTreeMap<u64, (FrameHeader, Vec<u16>)> = BTreeMap::new();
        for attempt in 1..=5 {
            let p = play(&bag);
            for (h, data) in p.colour.iter().zip(p.colour_data) {
                colour.entry(h.frame_number).or_insert(data);
            }
            for (h, d) in p.depth {
                depth.entry(h.frame_number).or_insert((h, d));
            }
            let missing: Vec<u64> = (2..=n as u64)
                .filter(|k| !colour.contains_key(k) || !depth.contains_key(k))
                .collect();
            if missing.is_empty() {
                break;
            }
            eprintln!(
                "{}: after {attempt} plays, frames {missing:?} still lack colour or depth; the camera said: {}",
                robot.id, p.stderr
            );
        }
        for (k, cap) in robot.captures.iter().enumerate() {
            // Frame 1 is the lead-in.
            let number = k as u64 + 2;
            let data = colour.get(&number).unwrap_or_else(|| {
                panic!(
                    "{}: colour frame {number} not received in five plays",
                    robot.id
                )
            });
            let image = RgbImage {
                width: c.width as usize,
                height: c.height as usize,
                data: data.clone(),
            };
            write_rgb(&ds.image_path(&robot.id, cap).unwrap(), &image).unwrap();
            let (h, d) = depth.get(&number).unwrap_or_else(|| {
                panic!(
                    "{}: depth of frame {number} not received in five plays",
                    robot.id
                )
            });
            let depth = DepthImage {
                width: c.width as usize,
                height: c.height as usize,
                data: d.clone(),
                unit_m: h.depth_unit_m,
            };
            write_depth(&ds.depth_path(&robot.id, cap).unwrap(), &depth).unwrap();
        }
    }
    let result_file = dir.path().join("RESULT.json");
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["calibrate", "--method", "rgbd", "--dataset"])
        .arg(&ds_dir)
        .arg("--out")
        .arg(&result_file)
        .arg("--state-dir")
        .arg(common::state_beside(&result_file))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "calibrate failed: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    let result: b2b_protocol::CalibrationResult =
        serde_json::from_str(&std::fs::read_to_string(&result_file).unwrap()).unwrap();
    // The played depth is to scale: no depth-scale finding (the check's own
    // limit, `depth_checks::SCALE_SYSTEMATIC_SIGMA`, holds its 0.34% reading).
    assert!(result.findings.is_empty(), "{:#?}", result.findings);
    let (dt, da) = common::truth_error(&ds_dir, &result);
    let (printout, v) = common::verify(
        &result_file,
        &ds_dir.join("touch_points.csv"),
        &["--tip-sigma-mm", "0.2"],
    );
    eprintln!("{printout}");
    let mean_mm = v["touch_mean_mm"].as_f64().unwrap();
    let inside = v["within_predicted_p95"].as_f64().unwrap();
    eprintln!(
        "rgbd from played-back D435 frames: {:.3} mm / {:.4} deg from the truth; touch mean {mean_mm:.2} mm, {:.0}% inside the predicted 95% bound",
        dt * 1e3,
        da.to_degrees(),
        inside * 100.0
    );
    // docs/realsense.md: 0.13 mm / 0.019° from the truth, touch mean 0.47 mm with the
    // pointers' 0.2 mm tip noise, 96% of touches inside the bound (the run is
    // deterministic); asserted within 1.5x.
    assert!(
        dt < 0.195e-3 && da.to_degrees() < 0.028,
        "{:.3} mm, {:.4} deg",
        dt * 1e3,
        da.to_degrees()
    );
    assert!(mean_mm < 0.705, "touch mean {mean_mm} mm");
    assert!(inside >= 0.9, "only {:.0}% inside", inside * 100.0);
}
