//! The agent's own check of a capture's depth: the depth frame numbered like its
//! colour frame is taken only when it was exposed within
//! `DEPTH_PAIR_WINDOW_NS` of it and has its size (aligned to colour); a late
//! one leaves the capture without depth, a misaligned one is an error; a frame
//! is taken by when it was exposed, not when it arrived.

use std::time::Duration;

use b2b_frames::{FrameHeader, FramePublisher, Stream, StreamKind, service_name_in};
use b2b_live::live::DEPTH_PAIR_WINDOW_NS;
use b2b_live::{FrameSource, IceoryxFrames};

const W: u32 = 64;
const H: u32 = 48;

struct Camera {
    colour: FramePublisher,
    depth: FramePublisher,
}

impl Camera {
    fn publish(&mut self, number: u64, colour_ns: u64, depth_ns: u64, depth_size: (u32, u32)) {
        let c = FrameHeader::new(StreamKind::Rgb8, W, H)
            .with_intrinsics(60.0, 60.0, 31.5, 23.5, [0.0; 5])
            .at(number, colour_ns);
        self.colour.publish_with(&c, |buf| buf.fill(128)).unwrap();
        let d = FrameHeader::new(StreamKind::Z16, depth_size.0, depth_size.1)
            .with_intrinsics(60.0, 60.0, 31.5, 23.5, [0.0; 5])
            .at(number, depth_ns);
        self.depth
            .publish_with(&d, |buf| {
                for px in buf.chunks_exact_mut(2) {
                    px.copy_from_slice(&600u16.to_le_bytes());
                }
            })
            .unwrap();
    }
}

fn setup(test: &str) -> (Camera, IceoryxFrames) {
    b2b_frames::quiet_iceoryx2_logs();
    let prefix = format!(
        "b2b-test/{}/{}/{test}",
        std::process::id(),
        b2b_frames::now_ns()
    );
    // The agent's side first: a publisher connects to the subscribers it finds.
    let frames = IceoryxFrames::new(&prefix, "robot1")
        .unwrap()
        .with_depth(&prefix, "robot1")
        .unwrap();
    let camera = Camera {
        colour: FramePublisher::new(
            &service_name_in(&prefix, "robot1", Stream::Colour),
            (W * H * 3) as usize,
        )
        .unwrap(),
        depth: FramePublisher::new(
            &service_name_in(&prefix, "robot1", Stream::Depth),
            (2 * W * H * 2) as usize,
        )
        .unwrap(),
    };
    (camera, frames)
}

#[test]
fn depth_exposed_with_its_colour_frame_is_taken_and_a_late_one_is_not() {
    let (mut camera, mut frames) = setup("pairing");
    let t = b2b_frames::now_ns();
    camera.publish(1, t, t + 400_000, (W, H));
    let f = frames.frame_after(0, Duration::from_secs(5)).unwrap();
    assert_eq!(f.number, 1);
    let (depth, unit) = f.depth.expect("depth 0.4 ms from its colour frame");
    assert_eq!((depth.width, depth.height, unit), (W, H, 0.001));

    // One frame period late (33 ms at 30 fps): not this capture's exposure.
    camera.publish(2, t + 100_000_000, t + 133_000_000, (W, H));
    let f = frames.frame_after(0, Duration::from_secs(5)).unwrap();
    assert_eq!(f.number, 2);
    assert!(f.depth.is_none(), "a depth frame 33 ms off was taken");

    // Just inside the window, and early rather than late: taken.
    let early = DEPTH_PAIR_WINDOW_NS - 1_000_000;
    camera.publish(3, t + 200_000_000, t + 200_000_000 - early, (W, H));
    let f = frames.frame_after(0, Duration::from_secs(5)).unwrap();
    assert_eq!(f.number, 3);
    assert!(f.depth.is_some());
}

#[test]
fn depth_not_aligned_to_colour_is_an_error() {
    let (mut camera, mut frames) = setup("misaligned");
    let t = b2b_frames::now_ns();
    camera.publish(1, t, t, (2 * W, H));
    let e = frames
        .frame_after(0, Duration::from_secs(5))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("depth frame 1 is 128x48 but its colour frame is 64x48"),
        "{e}"
    );
}

/// Exposure lags the request: a real camera delivers a frame tens of
/// milliseconds after exposing it, so the first frame to arrive after the arm
/// stopped may show it moving. The agent goes by the exposure time.
#[test]
fn a_frame_exposed_before_the_arm_stopped_is_not_taken_though_it_arrives_after() {
    let (mut camera, mut frames) = setup("exposure");
    let stopped = b2b_frames::now_ns();
    // Exposed 30 ms before the stop, arriving now; then one exposed after it.
    camera.publish(1, stopped - 30_000_000, stopped - 29_600_000, (W, H));
    camera.publish(2, stopped + 3_000_000, stopped + 3_400_000, (W, H));
    let f = frames.frame_after(stopped, Duration::from_secs(5)).unwrap();
    assert_eq!(f.number, 2);
    assert!(f.depth.is_some());
}
