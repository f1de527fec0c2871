//! Client session against the simulated controller on a virtual clock.

mod common;

use std::time::Duration;

use b2b_robot::{JointLimits, Joints};
use common::{Harness, SentCommand};
use kuka_fri::{Event, LinkConfig, SessionState, SimConfig};

/// Checks the wire invariants of everything the client sent.
fn check_sent(sent: &[SentCommand], limits: &JointLimits, send_period: f64) {
    let mut prev_active: Option<&SentCommand> = None;
    for (k, c) in sent.iter().enumerate() {
        assert_ne!(c.state, SessionState::Idle, "reply sent in IDLE: {c:?}");
        assert_eq!(
            c.sequence, k as u32,
            "client sequence counter must count up by one"
        );
        if c.state == SessionState::CommandingActive {
            let q = c.q.expect("commands carry joint positions");
            limits.check_position(&q, 0.0).expect("within joint limits");
            if let Some(p) = prev_active.filter(|p| p.state == SessionState::CommandingActive) {
                let dt = f64::from(c.reflected.wrapping_sub(p.reflected)) * send_period;
                assert!(dt > 0.0, "reflected counters must increase: {p:?} -> {c:?}");
                let pq = p.q.expect("q");
                for j in 0..7 {
                    assert!((q[j] - pq[j]).abs() <= limits.velocity[j] * dt * (1.0 + 1e-9));
                }
            }
        }
        prev_active = Some(c);
    }
}

fn dist(a: &Joints, b: &Joints) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

#[test]
fn full_session_lifecycle_on_a_perfect_link() {
    let mut h = Harness::new(
        SimConfig::default(),
        LinkConfig::perfect(),
        Harness::default_guard(),
    );
    h.reach_commanding();
    let target = [0.3, 0.2, -0.2, -1.0, 0.4, 0.6, 0.5];
    let (id, planned) = h.client.start_motion(target).expect("motion starts");
    assert!(h.run_until(planned + Duration::from_secs(1), |h| {
        h.motion_result(id).is_some()
    }));
    assert_eq!(h.motion_result(id), Some(Ok(())));
    h.run_for(Duration::from_millis(200));
    assert!(dist(&h.sim.q(), &target) < 1e-6, "arm at {:?}", h.sim.q());
    let latest = h.client.latest_joint_state().expect("joints");
    assert!(dist(&latest.q, &target) < 2e-4);
    assert!(h.client.is_still(Duration::from_millis(100), 2e-4));

    h.sim.stop_commanding();
    assert!(h.run_until(Duration::from_secs(1), |h| h.client.state()
        == SessionState::MonitoringReady));
    h.sim.close_session();
    assert!(h.run_until(Duration::from_secs(1), |h| h.client.state()
        == SessionState::Idle));
    let sent_before = h.sent.len();
    h.run_for(Duration::from_millis(500));
    assert_eq!(
        h.sent.len(),
        sent_before,
        "the client must never reply in IDLE"
    );

    let s = h.sim.stats();
    assert_eq!(
        (s.violations, s.malformed, s.bad_reflections, s.aborted),
        (0, 0, 0, 0)
    );
    check_sent(&h.sent, &JointLimits::iiwa7(), 0.005);
    let c = h.client.stats();
    assert_eq!((c.lost, c.stale, c.malformed, c.rejected), (0, 0, 0, 0));
    // Every state was reported in order.
    let states: Vec<SessionState> = h
        .events
        .iter()
        .filter_map(|e| match e {
            Event::StateChanged { to, .. } => Some(*to),
            _ => None,
        })
        .collect();
    assert_eq!(
        states,
        [
            SessionState::MonitoringWait,
            SessionState::MonitoringReady,
            SessionState::CommandingWait,
            SessionState::CommandingActive,
            SessionState::MonitoringReady,
            SessionState::Idle
        ]
    );
}

#[test]
fn thousands_of_cycles_with_loss_reordering_and_delay() {
    // 3 % loss and 3 % reordering each way, and a round trip of 1.6 to 5.6 ms: about one
    // reply in six misses its cycle (lost, reordered or late), within what the controller
    // accepts for commanding (GOOD: 60 % on time over 50 cycles).
    let link = LinkConfig {
        loss: 0.03,
        delay: Duration::from_micros(800),
        jitter: Duration::from_millis(2),
        reorder: 0.03,
        reorder_delay: Duration::from_millis(12),
        seed: 42,
    };
    let mut h = Harness::new(
        SimConfig {
            seed: 7,
            ..SimConfig::default()
        },
        link,
        Harness::default_guard(),
    );
    h.reach_commanding();
    let poses: [Joints; 3] = [
        [0.5, 0.3, 0.2, -1.1, -0.4, 0.7, 1.0],
        [-0.6, 0.6, -0.3, -0.8, 0.5, 0.4, -1.0],
        [0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0],
    ];
    let mut finished = 0;
    for round in 0..3 {
        for target in poses {
            let (id, planned) = h.client.start_motion(target).expect("motion starts");
            assert!(h.run_until(planned * 2 + Duration::from_secs(1), |h| {
                h.motion_result(id).is_some()
            }));
            assert_eq!(h.motion_result(id), Some(Ok(())), "round {round}");
            finished += 1;
            h.run_for(Duration::from_millis(300));
            assert!(
                dist(&h.sim.q(), &target) < 1e-6,
                "arm at {:?}, target {target:?}",
                h.sim.q()
            );
            assert!(h.client.is_still(Duration::from_millis(200), 3e-4));
        }
    }
    assert_eq!(finished, 9);
    let s = h.sim.stats();
    assert!(s.sent > 3000, "only {} cycles", s.sent);
    assert_eq!(
        (s.violations, s.malformed, s.bad_reflections, s.aborted),
        (0, 0, 0, 0),
        "{s:?}"
    );
    assert_eq!(h.sim.state(), SessionState::CommandingActive);
    let c = h.client.stats();
    assert!(c.lost > 50, "loss must have been seen: {c:?}");
    assert!(c.stale > 10, "reordering must have been seen: {c:?}");
    assert_eq!((c.malformed, c.rejected, c.timeouts), (0, 0, 0), "{c:?}");
    assert!(
        s.stale > 0,
        "the controller saw reordered commands too: {s:?}"
    );
    check_sent(&h.sent, &JointLimits::iiwa7(), 0.005);
    assert!(
        h.down.stats().dropped > 50 && h.up.stats().dropped > 50,
        "{:?} {:?}",
        h.down.stats(),
        h.up.stats()
    );
}

