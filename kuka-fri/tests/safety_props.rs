//! Property tests: whatever motion is requested, no command leaves the joint limits, the
//! velocity limits or the workspace box; and no byte string panics the decoders.

mod common;

use std::time::Duration;

use b2b_robot::{JointLimits, Joints, WorkspaceBox};
use common::{Harness, toy_fk};
use kuka_fri::codec;
use kuka_fri::{
    ClientSession, LinkConfig, SafetyGuard, SessionConfig, SessionState, SimConfig, Trajectory,
};
use proptest::prelude::*;

#[derive(Clone, Debug)]
enum Action {
    MoveTo(Joints),
    Position(Joints),
    Stop,
    Hold,
    Wait(u64),
}

fn any_joint() -> impl Strategy<Value = f64> {
    prop_oneof![
        8 => -3.5f64..3.5,
        1 => Just(f64::NAN),
        1 => prop_oneof![Just(f64::INFINITY), Just(-1e300), Just(3.05), Just(-2.1)],
    ]
}

fn any_joints() -> impl Strategy<Value = Joints> {
    proptest::array::uniform7(any_joint())
}

fn action() -> impl Strategy<Value = Action> {
    prop_oneof![
        4 => any_joints().prop_map(Action::MoveTo),
        2 => any_joints().prop_map(Action::Position),
        1 => Just(Action::Stop),
        1 => Just(Action::Hold),
        3 => (1u64..400).prop_map(Action::Wait),
    ]
}

/// Small perturbations of the start pose, so Position commands are sometimes accepted.
fn near_start() -> impl Strategy<Value = Action> {
    proptest::array::uniform7(-0.004f64..0.004).prop_map(|d| {
        let start = SimConfig::default().initial_q;
        Action::Position(std::array::from_fn(|j| start[j] + d[j]))
    })
}

