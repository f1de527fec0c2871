//! The publisher and subscriber in one process, over real iceoryx2 shared memory.
//! Every test uses its own service name.

use std::sync::mpsc::RecvTimeoutError;
use std::time::Duration;

use b2b_frames::{
    FrameHeader, FramePublisher, FrameSubscriber, FramesError, SUBSCRIBER_BUFFER, StreamKind,
};

fn unique(name: &str) -> String {
    format!(
        "b2b-test/{}/{}/{name}",
        std::process::id(),
        b2b_frames::now_ns()
    )
}

fn pattern(seed: u64, len: usize) -> Vec<u8> {
    let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..len)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as u8
        })
        .collect()
}

fn depth_header(n: u64) -> FrameHeader {
    FrameHeader::new(StreamKind::Z16, 64, 48)
        .with_intrinsics(50.0, 51.0, 32.0, 24.0, [0.1, -0.2, 0.001, 0.002, 0.03])
        .at(n, 1_000 + n)
}

#[test]
fn frames_arrive_byte_exact_with_their_header() {
    b2b_frames::quiet_iceoryx2_logs();
    let name = unique("exact");
    let mut publisher = FramePublisher::new(&name, 64 * 48 * 2).unwrap();
    let mut subscriber = FrameSubscriber::new(&name).unwrap();
    for n in 1..=5u64 {
        let header = depth_header(n);
        let bytes = pattern(n, header.payload_len());
        let sent = if n % 2 == 0 {
            publisher.publish_bytes(&header, &bytes).unwrap()
        } else {
            publisher
                .publish_with(&header, |buf| buf.copy_from_slice(&bytes))
                .unwrap()
        };
        assert_eq!(sent.sequence, n);
        assert_eq!(sent.subscribers, 1);
        let frame = subscriber.next().unwrap().expect("a frame");
        assert_eq!(frame.data(), &bytes[..]);
        assert_eq!(
            *frame.header(),
            FrameHeader {
                sequence: n,
                ..header
            }
        );
        assert_eq!(frame.row(1).unwrap(), &bytes[128..256]);
    }
    assert!(subscriber.next().unwrap().is_none());
    let s = subscriber.stats();
    assert_eq!(
        (s.received, s.dropped, s.skipped, s.source_gaps),
        (5, 0, 0, 0)
    );
}

#[test]
fn a_slow_subscriber_loses_old_frames_counts_them_and_never_blocks_the_publisher() {
    let name = unique("slow");
    let mut publisher = FramePublisher::new(&name, 64 * 48 * 2).unwrap();
    let mut subscriber = FrameSubscriber::new(&name).unwrap();
    // The subscriber reads nothing while 50 frames go out: publishing must not
    // wait for it. A publisher that waited would wait forever (nothing reads), so
    // the loop's end is the event; the watchdog's long limit only turns such a
    // hang into a failure, it measures nothing. (A failed publish drops `done`
    // and fails the test by itself: only the time running out is a hang.)
    let (done, finished) = std::sync::mpsc::channel::<()>();
    std::thread::spawn(move || {
        if let Err(RecvTimeoutError::Timeout) = finished.recv_timeout(Duration::from_secs(60)) {
            eprintln!("publishing to a stalled subscriber did not finish: it waits for its reader");
            std::process::exit(1);
        }
    });
    for n in 1..=50u64 {
        let h = depth_header(n);
        publisher.publish_with(&h, |buf| buf.fill(n as u8)).unwrap();
    }
    let _ = done.send(());
    // The queue kept the newest SUBSCRIBER_BUFFER frames.
    let frame = subscriber.latest().unwrap().expect("the newest frame");
    assert_eq!(frame.header().frame_number, 50);
    assert!(frame.data().iter().all(|b| *b == 50));
    let s = subscriber.stats();
    assert_eq!(s.received, SUBSCRIBER_BUFFER as u64);
    assert_eq!(s.skipped, SUBSCRIBER_BUFFER as u64 - 1);
    // The first frame received had sequence 50 - SUBSCRIBER_BUFFER + 1; nothing was
    // seen before it, so those are not counted as gaps yet. Now a second burst:
    drop(frame);
    for n in 51..=60u64 {
        publisher
            .publish_with(&depth_header(n), |buf| buf.fill(n as u8))
            .unwrap();
    }
    let frame = subscriber.next().unwrap().unwrap();
    assert_eq!(frame.header().sequence, 60 - SUBSCRIBER_BUFFER as u64 + 1);
    let s = subscriber.stats();
    // Frames 51..=58 minus the ones still queued were overwritten.
    assert_eq!(s.dropped, 60 - SUBSCRIBER_BUFFER as u64 - 50);
    assert_eq!(s.source_gaps, 0);
}