#[test]
fn replies_every_receive_multiplier_th_message() {
    let cfg = SimConfig {
        send_period_ms: 2,
        receive_multiplier: 3,
        ..SimConfig::default()
    };
    let mut h = Harness::new(cfg, LinkConfig::perfect(), Harness::default_guard());
    h.run_for(Duration::from_millis(600));
    let received = h.client.stats().received;
    let sent = h.client.stats().sent;
    assert!(received >= 299, "{received}");
    assert_eq!(sent, received / 3);
    assert!(
        h.sent
            .windows(2)
            .all(|w| w[1].reflected.wrapping_sub(w[0].reflected) == 3)
    );
    assert_eq!(h.client.state(), SessionState::MonitoringReady);
}

#[test]
fn silence_times_out_and_aborts_the_motion() {
    let mut h = Harness::new(
        SimConfig::default(),
        LinkConfig::perfect(),
        Harness::default_guard(),
    );
    h.reach_commanding();
    let (id, _) = h
        .client
        .start_motion([1.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0])
        .expect("motion");
    h.run_for(Duration::from_millis(100));
    h.cut = true;
    h.run_for(Duration::from_millis(300));
    assert_eq!(h.client.state(), SessionState::Idle);
    assert!(
        h.events
            .iter()
            .any(|e| matches!(e, Event::ConnectionLost { .. }))
    );
    assert!(matches!(h.motion_result(id), Some(Err(_))));
    assert_eq!(h.client.stats().timeouts, 1);
    // The controller, missing replies, drops out of commanding as a real one would.
    assert_eq!(h.sim.state(), SessionState::MonitoringWait);
    assert_eq!(h.sim.stats().violations, 0);
    // And the session recovers when datagrams flow again.
    h.cut = false;
    assert!(h.run_until(Duration::from_secs(3), |h| h.client.state()
        == SessionState::MonitoringReady));
}

#[test]
fn monitoring_only_sees_robot_application_motion_and_stillness() {
    let mut h = Harness::new(
        SimConfig::default(),
        LinkConfig::perfect(),
        Harness::default_guard(),
    );
    assert!(h.run_until(Duration::from_secs(2), |h| h.client.state()
        == SessionState::MonitoringReady));
    h.run_for(Duration::from_millis(300));
    assert!(h.client.is_still(Duration::from_millis(200), 2e-4));
    let start = h.client.latest_joint_state().expect("joints");
    h.sim.move_app_to([0.5, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0]);
    h.run_for(Duration::from_millis(100));
    assert!(
        !h.client.is_still(Duration::from_millis(50), 2e-4),
        "moving arm reported still"
    );
    assert_eq!(
        h.client.start_motion([0.0; 7]).unwrap_err().to_string(),
        "commands are only sent in COMMANDING_ACTIVE; session is MONITORING_READY"
    );
    h.run_for(Duration::from_secs(2));
    let end = h.client.latest_joint_state().expect("joints");
    assert!((end.q[0] - 0.5).abs() < 2e-4);
    assert!(end.timestamp > start.timestamp);
    assert!(h.client.is_still(Duration::from_millis(200), 2e-4));
    // Replies in monitoring echo the commanded position.
    let last = h.sent.last().expect("replies").q.expect("q");
    assert!((last[0] - 0.5).abs() < 1e-9);
}

#[test]
fn guard_rejects_unsafe_targets_before_moving() {
    let mut h = Harness::new(
        SimConfig::default(),
        LinkConfig::perfect(),
        Harness::default_guard(),
    );
    h.reach_commanding();
    let err = h
        .client
        .start_motion([3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        .unwrap_err();
    assert!(
        err.to_string()
            .starts_with("joint A1 position 3.0000 rad outside"),
        "{err}"
    );
    // A raw position jump far from the current command is refused too.
    let err = h
        .client
        .set_position_command([0.5, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0])
        .unwrap_err();
    assert!(err.to_string().contains("velocity"), "{err}");
    h.run_for(Duration::from_millis(100));
    assert_eq!(h.client.stats().rejected, 0);
}

#[test]
fn stop_motion_brakes_on_the_path() {
    let mut h = Harness::new(
        SimConfig::default(),
        LinkConfig::perfect(),
        Harness::default_guard(),
    );
    h.reach_commanding();
    let from = h.sim.q();
    let target = [1.2, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0];
    let (id, planned) = h.client.start_motion(target).expect("motion");
    h.run_for(planned / 4);
    h.client.stop_motion();
    assert!(h.run_until(Duration::from_secs(3), |h| h.motion_result(id).is_some()));
    h.run_for(Duration::from_millis(300));
    let q = h.sim.q();
    assert!(
        q[0] > from[0] + 0.1 && q[0] < target[0] - 0.05,
        "stopped at {q:?}"
    );
    assert_eq!(h.sim.stats().violations, 0);
    check_sent(&h.sent, &JointLimits::iiwa7(), 0.005);
}