/// Every command sent in COMMANDING_ACTIVE is inside the joint limits and the box, and
/// no step between two is faster than the velocity limits; the controller saw no
/// violation.
fn check_sent(
    h: &Harness,
    limits: &JointLimits,
    workspace: &WorkspaceBox,
) -> Result<(), TestCaseError> {
    let mut prev: Option<(Joints, u32)> = None;
    for c in &h.sent {
        if c.state != SessionState::CommandingActive {
            prev = None;
            continue;
        }
        let q = c.q.expect("commands carry positions");
        prop_assert!(limits.check_position(&q, 0.0).is_ok(), "joint limit: {q:?}");
        prop_assert!(workspace.contains(&toy_fk(&q)), "outside box: {q:?}");
        if let Some((pq, pseq)) = prev {
            let dt = f64::from(c.reflected.wrapping_sub(pseq)) * 0.005;
            prop_assert!(dt > 0.0);
            for j in 0..7 {
                prop_assert!(
                    (q[j] - pq[j]).abs() <= limits.velocity[j] * dt * (1.0 + 1e-9),
                    "joint {j} too fast: {} rad in {dt} s",
                    (q[j] - pq[j]).abs()
                );
            }
        }
        prev = Some((q, c.reflected));
    }
    prop_assert_eq!(h.sim.stats().violations, 0);
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn no_command_violates_limits_or_box(
        actions in proptest::collection::vec(prop_oneof![4 => action(), 1 => near_start()], 1..8),
        zmax in 0.9f64..1.6,
        rmax in 0.5f64..1.3,
        loss in 0.0f64..0.08,
        seed in any::<u64>(),
        iiwa14 in any::<bool>(),
    ) {
        let limits = if iiwa14 { JointLimits::iiwa14() } else { JointLimits::iiwa7() };
        let workspace = WorkspaceBox::new([-rmax, -rmax, 0.2], [rmax, rmax, zmax]).unwrap();
        // The start pose must itself be inside the box for commanding to begin.
        let start = SimConfig::default().initial_q;
        prop_assume!(workspace.contains(&toy_fk(&start)));
        let guard = SafetyGuard::new(limits, workspace, toy_fk).unwrap();
        let link = LinkConfig {
            loss,
            delay: Duration::from_micros(500),
            jitter: Duration::from_millis(2),
            reorder: loss,
            reorder_delay: Duration::from_millis(11),
            seed,
        };
        let sim_cfg = SimConfig { limits, seed, ..SimConfig::default() };
        let mut h = Harness::new(sim_cfg, link, guard);
        // Under heavy loss the controller may refuse command mode; the client
        // must then send no command at all, which the checks below cover too.
        let _commanding = h.try_reach_commanding();
        for a in actions {
            match a {
                Action::MoveTo(q) => { let _ = h.client.start_motion(q); }
                Action::Position(q) => { let _ = h.client.set_position_command(q); }
                Action::Stop => h.client.stop_motion(),
                Action::Hold => h.client.hold(),
                Action::Wait(ms) => h.run_for(Duration::from_millis(ms)),
            }
            h.run_for(Duration::from_millis(20));
        }
        h.run_for(Duration::from_millis(500));

        check_sent(&h, &limits, &workspace)?;
    }

    /// Long motions towards targets around and beyond the joint limits, through and out
    /// of the box: every one whose target or path would leave them must be refused or
    /// stopped. (The test above moves for at most a few seconds in all; here each motion
    /// gets three, so a guard that let a motion through would be seen to leave.)
    #[test]
    fn long_motions_never_leave_the_limits_or_box(
        targets in proptest::collection::vec(proptest::array::uniform7(-1.2f64..1.2), 1..4),
        zmax in 0.9f64..1.6,
        rmax in 0.5f64..1.3,
        seed in any::<u64>(),
        iiwa14 in any::<bool>(),
    ) {
        let limits = if iiwa14 { JointLimits::iiwa14() } else { JointLimits::iiwa7() };
        let workspace = WorkspaceBox::new([-rmax, -rmax, 0.2], [rmax, rmax, zmax]).unwrap();
        let start = SimConfig::default().initial_q;
        prop_assume!(workspace.contains(&toy_fk(&start)));
        let guard = SafetyGuard::new(limits, workspace, toy_fk).unwrap();
        let sim_cfg = SimConfig { limits, seed, ..SimConfig::default() };
        let mut h = Harness::new(sim_cfg, LinkConfig::perfect(), guard);
        prop_assert!(h.try_reach_commanding());
        for u in targets {
            let q: Joints = std::array::from_fn(|j| u[j] * limits.position_max[j]);
            let _ = h.client.start_motion(q);
            h.run_for(Duration::from_secs(3));
        }
        check_sent(&h, &limits, &workspace)?;
    }

    #[test]
    fn trajectories_respect_velocity_and_acceleration(
        a in proptest::array::uniform7(-2.0f64..2.0),
        b in proptest::array::uniform7(-2.0f64..2.0),
        dt in 0.001f64..0.01,
    ) {
        let limits = JointLimits::iiwa14();
        let traj = Trajectory::plan(&a, &b, &limits).unwrap();
        let n = (traj.duration() / dt).ceil() as usize + 2;
        let mut prev = traj.sample(0.0);
        prop_assert_eq!(prev, a);
        let mut prev_v = [0.0; 7];
        for k in 1..=n {
            let q = traj.sample(k as f64 * dt);
            for j in 0..7 {
                let v = (q[j] - prev[j]) / dt;
                prop_assert!(v.abs() <= limits.velocity[j] * (1.0 + 1e-9));
                prop_assert!(((v - prev_v[j]) / dt).abs() <= 2.0 * limits.acceleration[j] + 1e-6);
                prev_v[j] = v;
            }
            prev = q;
        }
        prop_assert_eq!(traj.sample(traj.duration() + dt), b);
    }

    #[test]
    fn arbitrary_bytes_never_panic_the_decoders(bytes in proptest::collection::vec(any::<u8>(), 0..1600)) {
        let _ = codec::decode_monitoring(&bytes);
        let _ = codec::decode_command(&bytes);
        let guard = SafetyGuard::new(JointLimits::iiwa7(), WorkspaceBox::unbounded(), toy_fk).unwrap();
        let mut s = ClientSession::new(SessionConfig::default(), guard);
        let now = std::time::Instant::now();
        let _ = s.handle_datagram(now, &bytes);
        let mut buf = [0u8; 1500];
        let _ = s.poll_transmit(now, &mut buf);
    }

    #[test]
    fn mutated_valid_datagrams_never_panic(
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6),
        cut in any::<prop::sample::Index>(),
    ) {
        let now = std::time::Instant::now();
        let mut sim = kuka_fri::SimulatedController::new(SimConfig::default(), now).unwrap();
        let mut buf = [0u8; 1500];
        let n = sim.poll_transmit(now, &mut buf).unwrap();
        let mut bytes = buf[..n].to_vec();
        for (i, v) in flips {
            let k = i.index(bytes.len());
            bytes[k] = v;
        }
        bytes.truncate(cut.index(bytes.len()) + 1);
        let guard = SafetyGuard::new(JointLimits::iiwa7(), WorkspaceBox::unbounded(), toy_fk).unwrap();
        let mut s = ClientSession::new(SessionConfig::default(), guard);
        if s.handle_datagram(now, &bytes).is_ok() {
            let _ = s.poll_transmit(now, &mut buf);
        }
    }
}
