//! Conformance of both sides to FRI as KUKA documents it, on a virtual clock.
//!
//! The controller side is driven by a client that does what KUKA's SDK example
//! `LBRJointSineOverlay` does (`common::sdk`); our own client (`ClientSession`) is checked
//! against the same controller semantics, with the robot application's interpolated
//! position held and moving. Each test is named after the documented behaviour it checks.

mod common;

use std::time::Duration;

use b2b_robot::Joints;
use common::Harness;
use common::sdk::SdkHarness;
use kuka_fri::{ConnectionQuality, LinkConfig, SessionState, SimConfig};

/// One-way delay of the virtual network in these tests.
const ONE_WAY: Duration = Duration::from_micros(300);

fn sdk(cfg: SimConfig) -> SdkHarness {
    SdkHarness::new(cfg, SdkHarness::delay(ONE_WAY), SdkHarness::delay(ONE_WAY))
}

fn max_abs_diff(a: &Joints, b: &Joints, skip: Option<usize>) -> f64 {
    (0..7)
        .filter(|&j| Some(j) != skip)
        .map(|j| (a[j] - b[j]).abs())
        .fold(0.0, f64::max)
}

/// Brings the SDK client to COMMANDING_ACTIVE the way `fri-sim-controller --command` does:
/// the application starts the overlay, which begins once MONITORING_READY is reached.
fn reach_active(h: &mut SdkHarness) {
    h.sim.start_commanding();
    assert!(
        h.run_until(Duration::from_secs(5), |h| h.sim.state()
            == SessionState::CommandingActive),
        "no COMMANDING_ACTIVE: {:?}, {:?}",
        h.sim.state(),
        h.sim.stats()
    );
}

#[test]
fn lbr_joint_sine_overlay_keeps_joint_4_within_its_amplitude_for_10_s() {
    // (send period ms, receive multiplier): the example's 5 ms, the fastest 1 ms, and a
    // multiplier above 1.
    for (period_ms, multiplier) in [(5, 1), (1, 1), (2, 3)] {
        let mut h = sdk(SimConfig {
            send_period_ms: period_ms,
            receive_multiplier: multiplier,
            ..SimConfig::default()
        });
        reach_active(&mut h);
        let held = h.sim.ipo();
        let amplitude = h.client.amplitude;
        let sent_before = h.sim.stats().sent;
        let (mut max_joint4, mut max_others, mut max_ipo_moved) = (0.0f64, 0.0f64, 0.0f64);
        h.run_for(Duration::from_secs(10), |h| {
            let q = h.sim.q();
            max_joint4 = max_joint4.max((q[3] - held[3]).abs());
            max_others = max_others.max(max_abs_diff(&q, &held, Some(3)));
            max_ipo_moved = max_ipo_moved.max(max_abs_diff(&h.sim.ipo(), &held, None));
        });
        let s = h.sim.stats();
        let ctx = format!("{period_ms} ms x{multiplier}: {s:?}");
        assert_eq!(
            s.sent - sent_before,
            10_000 / u64::from(period_ms),
            "10 s of controller time: {ctx}"
        );
        assert_eq!(h.sim.state(), SessionState::CommandingActive, "{ctx}");
        assert_eq!((s.violations, s.aborted, s.malformed), (0, 0, 0), "{ctx}");
        assert_eq!(s.bad_reflections, 0, "{ctx}");
        // Within the amplitude (the extrapolation between replies of a multiplier above 1
        // may round a peak by micro-radians), and really moved by the sine.
        assert!(
            max_joint4 <= amplitude + 1e-5,
            "joint 4 left its amplitude: {max_joint4} rad, {ctx}"
        );
        assert!(
            max_joint4 >= 0.99 * amplitude,
            "sine not applied: {max_joint4}"
        );
        assert!(max_others < 1e-12, "other joints moved {max_others} rad");
        // The application holds its pose: the overlay never leaks into ipoData.
        assert_eq!(max_ipo_moved, 0.0, "ipoData moved with the overlay");
        let seen_ipo_moved = h
            .client
            .seen
            .iter()
            .filter(|m| m.state == SessionState::CommandingActive)
            .map(|m| max_abs_diff(&m.ipo, &held, None))
            .fold(0.0, f64::max);
        assert_eq!(seen_ipo_moved, 0.0);
    }
}

