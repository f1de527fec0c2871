//! A test client that does what KUKA's FRI Client SDK and its example
//! `LBRJointSineOverlay` do, written from their documented behaviour (shared/facts.md §1.4),
//! not from our `ClientSession`, so the two cannot share one misreading of the controller:
//!
//! * every message runs the callback of its state: MONITORING_* → `monitor()` (command =
//!   `commandedJointPosition`), COMMANDING_WAIT → `waitForCommand()` (command = the
//!   interpolated position), COMMANDING_ACTIVE → `command()`: the example commands
//!   `getIpoJointPosition()` with `amplitude · sin(phi)` added on one joint, `phi`
//!   advancing by `2π · frequency · sampleTime` per call and reset to 0 on reaching
//!   MONITORING_READY;
//! * a reply goes out for every `receiveMultiplier`-th message, never in IDLE, with its own
//!   `sequenceCounter` counting up and `reflectedSequenceCounter` = the message's counter.
//!
//! Knobs make it misbehave the ways the conformance tests need: skip replies, go silent,
//! start away from the interpolated position, jump.

use std::f64::consts::TAU;
use std::time::{Duration, Instant};

use b2b_robot::Joints;
use kuka_fri::codec::{self, Header};
use kuka_fri::messages::{
    FriCommandMessage, JointValues, LBR_COMMAND_MESSAGE_ID, LBR_MONITOR_MESSAGE_ID,
    MAX_DATAGRAM_SIZE, MessageCommandData,
};
use kuka_fri::{ConnectionQuality, Link, LinkConfig, SessionState, SimConfig, SimulatedController};

/// What the client saw in one monitoring message.
#[derive(Clone, Copy, Debug)]
pub struct Seen {
    pub sequence: u32,
    pub state: SessionState,
    pub quality: ConnectionQuality,
    pub ipo: Joints,
    pub commanded: Joints,
    pub measured: Joints,
}

/// One command the client sent.
#[derive(Clone, Copy, Debug)]
pub struct Sent {
    pub sequence: u32,
    pub reflected: u32,
    pub state: SessionState,
    pub q: Joints,
}

/// KUKA's `LBRJointSineOverlay`, as a sans-I/O test client.
#[derive(Debug)]
pub struct SineOverlayClient {
    /// The joint the sine is put on (index 3 is KUKA's joint 4).
    pub joint: usize,
    /// Sine amplitude (rad).
    pub amplitude: f64,
    /// Sine frequency (Hz).
    pub frequency: f64,
    /// Leave out every `skip_every`-th reply that is due.
    pub skip_every: Option<u64>,
    /// Answer nothing.
    pub silent: bool,
    /// Added to the joint in every COMMANDING_ACTIVE command from the `n`-th one on.
    pub jump: Option<(u64, f64)>,
    /// Added to the joint in the first COMMANDING_ACTIVE command.
    pub first_offset: f64,
    sequence: u32,
    counter: u32,
    replies_due: u64,
    active_commands: u64,
    state: SessionState,
    phi: f64,
    step: f64,
    pub seen: Vec<Seen>,
    pub sent: Vec<Sent>,
}

impl SineOverlayClient {
    /// The example's defaults: joint 4, 0.04 rad at 0.25 Hz.
    pub fn lbr_joint_sine_overlay() -> Self {
        Self {
            joint: 3,
            amplitude: 0.04,
            frequency: 0.25,
            skip_every: None,
            silent: false,
            jump: None,
            first_offset: 0.0,
            sequence: 0,
            counter: 0,
            replies_due: 0,
            active_commands: 0,
            state: SessionState::Idle,
            phi: 0.0,
            step: 0.0,
            seen: Vec::new(),
            sent: Vec::new(),
        }
    }

