//! A virtual-clock harness: the client session and the simulated controller joined by two
//! lossy links, advanced event by event (quinn-proto's test style).

#![allow(dead_code)]

pub mod sdk;

use std::collections::HashMap;
use std::time::{Duration, Instant};

use b2b_robot::{JointLimits, Joints, WorkspaceBox};
use kuka_fri::codec;
use kuka_fri::messages::MAX_DATAGRAM_SIZE;
use kuka_fri::{
    ClientSession, Event, Link, LinkConfig, SafetyGuard, SessionConfig, SessionState, SimConfig,
    SimulatedController,
};

/// A toy forward kinematics for tests (not the iiwa's): smooth, nonlinear, reaches ~1.2 m.
pub fn toy_fk(q: &Joints) -> [f64; 3] {
    let r = 0.4 * q[1].cos() + 0.4 * (q[1] + q[3]).cos() + 0.126 * (q[1] + q[3] + q[5]).cos();
    let z = 0.34 + 0.4 * q[1].sin() + 0.4 * (q[1] + q[3]).sin() + 0.1 * q[2].sin() * q[4].cos();
    [r * q[0].cos(), r * q[0].sin(), z]
}

/// One command the client sent, as seen on the wire.
#[derive(Clone, Copy, Debug)]
pub struct SentCommand {
    pub at: Instant,
    pub state: SessionState,
    pub sequence: u32,
    pub reflected: u32,
    pub q: Option<Joints>,
}

pub struct Harness {
    pub now: Instant,
    pub sim: SimulatedController,
    pub client: ClientSession,
    pub down: Link,
    pub up: Link,
    pub sent: Vec<SentCommand>,
    /// The interpolated position each controller message carried, by sequence counter.
    pub ipo_sent: HashMap<u32, Joints>,
    pub events: Vec<Event>,
    pub client_errors: usize,
    /// Deliver nothing from the controller while true (to provoke timeouts).
    pub cut: bool,
    buf: Vec<u8>,
}

impl Harness {
    pub fn new(sim_cfg: SimConfig, link: LinkConfig, guard: SafetyGuard) -> Self {
        let now = Instant::now();
        let sim = SimulatedController::new(sim_cfg, now).expect("valid sim config");
        let up_cfg = LinkConfig {
            seed: link.seed.wrapping_add(1000),
            ..link
        };
        Self {
            now,
            sim,
            client: ClientSession::new(SessionConfig::default(), guard),
            down: Link::new(link),
            up: Link::new(up_cfg),
            sent: Vec::new(),
            ipo_sent: HashMap::new(),
            events: Vec::new(),
            client_errors: 0,
            cut: false,
            buf: vec![0u8; MAX_DATAGRAM_SIZE],
        }
    }

    pub fn default_guard() -> SafetyGuard {
        SafetyGuard::new(
            JointLimits::iiwa7(),
            WorkspaceBox::new([-1.5, -1.5, -0.5], [1.5, 1.5, 1.5]).expect("box"),
            toy_fk,
        )
        .expect("guard")
    }

    /// Advances to the next event and processes everything due then.
    pub fn step(&mut self) {
        let mut next = self.sim.poll_timeout();
        for t in [
            self.down.next_delivery(),
            self.up.next_delivery(),
            self.client.poll_timeout(),
        ]
        .into_iter()
        .flatten()
        {
            next = next.min(t);
        }
        self.now = self.now.max(next);
        let now = self.now;
        while let Some(n) = self.sim.poll_transmit(now, &mut self.buf) {
            let (header, msg) =
                codec::decode_monitoring_with_header(&self.buf[..n]).expect("valid message");
            if let Some(ipo) = msg.ipo_data.and_then(|i| i.joint_position) {
                let ipo = codec::joints(codec::MONITORING, "ipo", &ipo).expect("7 joints");
                self.ipo_sent.insert(header.sequence_counter, ipo);
            }
            if !self.cut {
                self.down.send(now, &self.buf[..n]);
            }
        }
        while let Some(d) = self.down.poll_deliver(now) {
            match self.client.handle_datagram(now, &d) {
                Ok(ev) => self.events.push(ev),
                Err(_) => self.client_errors += 1,
            }
            if let Some(n) = self.client.poll_transmit(now, &mut self.buf) {
                let msg = codec::decode_command_with_header(&self.buf[..n])
                    .expect("client sends valid commands");
                let q = msg.1.command_data.and_then(|c| c.joint_position).map(|jv| {
                    codec::joints(codec::COMMAND, "jointPosition", &jv).expect("7 finite joints")
                });
                self.sent.push(SentCommand {
                    at: now,
                    state: self.client.state(),
                    sequence: msg.0.sequence_counter,
                    reflected: msg.0.reflected_sequence_counter,
                    q,
                });
                self.up.send(now, &self.buf[..n]);
            }
        }
        while let Some(d) = self.up.poll_deliver(now) {
            self.sim
                .handle_datagram(now, &d)
                .expect("sim accepts client commands");
        }
        self.client.handle_timeout(now);
        while let Some(e) = self.client.poll_event() {
            self.events.push(e);
        }
    }

    /// Steps until `cond` holds or `limit` of virtual time passes; returns whether it held.
    pub fn run_until(&mut self, limit: Duration, mut cond: impl FnMut(&mut Self) -> bool) -> bool {
        let end = self.now + limit;
        while self.now < end {
            if cond(self) {
                return true;
            }
            self.step();
        }
        cond(self)
    }

    pub fn run_for(&mut self, d: Duration) {
        let end = self.now + d;
        while self.now < end {
            self.step();
        }
    }

    pub fn motion_result(&self, id: u64) -> Option<Result<(), String>> {
        self.events.iter().find_map(|e| match e {
            Event::MotionFinished { id: i } if *i == id => Some(Ok(())),
            Event::MotionAborted { id: i, reason } if *i == id => Some(Err(reason.clone())),
            _ => None,
        })
    }

    /// Tries to bring the session to COMMANDING_ACTIVE; `false` when the
    /// controller does not get there within 5 s (it refuses command mode while the
    /// connection quality, judged from lost replies, is below GOOD).
    #[allow(dead_code)]
    pub fn try_reach_commanding(&mut self) -> bool {
        if !self.run_until(Duration::from_secs(5), |h| {
            h.client.state() == SessionState::MonitoringReady
        }) {
            return false;
        }
        self.sim.start_commanding();
        self.run_until(Duration::from_secs(5), |h| {
            h.client.state() == SessionState::CommandingActive
        })
    }

    /// Brings the session to COMMANDING_ACTIVE.
    #[allow(dead_code)]
    pub fn reach_commanding(&mut self) {
        assert!(
            self.run_until(Duration::from_secs(5), |h| h.client.state()
                == SessionState::MonitoringReady),
            "no MONITORING_READY: sim {:?} {:?}",
            self.sim.state(),
            self.sim.stats()
        );
        self.sim.start_commanding();
        assert!(
            self.run_until(Duration::from_secs(5), |h| h.client.state()
                == SessionState::CommandingActive),
            "no COMMANDING_ACTIVE: sim {:?}",
            self.sim.state()
        );
    }
}
