//! A D435 recording played through librealsense into iceoryx2, per frame: from
//! librealsense handing over a frameset to the publish of what it carried, as
//! `camera --realsense` does it ([`RealSense::publish_next`], timed by
//! [`RealSense::last_work`]; the wait for the next frameset is the recording's
//! pace, not the camera's work, and is left out):
//! - a 1280x720 colour frame copied out of librealsense's buffer into its
//!   loaned sample and published (goal: ≤ 2 ms);
//! - an 848x480 depth frame copied, aligned to colour (`benches/align.rs`
//!   times the alignment alone) and published.
//!
//! The recording: six frames at 30 fps, looped (`benches/common/d435.rs`), so
//! a sample takes real time to play.
//!
//! Needs the `realsense` feature and librealsense (`scripts/setup-realsense`):
//! `cargo bench -p b2b-frames --features realsense --bench playback`; the gate
//! runs it once.

#[path = "common/d435.rs"]
mod d435;

use std::time::Duration;

use b2b_frames::realsense::{Played, RealSense, RealSenseOptions};
use b2b_frames::{FramePublisher, Stream, service_name_in};
use criterion::{Criterion, criterion_group, criterion_main};

const FPS: u32 = 30;

fn bench(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let bag = d435::record(dir.path(), 6, f64::from(FPS));
    b2b_frames::quiet_iceoryx2_logs();
    let mut rs = RealSense::open(&RealSenseOptions {
        bag: Some(bag),
        loop_playback: true,
        fps: FPS,
        ..RealSenseOptions::default()
    })
    .unwrap();
    let prefix = format!("b2b-bench/{}/playback", std::process::id());
    let (colour_bytes, depth_bytes) = rs.max_bytes();
    let mut colour = FramePublisher::new(
        &service_name_in(&prefix, "rs", Stream::Colour),
        colour_bytes,
    )
    .unwrap();
    let mut depth =
        FramePublisher::new(&service_name_in(&prefix, "rs", Stream::Depth), depth_bytes).unwrap();
    let mut group = c.benchmark_group("d435_playback_to_iceoryx2_per_frame");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(1));
    // Each sample plays frames until this many of one stream went out, and
    // sums that stream's share of every frameset's work (a colour frame's
    // depth may come in the next frameset).
    let mut play = |frames: u64, depth_frames: bool| {
        let (mut work, mut n) = (Duration::ZERO, 0);
        while n < frames {
            let events = rs
                .publish_next(&mut colour, &mut depth, Duration::from_secs(5))
                .unwrap();
            let w = rs.last_work();
            work += if depth_frames { w.depth } else { w.colour };
            n += events
                .iter()
                .filter(|e| match e {
                    Played::Colour { .. } => !depth_frames,
                    Played::Depth { .. } => depth_frames,
                    _ => false,
                })
                .count() as u64;
        }
        work
    };
    group.bench_function("ours, colour 1280x720: copied and published", |b| {
        b.iter_custom(|n| play(n, false))
    });
    group.bench_function(
        "ours, depth 848x480: copied, aligned to colour and published",
        |b| b.iter_custom(|n| play(n, true)),
    );
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