#[test]
fn the_camera_s_own_gaps_are_counted_apart_from_transport_drops() {
    let name = unique("gaps");
    let mut publisher = FramePublisher::new(&name, 64 * 48 * 2).unwrap();
    let mut subscriber = FrameSubscriber::new(&name).unwrap();
    for n in [10u64, 11, 14, 15] {
        publisher
            .publish_with(&depth_header(n), |b| b.fill(1))
            .unwrap();
        subscriber.next().unwrap().unwrap();
    }
    let s = subscriber.stats();
    assert_eq!((s.dropped, s.source_gaps), (0, 2));
}

#[test]
fn a_late_subscriber_gets_the_newest_frame_from_history() {
    let name = unique("late");
    let mut publisher = FramePublisher::new(&name, 64 * 48 * 2).unwrap();
    for n in 1..=3u64 {
        publisher
            .publish_with(&depth_header(n), |b| b.fill(n as u8))
            .unwrap();
    }
    let mut subscriber = FrameSubscriber::new(&name).unwrap();
    // History is handed over by the publisher's side (it is paused here). The
    // frame is there as soon as it is handed over; the long limit only turns
    // history that never comes into a failure.
    publisher.update_connections().unwrap();
    let frame = subscriber
        .wait_next(Duration::from_secs(60))
        .unwrap()
        .expect("no history frame within 60 s of the publisher's update_connections");
    assert_eq!(frame.header().frame_number, 3);
    assert!(subscriber.next().unwrap().is_none());
}

#[test]
fn wrong_frames_are_refused_before_anything_is_sent() {
    let name = unique("refuse");
    let mut publisher = FramePublisher::new(&name, 64 * 48 * 2).unwrap();
    let mut subscriber = FrameSubscriber::new(&name).unwrap();
    let big = FrameHeader::new(StreamKind::Rgb8, 64, 48);
    match publisher.publish_with(&big, |_| {}) {
        Err(FramesError::FrameTooLarge { len, max_bytes, .. }) => {
            assert_eq!((len, max_bytes), (64 * 48 * 3, 64 * 48 * 2))
        }
        other => panic!("{other:?}"),
    }
    let h = depth_header(1);
    match publisher.publish_bytes(&h, &[0; 10]) {
        Err(FramesError::WrongLength { expected, got, .. }) => {
            assert_eq!((expected, got), (6144, 10))
        }
        other => panic!("{other:?}"),
    }
    let bad = FrameHeader {
        depth_unit_m: -1.0,
        ..h
    };
    let e = publisher
        .publish_with(&bad, |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains(&name) && e.contains("depth_unit_m"), "{e}");
    // The cause is the error's source, printed once in the chain operators see.
    let err = publisher
        .try_publish_with(&h, |_| Err("decoder broke"))
        .unwrap_err();
    let mut e = err.to_string();
    let mut source = std::error::Error::source(&err);
    while let Some(s) = source {
        e += &format!(": {s}");
        source = s.source();
    }
    assert_eq!(e.matches("decoder broke").count(), 1, "{e}");
    assert!(
        subscriber.next().unwrap().is_none(),
        "a refused frame was sent"
    );
    assert_eq!(publisher.sent(), 0);
    // The sequence did not advance: the next frame is number 1, without a gap.
    publisher.publish_with(&h, |b| b.fill(3)).unwrap();
    assert_eq!(subscriber.next().unwrap().unwrap().header().sequence, 1);
}

#[test]
fn a_second_publisher_and_a_bad_name_are_clear_errors() {
    let name = unique("two");
    let _first = FramePublisher::new(&name, 1024).unwrap();
    let e = FramePublisher::new(&name, 1024).unwrap_err();
    assert!(
        matches!(e, FramesError::Setup { .. }) && e.to_string().contains(&name),
        "{e}"
    );
    let e = FramePublisher::new("", 1024).unwrap_err();
    assert!(matches!(e, FramesError::ServiceName { .. }), "{e}");
    let e = FramePublisher::new(&unique("zero"), 0).unwrap_err();
    assert!(e.to_string().contains("max_bytes"), "{e}");
}
