//! The pre-fit consistency checks and the image-size checks on real and rendered
//! data: clean data passes them, and a copy of a rendered data set with one thing
//! broken is refused with the likely cause named.

use std::path::{Path, PathBuf};
use std::time::Instant;

use b2b_calib::CalibError;
use b2b_dataset::Dataset;
use b2b_pipeline::{PipelineError, observe_robot, screen_observations};
use b2b_vision::VisionError;

mod common;
use common::*;

/// A copy of the rendered two-robot checkerboard data set in a temporary folder.
fn sim_copy() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    copy_dir(&bundled("sim-checkerboard-2x12"), &dir);
    (tmp, dir)
}

/// Rewrites a captures.csv so that its qx, qy, qz, qw columns hold w, x, y, z.
pub fn rewrite_wxyz(captures: &Path) {
    let text = std::fs::read_to_string(captures).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| header.iter().position(|h| *h == n).unwrap();
    let (qx, qy, qz, qw) = (col("qx"), col("qy"), col("qz"), col("qw"));
    let mut out = header.join(",") + "\n";
    for line in lines {
        let f: Vec<&str> = line.split(',').collect();
        let mut g = f.clone();
        g[qx] = f[qw];
        g[qy] = f[qx];
        g[qz] = f[qy];
        g[qw] = f[qz];
        out += &(g.join(",") + "\n");
    }
    std::fs::write(captures, out).unwrap();
}

