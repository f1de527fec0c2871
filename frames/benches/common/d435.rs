//! A D435's two streams for the benchmarks: the factory headers, a scene's
//! depth frame, and (for playback) a `.bag` recorded by librealsense's own
//! recorder (`scripts/realsense-bag.py`, the layout `b2b_sim::d435` writes).

#![allow(dead_code)]

use std::path::{Path, PathBuf};

use b2b_frames::align::Extrinsic;
use b2b_frames::{FrameHeader, StreamKind};

/// A D435's factory streams (the simulator's `D435::factory`).
pub fn colour() -> FrameHeader {
    FrameHeader::new(StreamKind::Rgb8, 1280, 720)
        .with_intrinsics(909.7, 909.9, 643.2, 357.8, [0.0; 5])
}

pub fn depth_stream() -> FrameHeader {
    FrameHeader::new(StreamKind::Z16, 848, 480)
        .with_intrinsics(421.4, 421.4, 422.1, 241.6, [0.0; 5])
}

/// `colour_from_depth`: 14.8 mm along x.
pub const COLOUR_FROM_DEPTH: Extrinsic = Extrinsic {
    rotation: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
    translation_m: [0.0148, 0.0, 0.0],
};

/// A tilted table with a box in the middle, in millimetres.
pub fn depth_frame() -> Vec<u16> {
    let (w, h) = (
        depth_stream().width as usize,
        depth_stream().height as usize,
    );
    (0..w * h)
        .map(|i| {
            let (u, v) = ((i % w) as f64, (i / w) as f64);
            let table = 600.0 + 0.2 * v;
            let in_box = (300.0..520.0).contains(&u) && (150.0..330.0).contains(&v);
            (if in_box { table - 150.0 } else { table }).round() as u16
        })
        .collect()
}

/// A colour frame: a pattern that changes with `k`.
pub fn colour_frame(k: usize) -> Vec<u8> {
    let (w, h) = (colour().width as usize, colour().height as usize);
    (0..w * h * 3)
        .map(|i| ((i / 3 % w + i / 3 / w + 40 * k + 85 * (i % 3)) % 256) as u8)
        .collect()
}

fn intrinsics(h: &FrameHeader) -> String {
    let d = h.dist;
    format!(
        r#"{{"width": {}, "height": {}, "fx": {}, "fy": {}, "cx": {}, "cy": {}, "dist": [{}, {}, {}, {}, {}]}}"#,
        h.width, h.height, h.fx, h.fy, h.cx, h.cy, d[0], d[1], d[2], d[3], d[4]
    )
}

/// Records `n` colour and depth frames, `1000 / fps` ms apart (depth 0.4 ms
/// after its colour frame), into `dir/bench.bag`.
pub fn record(dir: &Path, n: usize, fps: f64) -> PathBuf {
    let raw = dir.join("frames");
    std::fs::create_dir_all(&raw).unwrap();
    let depth: Vec<u8> = depth_frame().iter().flat_map(|z| z.to_le_bytes()).collect();
    std::fs::write(raw.join("depth.z16"), depth).unwrap();
    let mut list = Vec::new();
    for k in 0..n {
        let file = format!("colour_{k:03}.rgb");
        std::fs::write(raw.join(&file), colour_frame(k)).unwrap();
        let t = 1000.0 + 1000.0 / fps * k as f64;
        list.push(format!(
            r#"{{"stream": "colour", "number": {}, "timestamp_ms": {t}, "file": "{file}"}}"#,
            k + 1
        ));
        list.push(format!(
            r#"{{"stream": "depth", "number": {}, "timestamp_ms": {}, "file": "depth.z16"}}"#,
            k + 1,
            t + 0.4
        ));
    }
    // depth_from_colour is the inverse of COLOUR_FROM_DEPTH.
    let t = COLOUR_FROM_DEPTH.translation_m.map(|x| -x);
    let manifest = format!(
        r#"{{"colour": {}, "depth": {}, "fps": {fps}, "depth_unit_m": 0.001,
"depth_from_colour": {{"rotation": [1, 0, 0, 0, 1, 0, 0, 0, 1], "translation_m": [{}, {}, {}]}},
"frames": [{}]}}"#,
        intrinsics(&colour()),
        intrinsics(&depth_stream()),
        t[0],
        t[1],
        t[2],
        list.join(",\n")
    );
    std::fs::write(raw.join("manifest.json"), manifest).unwrap();
    let bag = dir.join("bench.bag");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/realsense-bag.py");
    let out = std::process::Command::new("python3")
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