#[test]
fn lbr_joint_sine_overlay_rides_on_the_applications_own_motion() {
    let mut h = sdk(SimConfig::default());
    reach_active(&mut h);
    let start = h.sim.ipo();
    let mut target = start;
    target[0] += 0.5;
    target[3] += 0.3;
    // The robot application moves (its own motion, with the overlay on it).
    h.sim.move_app_to(target);
    let amplitude = h.client.amplitude;
    let (mut max_overlay, mut max_tracking, mut ipo_moved) = (0.0f64, 0.0f64, false);
    h.run_for(Duration::from_secs(4), |h| {
        let overlay = h.sim.overlay();
        max_overlay = max_overlay.max(overlay[3].abs());
        assert!(
            max_abs_diff(&overlay, &[0.0; 7], Some(3)) < 1e-12,
            "{overlay:?}"
        );
        max_tracking = max_tracking.max(max_abs_diff(&h.sim.q(), &h.sim.commanded(), None));
        ipo_moved |= max_abs_diff(&h.sim.ipo(), &start, None) > 0.1;
    });
    let s = h.sim.stats();
    assert!(ipo_moved, "the application did not move");
    assert_eq!((s.violations, s.aborted), (0, 0), "{s:?}");
    assert!(
        max_overlay <= amplitude + 1e-12,
        "overlay {max_overlay} rad"
    );
    assert!(max_overlay >= 0.99 * amplitude);
    // The arm is where the client commands it: the application's pose plus the sine (the
    // sine starts at its full slope, 0.063 rad/s, which the arm reaches in two cycles).
    assert!(
        max_tracking < 2e-4,
        "arm {max_tracking} rad from its command"
    );
    assert!(max_abs_diff(&h.sim.ipo(), &target, None) < 1e-12);
    assert!(max_abs_diff(&h.sim.q(), &target, Some(3)) < 1e-12);
    assert!((h.sim.q()[3] - target[3]).abs() <= amplitude + 1e-12);
}

#[test]
fn first_command_after_commanding_wait_equals_the_ipo_position() {
    // KUKA's example client.
    let mut h = sdk(SimConfig::default());
    reach_active(&mut h);
    h.run_for(Duration::from_millis(100), |_| {});
    let first = h
        .client
        .sent
        .iter()
        .find(|c| c.state == SessionState::CommandingActive)
        .expect("a command in COMMANDING_ACTIVE");
    let answered = h
        .client
        .seen
        .iter()
        .find(|m| m.sequence == first.reflected)
        .expect("the message it answers");
    assert_eq!(first.q, answered.ipo);
    // Before it, COMMANDING_WAIT was answered with the interpolated position too.
    assert!(
        h.client
            .sent
            .iter()
            .any(|c| c.state == SessionState::CommandingWait)
    );

    // Our client, with the application's pose held.
    let mut ours = Harness::new(
        SimConfig::default(),
        LinkConfig::perfect(),
        Harness::default_guard(),
    );
    ours.reach_commanding();
    ours.run_for(Duration::from_millis(50));
    let first = ours
        .sent
        .iter()
        .find(|c| c.state == SessionState::CommandingActive)
        .expect("a command in COMMANDING_ACTIVE");
    assert_eq!(first.q, Some(ours.ipo_sent[&first.reflected]));
}

#[test]
fn a_first_command_away_from_the_ipo_position_is_refused_and_aborts_the_overlay() {
    let mut h = sdk(SimConfig::default());
    h.client.first_offset = 0.05; // 10 rad/s over one 5 ms period
    reach_active(&mut h);
    let held = h.sim.ipo();
    h.run_for(Duration::from_millis(200), |_| {});
    let s = h.sim.stats();
    assert_eq!((s.violations, s.aborted), (1, 1), "{s:?}");
    // Back to MONITORING_READY (the connection is fine); the arm never took the command.
    assert_eq!(h.sim.state(), SessionState::MonitoringReady);
    assert!(max_abs_diff(&h.sim.q(), &held, None) < 1e-12);
    assert_eq!(h.client.state(), SessionState::MonitoringReady);
}