/// Multiplies the checkerboard's square size in dataset.json by 1000.
pub fn square_size_times_1000(dir: &Path) {
    let p = dir.join("dataset.json");
    let text = std::fs::read_to_string(&p).unwrap();
    assert!(text.contains("\"square_m\": 0.025"), "{text}");
    std::fs::write(
        &p,
        text.replace("\"square_m\": 0.025", "\"square_m\": 25.0"),
    )
    .unwrap();
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for b in bytes {
        c ^= u32::from(*b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

/// A small file with a valid PNG signature and IHDR claiming `width` x `height`
/// 8-bit grey pixels (and a token IDAT and IEND).
pub fn fake_png(path: &Path, width: u32, height: u32) {
    let chunk = |kind: &[u8; 4], data: &[u8]| {
        let mut c = (data.len() as u32).to_be_bytes().to_vec();
        let mut body = kind.to_vec();
        body.extend_from_slice(data);
        c.extend_from_slice(&body);
        c.extend_from_slice(&crc32(&body).to_be_bytes());
        c
    };
    let mut ihdr = width.to_be_bytes().to_vec();
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    let mut png = vec![0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];
    png.extend(chunk(b"IHDR", &ihdr));
    // zlib stream of a few zero rows (the rest missing).
    png.extend(chunk(
        b"IDAT",
        &[0x78, 0x9C, 0x63, 0x00, 0x00, 0x00, 0x01, 0x00, 0x01],
    ));
    png.extend(chunk(b"IEND", &[]));
    std::fs::write(path, png).unwrap();
}

fn sanity_error(e: PipelineError) -> (String, CalibError) {
    let msg = e.to_string();
    match e {
        PipelineError::CapturesInconsistent { problem, .. } => (msg, problem),
        other => panic!("expected CapturesInconsistent, got {other:?}"),
    }
}

/// Real data nobody here made (ViSP's Franka recording, 8 captures) and the rendered
/// data set pass the checks with every capture kept; their scores are printed.
#[test]
fn real_and_rendered_data_pass() {
    let visp = Dataset::load(&shared_dataset("visp-franka-eye-in-hand")).unwrap();
    let sim = Dataset::load(&bundled("sim-checkerboard-2x12")).unwrap();
    for (name, ds, robots) in [
        ("visp", &visp, vec!["robot1"]),
        ("sim-checkerboard-2x12", &sim, vec!["robot1", "robot2"]),
    ] {
        for robot in robots {
            let obs = observe_robot(ds, robot).unwrap();
            let n = ds.robot(robot).unwrap().captures.len();
            assert_eq!(
                obs.observations.len(),
                n,
                "{name}/{robot}: {:?}",
                obs.rejected
            );
            let (kept, rep) = screen_observations(&obs, name).unwrap();
            eprintln!(
                "{name}/{robot}: {} captures, angle score {:.2} sigma (median {:.3} deg), pitch score {:.2} sigma (median {:.2} mm over {} pairs), board at {:.2} m",
                rep.captures,
                rep.angle_score,
                rep.median_angle_diff_rad.to_degrees(),
                rep.pitch_score,
                rep.median_pitch_diff_m * 1e3,
                rep.pitch_pairs,
                rep.median_board_distance_m
            );
            assert!(rep.checked && rep.pitch_pairs > 0);
            assert!(
                rep.suspects.is_empty(),
                "{name}/{robot}: {:?}",
                rep.suspects
            );
            assert_eq!(kept.observations.len(), n);
            assert!(rep.angle_score < 2.5 && rep.pitch_score < 2.5, "{rep:?}");
        }
    }
}

#[test]
fn wxyz_quaternions_are_named_with_the_file() {
    let (_tmp, dir) = sim_copy();
    let captures = dir.join("robot1/captures.csv");
    rewrite_wxyz(&captures);
    let ds = Dataset::load(&dir).unwrap();
    let (msg, source) = sanity_error(observe_robot(&ds, "robot1").unwrap_err());
    eprintln!("{msg}");
    assert!(
        matches!(source, CalibError::QuaternionOrder { .. }),
        "{source:?}"
    );
    assert!(
        msg.contains("w, x, y, z") && msg.contains("robot1/captures.csv"),
        "{msg}"
    );
}

#[test]
fn square_size_in_millimetres_is_named_with_the_ratio() {
    let (_tmp, dir) = sim_copy();
    square_size_times_1000(&dir);
    let ds = Dataset::load(&dir).unwrap();
    let (msg, source) = sanity_error(observe_robot(&ds, "robot1").unwrap_err());
    eprintln!("{msg}");
    let CalibError::ScaleMismatch { ratio, .. } = source else {
        panic!("{source:?}");
    };
    assert!((ratio / 1000.0 - 1.0).abs() < 0.05, "{ratio}");
    assert!(msg.contains("millimetres written as metres") && msg.contains("square_m"));
}

/// One flange row with tx off by 65 cm is rejected with a reason; the others are kept.
#[test]
fn one_typo_row_is_rejected_not_fatal() {
    let (_tmp, dir) = sim_copy();
    let captures = dir.join("robot1/captures.csv");
    let text = std::fs::read_to_string(&captures).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    let mut f: Vec<String> = lines[5].split(',').map(str::to_owned).collect();
    let tx: f64 = f[2].parse().unwrap();
    f[2] = format!("{:?}", tx + 0.65);
    lines[5] = f.join(",");
    std::fs::write(&captures, lines.join("\n") + "\n").unwrap();
    let ds = Dataset::load(&dir).unwrap();
    let obs = observe_robot(&ds, "robot1").unwrap();
    eprintln!("rejected: {:?}", obs.rejected);
    assert_eq!(obs.observations.len(), 11);
    assert_eq!(obs.rejected.len(), 1);
    assert_eq!(obs.rejected[0].row, Some(5));
    assert!(obs.rejected[0].reason.contains("disagree"));
}

/// Image headers are checked before anything is decoded: a PNG that claims
/// 32000x32000 pixels and one of another size than the intrinsics are refused at once.
#[test]
fn image_headers_are_checked_before_decoding() {
    for (w, h, words) in [
        (32000, 32000, "claims 32000x32000"),
        (1280, 960, "intrinsics are for 640x480"),
    ] {
        let (_tmp, dir) = sim_copy();
        fake_png(&dir.join("robot1/images/003.png"), w, h);
        let ds = Dataset::load(&dir).unwrap();
        let start = Instant::now();
        let err = observe_robot(&ds, "robot1").unwrap_err();
        let secs = start.elapsed().as_secs_f64();
        eprintln!("{w}x{h}: {secs:.3} s: {err}");
        assert!(
            matches!(
                err,
                PipelineError::Vision(
                    VisionError::ImageTooLarge { .. } | VisionError::ImageSizeMismatch { .. }
                )
            ),
            "{err:?}"
        );
        let msg = err.to_string();
        assert!(msg.contains(words) && msg.contains("003.png"), "{msg}");
        assert!(secs < 1.0, "{secs} s");
        // The loader itself refuses it too, whoever calls it.
        let err = b2b_vision::load_gray(&dir.join("robot1/images/003.png"));
        if w == 32000 {
            assert!(
                matches!(err, Err(VisionError::ImageTooLarge { .. })),
                "{err:?}"
            );
        }
    }
}