    /// Takes one monitoring datagram; returns the length of the reply written to `out`.
    pub fn on_datagram(&mut self, bytes: &[u8], out: &mut [u8]) -> Option<usize> {
        let (header, msg) = codec::decode_monitoring_with_header(bytes).expect("valid message");
        assert_eq!(header.message_identifier, LBR_MONITOR_MESSAGE_ID);
        let ci = msg.connection_info.expect("connectionInfo");
        let state = SessionState::try_from(ci.session_state.expect("state")).expect("state");
        let quality = ConnectionQuality::try_from(ci.quality.expect("quality")).expect("quality");
        let sample_time = f64::from(ci.send_period.expect("sendPeriod")) * 1e-3;
        let multiplier = ci.receive_multiplier.expect("receiveMultiplier").max(1);
        let j = |v: Option<&JointValues>, f| {
            codec::joints(codec::MONITORING, f, v.expect("joint values")).expect("7 joints")
        };
        let ipo = j(
            msg.ipo_data
                .as_ref()
                .and_then(|i| i.joint_position.as_ref()),
            "ipo",
        );
        let md = msg.monitor_data.as_ref().expect("monitorData");
        let commanded = j(md.commanded_joint_position.as_ref(), "commanded");
        let measured = j(md.measured_joint_position.as_ref(), "measured");
        self.seen.push(Seen {
            sequence: header.sequence_counter,
            state,
            quality,
            ipo,
            commanded,
            measured,
        });
        if state != self.state {
            // onStateChange: the example resets its sine on reaching MONITORING_READY.
            if state == SessionState::MonitoringReady {
                self.phi = 0.0;
                self.step = TAU * self.frequency * sample_time;
            }
            self.state = state;
        }
        let q = match state {
            SessionState::Idle => return None,
            SessionState::MonitoringWait | SessionState::MonitoringReady => commanded,
            SessionState::CommandingWait => ipo,
            SessionState::CommandingActive => {
                let mut q = ipo;
                q[self.joint] += self.amplitude * self.phi.sin();
                self.phi += self.step;
                if self.phi >= TAU {
                    self.phi -= TAU;
                }
                self.active_commands += 1;
                if self.active_commands == 1 {
                    q[self.joint] += self.first_offset;
                }
                if let Some((from, by)) = self.jump
                    && self.active_commands >= from
                {
                    q[self.joint] += by;
                }
                q
            }
        };
        self.counter += 1;
        if self.counter < multiplier {
            return None;
        }
        self.counter = 0;
        self.replies_due += 1;
        if self.silent
            || self
                .skip_every
                .is_some_and(|k| self.replies_due.is_multiple_of(k))
        {
            return None;
        }
        let reply = FriCommandMessage {
            header: Some(
                Header {
                    message_identifier: LBR_COMMAND_MESSAGE_ID,
                    sequence_counter: self.sequence,
                    reflected_sequence_counter: header.sequence_counter,
                }
                .to_message(),
            ),
            command_data: Some(MessageCommandData {
                joint_position: Some(JointValues::from_array(&q)),
                ..Default::default()
            }),
            end_of_message_data: None,
        };
        let n = codec::encode_command(&reply, out).expect("encodes");
        self.sent.push(Sent {
            sequence: self.sequence,
            reflected: header.sequence_counter,
            state,
            q,
        });
        self.sequence = self.sequence.wrapping_add(1);
        Some(n)
    }

    /// The last state seen.
    pub fn state(&self) -> SessionState {
        self.state
    }
}

/// The sine client and the simulated controller on a virtual clock, joined by two links.
pub struct SdkHarness {
    pub now: Instant,
    pub sim: SimulatedController,
    pub client: SineOverlayClient,
    pub down: Link,
    pub up: Link,
    buf: Vec<u8>,
    out: Vec<u8>,
}

impl SdkHarness {
    pub fn new(cfg: SimConfig, down: LinkConfig, up: LinkConfig) -> Self {
        let now = Instant::now();
        Self {
            now,
            sim: SimulatedController::new(cfg, now).expect("valid sim config"),
            client: SineOverlayClient::lbr_joint_sine_overlay(),
            down: Link::new(down),
            up: Link::new(up),
            buf: vec![0u8; MAX_DATAGRAM_SIZE],
            out: vec![0u8; MAX_DATAGRAM_SIZE],
        }
    }

    /// A link with a fixed one-way delay.
    pub fn delay(d: Duration) -> LinkConfig {
        LinkConfig {
            delay: d,
            ..LinkConfig::perfect()
        }
    }

    /// Advances to the next event and processes everything due then.
    pub fn step(&mut self) {
        let mut next = self.sim.poll_timeout();
        for t in [self.down.next_delivery(), self.up.next_delivery()]
            .into_iter()
            .flatten()
        {
            next = next.min(t);
        }
        self.now = self.now.max(next);
        let now = self.now;
        while let Some(n) = self.sim.poll_transmit(now, &mut self.buf) {
            self.down.send(now, &self.buf[..n]);
        }
        while let Some(d) = self.down.poll_deliver(now) {
            if let Some(n) = self.client.on_datagram(&d, &mut self.out) {
                self.up.send(now, &self.out[..n]);
            }
        }
        while let Some(d) = self.up.poll_deliver(now) {
            self.sim
                .handle_datagram(now, &d)
                .expect("the controller decodes every command");
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

    /// Steps for `d` of virtual time, calling `each` after every step.
    pub fn run_for(&mut self, d: Duration, mut each: impl FnMut(&mut Self)) {
        let end = self.now + d;
        while self.now < end {
            self.step();
            each(self);
        }
    }
}