#[test]
fn a_command_jump_beyond_the_velocity_limit_aborts_the_overlay() {
    let mut h = sdk(SimConfig::default());
    // After 200 commands (1 s) the client adds 0.05 rad at once: 10 rad/s over 5 ms.
    h.client.jump = Some((200, 0.05));
    reach_active(&mut h);
    let held = h.sim.ipo();
    let amplitude = h.client.amplitude;
    let mut max_joint4 = 0.0f64;
    h.run_for(Duration::from_secs(2), |h| {
        max_joint4 = max_joint4.max((h.sim.q()[3] - held[3]).abs());
    });
    let s = h.sim.stats();
    assert_eq!((s.violations, s.aborted), (1, 1), "{s:?}");
    assert_eq!(h.sim.state(), SessionState::MonitoringReady);
    assert!(
        max_joint4 <= amplitude,
        "the jump reached the arm: {max_joint4}"
    );
    // The arm stays where the overlay left it, now the application's held pose.
    assert!(max_abs_diff(&h.sim.ipo(), &h.sim.q(), None) < 1e-12);
}

#[test]
fn missing_replies_drop_the_quality_and_abort_the_overlay() {
    let mut h = sdk(SimConfig::default());
    reach_active(&mut h);
    let held = h.sim.ipo();
    h.run_for(Duration::from_secs(1), |_| {});
    h.client.silent = true;
    let before = h.sim.q();
    let mut max_move = 0.0f64;
    h.run_for(Duration::from_millis(500), |h| {
        max_move = max_move.max(max_abs_diff(&h.sim.q(), &before, None));
    });
    let s = h.sim.stats();
    assert_eq!(s.aborted, 1, "{s:?}");
    assert_eq!(s.violations, 0);
    assert_eq!(h.sim.state(), SessionState::MonitoringWait);
    let last = h.client.seen.last().expect("messages");
    assert_eq!(last.state, SessionState::MonitoringWait);
    assert!(last.quality < ConnectionQuality::Good, "{last:?}");
    // The arm held where the lost commands left it (at most three bridged cycles).
    assert!(max_move < 1e-3, "arm moved {max_move} rad without commands");
    assert!((h.sim.q()[3] - held[3]).abs() <= h.client.amplitude + 1e-3);
    // Replies again: MONITORING_READY, and the application does not restart the overlay
    // by itself.
    h.client.silent = false;
    assert!(h.run_until(Duration::from_secs(2), |h| h.sim.state()
        == SessionState::MonitoringReady));
    h.run_for(Duration::from_millis(500), |_| {});
    assert_eq!(h.sim.state(), SessionState::MonitoringReady);
}

#[test]
fn the_application_ending_the_overlay_leaves_the_arm_where_it_was_commanded() {
    let mut h = sdk(SimConfig::default());
    reach_active(&mut h);
    h.run_for(Duration::from_millis(1500), |_| {});
    let at_end = h.sim.commanded();
    assert!(
        max_abs_diff(&at_end, &h.sim.ipo(), None) > 0.01,
        "no overlay to end"
    );
    h.sim.stop_commanding();
    let mut max_move = 0.0f64;
    h.run_for(Duration::from_millis(500), |h| {
        max_move = max_move.max(max_abs_diff(&h.sim.q(), &at_end, None));
    });
    assert_eq!(h.sim.state(), SessionState::MonitoringReady);
    assert_eq!(
        h.sim.ipo(),
        at_end,
        "the held pose is where the overlay ended"
    );
    assert!(max_move < 1e-9, "the arm moved {max_move} rad");
    let s = h.sim.stats();
    assert_eq!((s.violations, s.aborted), (0, 0));
}

/// What a client sees for a given share of replies on time.
#[test]
fn quality_is_the_share_of_replies_on_time() {
    struct Case {
        what: &'static str,
        skip_every: Option<u64>,
        silent: bool,
        uplink: Duration,
        quality: ConnectionQuality,
        ready: bool,
    }
    let period = Duration::from_millis(5);
    let cases = [
        Case {
            what: "every reply on time",
            skip_every: None,
            silent: false,
            uplink: ONE_WAY,
            quality: ConnectionQuality::Excellent,
            ready: true,
        },
        Case {
            what: "one reply in five left out",
            skip_every: Some(5),
            silent: false,
            uplink: ONE_WAY,
            quality: ConnectionQuality::Good,
            ready: true,
        },
        Case {
            what: "every other reply left out",
            skip_every: Some(2),
            silent: false,
            uplink: ONE_WAY,
            quality: ConnectionQuality::Fair,
            ready: false,
        },
        Case {
            what: "every reply a period and a half late",
            skip_every: None,
            silent: false,
            uplink: period + period / 2,
            quality: ConnectionQuality::Poor,
            ready: false,
        },
        Case {
            what: "no reply",
            skip_every: None,
            silent: true,
            uplink: ONE_WAY,
            quality: ConnectionQuality::Poor,
            ready: false,
        },
    ];
    for c in cases {
        let mut h = SdkHarness::new(
            SimConfig::default(),
            SdkHarness::delay(ONE_WAY),
            SdkHarness::delay(c.uplink),
        );
        h.client.skip_every = c.skip_every;
        h.client.silent = c.silent;
        h.run_for(Duration::from_secs(2), |_| {});
        let last = h.client.seen.last().expect("messages");
        assert_eq!(last.quality, c.quality, "{}", c.what);
        let ready = h
            .client
            .seen
            .iter()
            .any(|m| m.state == SessionState::MonitoringReady);
        assert_eq!(ready, c.ready, "{}", c.what);
        assert_eq!(
            last.state,
            if c.ready {
                SessionState::MonitoringReady
            } else {
                SessionState::MonitoringWait
            },
            "{}",
            c.what
        );
        let s = h.sim.stats();
        if c.uplink > period {
            assert_eq!(s.late_replies, s.commands, "{}: {s:?}", c.what);
            assert!(s.commands > 300, "{}: {s:?}", c.what);
        } else {
            assert_eq!(s.late_replies, 0, "{}: {s:?}", c.what);
        }
    }
}

#[test]
fn our_client_commands_from_an_ipo_position_that_moves_on_its_own() {
    let mut h = Harness::new(
        SimConfig::default(),
        LinkConfig::perfect(),
        Harness::default_guard(),
    );
    assert!(h.run_until(Duration::from_secs(2), |h| h.client.state()
        == SessionState::MonitoringReady));
    let start = h.sim.ipo();
    let mut app_target = start;
    app_target[0] += 0.8;
    app_target[3] += 0.3;
    // The application moves, and starts the overlay while it moves.
    h.sim.move_app_to(app_target);
    h.run_for(Duration::from_millis(100));
    h.sim.start_commanding();
    assert!(h.run_until(Duration::from_secs(2), |h| h.client.state()
        == SessionState::CommandingActive));
    let ipo_then = h.sim.ipo();
    h.step();
    assert!(
        max_abs_diff(&h.sim.ipo(), &ipo_then, None) > 1e-4,
        "the interpolated position must still move when commanding starts"
    );
    // The monitoring replies followed the moving arm; COMMANDING_WAIT echoed each message's
    // own interpolated position; the first command is the interpolated position too.
    for c in &h.sent {
        if c.state == SessionState::CommandingWait {
            assert_eq!(c.q, Some(h.ipo_sent[&c.reflected]), "{c:?}");
        }
    }
    let first = h
        .sent
        .iter()
        .find(|c| c.state == SessionState::CommandingActive)
        .expect("a command in COMMANDING_ACTIVE");
    assert_eq!(first.q, Some(h.ipo_sent[&first.reflected]));
    // Our client takes the arm over: it holds its commands while the application's
    // position moves on, and a motion goes to the absolute target it names.
    let target = [0.3, 0.4, -0.2, -1.0, 0.4, 0.6, 0.5];
    let (id, planned) = h.client.start_motion(target).expect("motion starts");
    assert!(h.run_until(planned + Duration::from_secs(1), |h| {
        h.motion_result(id).is_some()
    }));
    assert_eq!(h.motion_result(id), Some(Ok(())));
    h.run_for(Duration::from_millis(1500));
    assert!(
        max_abs_diff(&h.sim.ipo(), &app_target, None) < 1e-12,
        "the application finished its motion"
    );
    assert!(
        max_abs_diff(&h.sim.q(), &target, None) < 1e-6,
        "{:?}",
        h.sim.q()
    );
    assert!(h.client.is_still(Duration::from_millis(200), 2e-4));
    let s = h.sim.stats();
    assert_eq!(
        (s.violations, s.aborted, s.bad_reflections),
        (0, 0, 0),
        "{s:?}"
    );
    assert_eq!(h.client.state(), SessionState::CommandingActive);
    assert_eq!(h.client.stats().rejected, 0);
}
