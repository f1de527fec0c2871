//! A simulated KUKA controller (the robot side of FRI) and a lossy network link.
//!
//! # Why it lives here, on the same types
//! The simulator is the client's test partner and the project's stand-in for hardware. It
//! encodes and decodes with the same [`crate::codec`] and is sans-I/O like the client: it
//! is fed command datagrams and instants and asked for monitoring datagrams, so a test can
//! run thousands of cycles on a virtual clock in milliseconds, and the `fri-sim-controller`
//! binary puts the very same object behind a UDP socket.
//!
//! # What it models
//! * A monitoring message every `send_period_ms`, with measured positions = true positions
//!   plus Gaussian encoder noise, the interpolator/commanded position, a Unix time stamp of the
//!   simulated controller clock, and the session state and connection quality.
//! * The arm follows its target within velocity and acceleration limits (braking so it never
//!   overshoots). The target is the robot application's ([`SimulatedController::move_app_to`])
//!   except in COMMANDING_ACTIVE, where it is the client's last accepted command.
//! * Session states: IDLE ⇄ MONITORING_WAIT → MONITORING_READY (once a full window of replies
//!   arrived with GOOD quality) → COMMANDING_WAIT (on [`SimulatedController::start_commanding`])
//!   → COMMANDING_ACTIVE (after the client echoed the interpolator position for a few cycles).
//!   Quality below GOOD drops back to MONITORING_WAIT and aborts commanding, as the real
//!   controller aborts an FRI overlay.
//! * Connection quality is the ratio of replies received to replies expected over a sliding
//!   window (a simplification: the real controller also weighs latency and jitter).
//! * Commands are checked like the real controller would fault on them: outside the joint
//!   limits or faster than the velocity limit → counted in [`SimStats::violations`] and ignored.
//!
//! [`Link`] models one direction of the network: seeded loss, delay with jitter, and
//! reordering (a fraction of datagrams delayed past later ones).

use std::cmp::Reverse;
use std::collections::{BinaryHeap, VecDeque};
use std::time::{Duration, Instant};

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use b2b_robot::{JointLimits, Joints};

use crate::codec;
use crate::error::{FriError, Result};
use crate::joints::ControllerTime;
use crate::messages::{
    ClientCommandMode, ConnectionInfo, ConnectionQuality, ControlMode, DriveState,
    FriMonitoringMessage, JointValues, LBR_MONITOR_MESSAGE_ID, MessageIpoData, MessageMonitorData,
    NUM_JOINTS, OperationMode, OverlayType, RobotInfo, SafetyState, SessionState, TimeStamp,
};

/// Settings of a [`SimulatedController`].
#[derive(Clone, Debug)]
pub struct SimConfig {
    /// Send period (ms), 1..=100.
    pub send_period_ms: u32,
    /// The client answers every `receive_multiplier`-th message.
    pub receive_multiplier: u32,
    /// Position and velocity limits the arm moves within and checks commands against.
    pub limits: JointLimits,
    /// The arm's own acceleration capability (rad/s²), above the planning limits in
    /// [`JointLimits::acceleration`] as on a real arm.
    pub arm_acceleration: f64,
    /// Initial joint positions (rad).
    pub initial_q: Joints,
    /// Standard deviation of the encoder noise on measured positions (rad).
    pub encoder_noise: f64,
    /// Seed of the noise generator.
    pub seed: u64,
    /// Cycles over which the reply ratio is measured.
    pub quality_window: u32,
    /// Reply ratio at or above which quality is GOOD.
    pub good_ratio: f64,
    /// Reply ratio at or above which quality is EXCELLENT.
    pub excellent_ratio: f64,
    /// Cycles the client must echo the interpolator position in COMMANDING_WAIT.
    pub commanding_wait_cycles: u32,
    /// Controller clock (Unix time) at the simulator's start.
    pub clock_at_start: ControllerTime,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            send_period_ms: 5,
            receive_multiplier: 1,
            limits: JointLimits::iiwa7(),
            arm_acceleration: 10.0,
            initial_q: [0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0],
            encoder_noise: 2e-5,
            seed: 1,
            quality_window: 50,
            good_ratio: 0.6,
            excellent_ratio: 0.85,
            commanding_wait_cycles: 5,
            clock_at_start: ControllerTime {
                sec: 1_700_000_000,
                nanosec: 0,
            },
        }
    }
}

/// Counters of the simulator.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SimStats {
    /// Monitoring messages produced.
    pub sent: u64,
    /// Valid command messages received.
    pub commands: u64,
    /// Datagrams rejected by the codec.
    pub malformed: u64,
    /// Reordered or duplicated commands ignored.
    pub stale: u64,
    /// COMMANDING_ACTIVE commands outside joint or velocity limits (a real controller faults).
    pub violations: u64,
    /// Commanding phases aborted because the quality dropped.
    pub aborted: u64,
    /// Replies whose reflected sequence counter was never sent.
    pub bad_reflections: u64,
    /// Cycles (outside IDLE) that closed with no reply for the last `receive_multiplier`
    /// cycles: a reply the controller did not get in time, late or lost. These are the
    /// zeros of the connection-quality window; a real controller counts them as missing.
    pub missed_replies: u64,
    /// Of [`missed_replies`](Self::missed_replies), those that followed a late send of the
    /// controller's own, which left the client less than half a period to answer.
    pub missed_after_late_send: u64,
    /// Messages sent more than half a period after they were due (the controller's own
    /// cycle ran late).
    pub late_sends: u64,
    /// Replies that arrived after `receive_multiplier` further messages had been sent.
    pub late_replies: u64,
    /// Longest delay of a send past its due time.
    pub max_send_lateness: Duration,
    /// Longest time from sending a message to taking in the reply that reflects it (a
    /// cyclic driver takes replies in at its next cycle, so this is then about a period).
    pub max_reply_latency: Duration,
}

/// The robot side of FRI (sans-I/O).
#[derive(Debug)]
pub struct SimulatedController {
    cfg: SimConfig,
    rng: StdRng,
    start: Instant,
    next_send: Instant,
    seq: u32,
    last_client_seq: Option<u32>,
    state: SessionState,
    quality: ConnectionQuality,
    q: Joints,
    v: Joints,
    app_target: Joints,
    command: Option<(Joints, u32)>,
    /// Per-cycle velocity of the command in force, for bridging lost commands.
    command_rate: Joints,
    window: VecDeque<u32>,
    replies_this_cycle: u32,
    echo_ok_cycles: u32,
    echo_ok_this_cycle: bool,
    commanding_requested: bool,
    /// Cycles since the last one in which a reply arrived.
    silent_cycles: u32,
    /// Whether the newest message was sent late.
    last_send_late: bool,
    /// Send instants of the newest messages, indexed by sequence counter.
    sent_at: [Option<Instant>; SENT_AT_SLOTS],
    stats: SimStats,
}

/// Messages whose send instant is kept to measure reply latency.
const SENT_AT_SLOTS: usize = 16;

/// Largest backward step of the client's sequence counter treated as reordering.
const REORDER_WINDOW: u32 = 64;

impl SimulatedController {
    /// A controller in MONITORING_WAIT (an FRI session has just been opened), whose first
    /// message is due at `now`.
    pub fn new(cfg: SimConfig, now: Instant) -> Result<Self> {
        if !(1..=100).contains(&cfg.send_period_ms) {
            return Err(FriError::InvalidValue {
                what: "send period",
                value: format!("{} ms", cfg.send_period_ms),
            });
        }
        if !(1..=100).contains(&cfg.receive_multiplier)
            || cfg.send_period_ms * cfg.receive_multiplier > 100
        {
            return Err(FriError::InvalidValue {
                what: "receive multiplier",
                value: format!(
                    "{} (receive period must be 1..=100 ms)",
                    cfg.receive_multiplier
                ),
            });
        }
        if !(cfg.arm_acceleration.is_finite() && cfg.arm_acceleration > 0.0) {
            return Err(FriError::InvalidValue {
                what: "arm acceleration",
                value: cfg.arm_acceleration.to_string(),
            });
        }
        if !(cfg.encoder_noise.is_finite() && cfg.encoder_noise >= 0.0) {
            return Err(FriError::InvalidValue {
                what: "encoder noise",
                value: cfg.encoder_noise.to_string(),
            });
        }
        cfg.limits.validate()?;
        cfg.limits.check_position(&cfg.initial_q, 0.0)?;
        Ok(Self {
            rng: StdRng::seed_from_u64(cfg.seed),
            start: now,
            next_send: now,
            seq: 0,
            last_client_seq: None,
            state: SessionState::MonitoringWait,
            quality: ConnectionQuality::Poor,
            q: cfg.initial_q,
            v: [0.0; NUM_JOINTS],
            app_target: cfg.initial_q,
            command: None,
            command_rate: [0.0; NUM_JOINTS],
            window: VecDeque::new(),
            replies_this_cycle: 0,
            echo_ok_cycles: 0,
            echo_ok_this_cycle: false,
            commanding_requested: false,
            silent_cycles: 0,
            last_send_late: false,
            sent_at: [None; SENT_AT_SLOTS],
            stats: SimStats::default(),
            cfg,
        })
    }

    /// The session state.
    pub fn state(&self) -> SessionState {
        self.state
    }

    /// The connection quality.
    pub fn quality(&self) -> ConnectionQuality {
        self.quality
    }

    /// True joint positions (rad).
    pub fn q(&self) -> Joints {
        self.q
    }

    /// Counters.
    pub fn stats(&self) -> SimStats {
        self.stats
    }

    /// The configuration.
    pub fn config(&self) -> &SimConfig {
        &self.cfg
    }

    /// Send period as a duration.
    pub fn send_period(&self) -> Duration {
        Duration::from_millis(u64::from(self.cfg.send_period_ms))
    }

    /// The robot application moves the arm (outside COMMANDING_ACTIVE), e.g. a Sunrise motion
    /// while the client only monitors. Clamped to the joint limits.
    pub fn move_app_to(&mut self, q: Joints) {
        let l = &self.cfg.limits;
        for (j, (dst, &v)) in self.app_target.iter_mut().zip(&q).enumerate() {
            if v.is_finite() {
                *dst = v.clamp(l.position_min[j], l.position_max[j]);
            }
        }
    }

    /// The robot application starts a motion with an FRI joint overlay.
    pub fn start_commanding(&mut self) {
        self.commanding_requested = true;
    }

    /// The overlay motion ends; back to MONITORING_READY.
    pub fn stop_commanding(&mut self) {
        self.commanding_requested = false;
        if matches!(
            self.state,
            SessionState::CommandingWait | SessionState::CommandingActive
        ) {
            self.leave_commanding(SessionState::MonitoringReady);
        }
    }

    /// The FRI session is closed: IDLE.
    pub fn close_session(&mut self) {
        self.commanding_requested = false;
        self.leave_commanding(SessionState::Idle);
        self.window.clear();
        self.quality = ConnectionQuality::Poor;
    }

    /// A new FRI session is opened: MONITORING_WAIT.
    pub fn open_session(&mut self) {
        if self.state == SessionState::Idle {
            self.state = SessionState::MonitoringWait;
            self.window.clear();
        }
    }

    fn leave_commanding(&mut self, to: SessionState) {
        self.state = to;
        self.command = None;
        self.echo_ok_cycles = 0;
        self.app_target = self.q;
    }

    /// When the next monitoring message is due.
    pub fn poll_timeout(&self) -> Instant {
        self.next_send
    }

    /// Handles a command datagram from the client, received at `now`.
    pub fn handle_datagram(&mut self, now: Instant, bytes: &[u8]) -> Result<()> {
        let (header, msg) = match codec::decode_command_with_header(bytes) {
            Ok(v) => v,
            Err(e) => {
                self.stats.malformed += 1;
                return Err(e);
            }
        };
        if let Some(last) = self.last_client_seq {
            let behind = last.wrapping_sub(header.sequence_counter);
            if behind <= REORDER_WINDOW {
                self.stats.stale += 1;
                return Ok(());
            }
        }
        self.last_client_seq = Some(header.sequence_counter);
        if header.reflected_sequence_counter.wrapping_sub(self.seq) < u32::MAX / 2 {
            // Reflects a counter we have not sent yet.
            self.stats.bad_reflections += 1;
        }
        self.stats.commands += 1;
        self.audit_reply(now, header.reflected_sequence_counter);
        if self.state == SessionState::Idle {
            return Ok(());
        }
        self.replies_this_cycle += 1;
        let q = match msg.command_data.and_then(|c| c.joint_position) {
            Some(jv) => codec::joints(codec::COMMAND, "commandData.jointPosition", &jv)?,
            None => return Ok(()),
        };
        match self.state {
            SessionState::CommandingWait => {
                let close = q.iter().zip(&self.q).all(|(a, b)| (a - b).abs() < 1e-3);
                self.echo_ok_this_cycle |= close;
            }
            SessionState::CommandingActive => {
                let reflected = header.reflected_sequence_counter;
                let ok_pos = self.cfg.limits.check_position(&q, 0.0).is_ok();
                let ok_vel = match self.command {
                    Some((prev, prev_seq)) => {
                        let cycles = reflected.wrapping_sub(prev_seq);
                        if cycles == 0 || cycles > u32::MAX / 2 {
                            // Older than the command in force: out of order, ignore.
                            self.stats.stale += 1;
                            return Ok(());
                        }
                        let dt = f64::from(cycles) * f64::from(self.cfg.send_period_ms) * 1e-3;
                        (0..NUM_JOINTS).all(|j| {
                            (q[j] - prev[j]).abs()
                                <= self.cfg.limits.velocity[j] * dt * (1.0 + 1e-6)
                        })
                    }
                    None => (0..NUM_JOINTS).all(|j| (q[j] - self.q[j]).abs() < 1e-2),
                };
                if ok_pos && ok_vel {
                    self.command_rate = match self.command {
                        Some((prev, prev_seq)) => {
                            let cycles = f64::from(reflected.wrapping_sub(prev_seq));
                            std::array::from_fn(|j| (q[j] - prev[j]) / cycles)
                        }
                        None => [0.0; NUM_JOINTS],
                    };
                    self.command = Some((q, reflected));
                } else {
                    self.stats.violations += 1;
                }
            }
            _ => {}
        }
        Ok(())
    }

    /// Reply latency and lateness of a reply reflecting message `reflected`.
    fn audit_reply(&mut self, now: Instant, reflected: u32) {
        // `self.seq` is the next message's counter: messages up to `self.seq - 1` are out.
        let behind = self.seq.wrapping_sub(reflected);
        if behind == 0 || behind > u32::MAX / 2 {
            return; // Reflects a message not sent yet (counted as a bad reflection).
        }
        if behind > self.cfg.receive_multiplier {
            self.stats.late_replies += 1;
        }
        if (behind as usize) <= SENT_AT_SLOTS
            && let Some(sent) = self.sent_at[reflected as usize % SENT_AT_SLOTS]
        {
            let latency = now.saturating_duration_since(sent);
            self.stats.max_reply_latency = self.stats.max_reply_latency.max(latency);
        }
    }

    /// Counts a missed reply when `receive_multiplier` cycles closed without one, and the
    /// lateness of the send at `now` of a message due at `due`.
    fn audit_cycle(&mut self, now: Instant, due: Instant) {
        // Before the first message nothing was owed.
        if self.state != SessionState::Idle && self.stats.sent > 0 {
            if self.replies_this_cycle == 0 {
                self.silent_cycles += 1;
                if self.silent_cycles >= self.cfg.receive_multiplier {
                    self.silent_cycles = 0;
                    self.stats.missed_replies += 1;
                    if self.last_send_late {
                        self.stats.missed_after_late_send += 1;
                    }
                }
            } else {
                self.silent_cycles = 0;
            }
        }
        let lateness = now.saturating_duration_since(due);
        self.last_send_late = lateness > self.send_period() / 2;
        if self.last_send_late {
            self.stats.late_sends += 1;
        }
        self.stats.max_send_lateness = self.stats.max_send_lateness.max(lateness);
        self.sent_at[self.seq as usize % SENT_AT_SLOTS] = Some(now);
    }

    fn gaussian(&mut self) -> f64 {
        // Box–Muller.
        let u1: f64 = self.rng.random::<f64>().max(f64::MIN_POSITIVE);
        let u2: f64 = self.rng.random::<f64>();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    fn step_arm(&mut self, dt: f64) {
        let l = self.cfg.limits;
        let (target, target_rate) = match (self.state, self.command) {
            (SessionState::CommandingActive, Some((q, reflected))) => {
                // The command answering message r is applied in cycle r + 1. When newer ones
                // are missing (lost or late), extrapolate the command's motion for up to
                // three cycles, as an interpolator bridging gaps would, then hold.
                let missing = self.seq.wrapping_sub(reflected).saturating_sub(1);
                let rate = if missing < 3 {
                    self.command_rate
                } else {
                    [0.0; NUM_JOINTS]
                };
                let n = f64::from(missing.min(3));
                let mut t = q;
                for j in 0..NUM_JOINTS {
                    t[j] = (q[j] + self.command_rate[j] * n)
                        .clamp(l.position_min[j], l.position_max[j]);
                }
                (t, rate)
            }
            (SessionState::CommandingActive | SessionState::CommandingWait, None) => {
                (self.q, [0.0; NUM_JOINTS])
            }
            _ => (self.app_target, [0.0; NUM_JOINTS]),
        };
        for j in 0..NUM_JOINTS {
            let e = target[j] - self.q[j];
            let (vmax, amax) = (l.velocity[j], self.cfg.arm_acceleration);
            // Close the error no faster than in one cycle, and slowly enough to brake in time
            // (discrete-time stopping distance), on top of the target's own velocity.
            let adt = amax * dt;
            let closing =
                (e.abs() / dt).min(adt * ((0.25 + 2.0 * e.abs() / (adt * dt)).sqrt() - 0.5));
            let desired = target_rate[j] / dt + closing.copysign(e);
            let v = desired
                .clamp(self.v[j] - adt, self.v[j] + adt)
                .clamp(-vmax, vmax);
            self.v[j] = v;
            self.q[j] = (self.q[j] + v * dt).clamp(l.position_min[j], l.position_max[j]);
        }
    }

    fn update_quality_and_state(&mut self) {
        let window = self.cfg.quality_window.max(1) as usize;
        self.window.push_back(self.replies_this_cycle);
        self.replies_this_cycle = 0;
        while self.window.len() > window {
            self.window.pop_front();
        }
        let echo_ok = std::mem::take(&mut self.echo_ok_this_cycle);
        if self.state == SessionState::Idle {
            return;
        }
        let received: u32 = self.window.iter().sum();
        let expected = self.window.len() as f64 / f64::from(self.cfg.receive_multiplier);
        let ratio = f64::from(received) / expected.max(1.0);
        let full = self.window.len() == window;
        self.quality = if ratio >= self.cfg.excellent_ratio {
            ConnectionQuality::Excellent
        } else if ratio >= self.cfg.good_ratio {
            ConnectionQuality::Good
        } else if ratio >= self.cfg.good_ratio / 2.0 {
            ConnectionQuality::Fair
        } else {
            ConnectionQuality::Poor
        };
        let good = full && self.quality >= ConnectionQuality::Good;
        match self.state {
            SessionState::Idle => {}
            SessionState::MonitoringWait => {
                if good {
                    self.state = SessionState::MonitoringReady;
                }
            }
            SessionState::MonitoringReady => {
                if !good {
                    self.state = SessionState::MonitoringWait;
                } else if self.commanding_requested {
                    self.state = SessionState::CommandingWait;
                    self.echo_ok_cycles = 0;
                }
            }
            SessionState::CommandingWait | SessionState::CommandingActive => {
                if !good {
                    self.stats.aborted += 1;
                    self.commanding_requested = false;
                    self.leave_commanding(SessionState::MonitoringWait);
                } else if self.state == SessionState::CommandingWait {
                    if echo_ok {
                        self.echo_ok_cycles += 1;
                    }
                    if self.echo_ok_cycles >= self.cfg.commanding_wait_cycles {
                        self.state = SessionState::CommandingActive;
                        self.command = None;
                    }
                }
            }
        }
    }

    /// If a monitoring message is due at `now`, advances the simulation one cycle, writes
    /// the message into `buf` and returns its length. A cycle that runs a period or more
    /// late skips the cycles it missed and starts a new period at `now`: like a real
    /// controller, it never sends two messages less than a period apart, which would leave
    /// the client no time to answer the first.
    pub fn poll_transmit(&mut self, now: Instant, buf: &mut [u8]) -> Option<usize> {
        if now < self.next_send {
            return None;
        }
        let period = self.send_period();
        let due = self.next_send;
        self.next_send += period;
        if now >= self.next_send {
            self.next_send = now + period;
        }
        self.audit_cycle(now, due);
        let dt = period.as_secs_f64();
        self.step_arm(dt);
        self.update_quality_and_state();
        let msg = self.monitoring_message(now);
        self.seq = self.seq.wrapping_add(1);
        match codec::encode_monitoring(&msg, buf) {
            Ok(n) => {
                self.stats.sent += 1;
                Some(n)
            }
            Err(err) => {
                tracing::error!(%err, "simulated controller could not encode");
                None
            }
        }
    }

    /// The monitoring message for the current state (sequence counter = the next one).
    pub fn monitoring_message(&mut self, now: Instant) -> FriMonitoringMessage {
        let mut measured = self.q;
        for m in measured.iter_mut() {
            *m += self.cfg.encoder_noise * self.gaussian();
        }
        let stamp = ControllerTime::from_duration(
            self.cfg.clock_at_start.as_duration() + now.saturating_duration_since(self.start),
        );
        let commanding = matches!(
            self.state,
            SessionState::CommandingWait | SessionState::CommandingActive
        );
        FriMonitoringMessage {
            header: Some(
                codec::Header {
                    message_identifier: LBR_MONITOR_MESSAGE_ID,
                    sequence_counter: self.seq,
                    reflected_sequence_counter: self.last_client_seq.unwrap_or(0),
                }
                .to_message(),
            ),
            robot_info: Some(RobotInfo {
                number_of_joints: Some(NUM_JOINTS as i32),
                safety_state: Some(SafetyState::NormalOperation as i32),
                drive_state: vec![DriveState::Active as i32; NUM_JOINTS],
                operation_mode: Some(OperationMode::AutomaticMode as i32),
                control_mode: Some(ControlMode::PositionControlMode as i32),
            }),
            monitor_data: Some(MessageMonitorData {
                measured_joint_position: Some(JointValues::from_array(&measured)),
                measured_torque: Some(JointValues::from_array(&[0.0; NUM_JOINTS])),
                commanded_joint_position: Some(JointValues::from_array(&self.q)),
                commanded_torque: Some(JointValues::from_array(&[0.0; NUM_JOINTS])),
                external_torque: Some(JointValues::from_array(&[0.0; NUM_JOINTS])),
                read_io_request: Vec::new(),
                timestamp: Some(TimeStamp {
                    sec: Some(stamp.sec),
                    nanosec: Some(stamp.nanosec),
                }),
            }),
            connection_info: Some(ConnectionInfo {
                session_state: Some(self.state as i32),
                quality: Some(self.quality as i32),
                send_period: Some(self.cfg.send_period_ms),
                receive_multiplier: Some(self.cfg.receive_multiplier),
            }),
            ipo_data: Some(MessageIpoData {
                joint_position: Some(JointValues::from_array(&self.q)),
                client_command_mode: Some(ClientCommandMode::Position as i32),
                overlay_type: Some(if commanding {
                    OverlayType::Joint
                } else {
                    OverlayType::NoOverlay
                } as i32),
                tracking_performance: Some(if self.state == SessionState::CommandingActive {
                    1.0
                } else {
                    0.0
                }),
            }),
            requested_transformations: Vec::new(),
            end_of_message_data: None,
        }
    }
}

/// Impairments of one direction of a [`Link`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinkConfig {
    /// Probability that a datagram is dropped.
    pub loss: f64,
    /// Fixed one-way delay.
    pub delay: Duration,
    /// Extra uniformly distributed delay in `[0, jitter]`.
    pub jitter: Duration,
    /// Probability that a datagram is held back by `reorder_delay` (so later ones overtake it).
    pub reorder: f64,
    /// Extra delay of a reordered datagram.
    pub reorder_delay: Duration,
    /// RNG seed.
    pub seed: u64,
}

impl LinkConfig {
    /// A perfect link (no loss, no delay).
    pub fn perfect() -> Self {
        Self {
            loss: 0.0,
            delay: Duration::ZERO,
            jitter: Duration::ZERO,
            reorder: 0.0,
            reorder_delay: Duration::ZERO,
            seed: 0,
        }
    }
}

/// Counters of a [`Link`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Datagrams offered.
    pub sent: u64,
    /// Datagrams dropped.
    pub dropped: u64,
    /// Datagrams held back to be reordered.
    pub reordered: u64,
    /// Datagrams delivered.
    pub delivered: u64,
}

/// One direction of a simulated network with loss, delay, jitter and reordering.
#[derive(Debug)]
pub struct Link {
    cfg: LinkConfig,
    rng: StdRng,
    queue: BinaryHeap<Reverse<(Instant, u64, Vec<u8>)>>,
    order: u64,
    stats: LinkStats,
}

impl Link {
    /// A link with the given impairments.
    pub fn new(cfg: LinkConfig) -> Self {
        Self {
            rng: StdRng::seed_from_u64(cfg.seed),
            cfg,
            queue: BinaryHeap::new(),
            order: 0,
            stats: LinkStats::default(),
        }
    }

    /// Counters.
    pub fn stats(&self) -> LinkStats {
        self.stats
    }

    /// Offers a datagram at `now`.
    pub fn send(&mut self, now: Instant, bytes: &[u8]) {
        self.stats.sent += 1;
        if self.rng.random::<f64>() < self.cfg.loss {
            self.stats.dropped += 1;
            return;
        }
        let mut delay = self.cfg.delay + self.cfg.jitter.mul_f64(self.rng.random::<f64>());
        if self.rng.random::<f64>() < self.cfg.reorder {
            self.stats.reordered += 1;
            delay += self.cfg.reorder_delay;
        }
        self.order += 1;
        self.queue
            .push(Reverse((now + delay, self.order, bytes.to_vec())));
    }

    /// When the next datagram arrives.
    pub fn next_delivery(&self) -> Option<Instant> {
        self.queue.peek().map(|Reverse((t, _, _))| *t)
    }

    /// A datagram that has arrived by `now`, earliest first.
    pub fn poll_deliver(&mut self, now: Instant) -> Option<Vec<u8>> {
        if self.next_delivery()? > now {
            return None;
        }
        let Reverse((_, _, bytes)) = self.queue.pop()?;
        self.stats.delivered += 1;
        Some(bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn monitoring_message_is_a_realistic_size_and_decodes() {
        let now = Instant::now();
        let mut sim = SimulatedController::new(SimConfig::default(), now).unwrap();
        let mut buf = [0u8; crate::messages::MAX_DATAGRAM_SIZE];
        let n = sim.poll_transmit(now, &mut buf).unwrap();
        assert!((400..600).contains(&n), "{n} bytes");
        let msg = codec::decode_monitoring(&buf[..n]).unwrap();
        assert_eq!(msg.header.and_then(|h| h.sequence_counter), Some(0));
        assert!(
            sim.poll_transmit(now, &mut buf).is_none(),
            "one message per period"
        );
    }

    #[test]
    fn link_is_deterministic_per_seed_and_loses_about_the_configured_share() {
        let cfg = LinkConfig {
            loss: 0.05,
            seed: 9,
            ..LinkConfig::perfect()
        };
        let now = Instant::now();
        let run = || {
            let mut l = Link::new(cfg);
            for _ in 0..10_000 {
                l.send(now, &[1]);
            }
            l.stats().dropped
        };
        let dropped = run();
        assert_eq!(dropped, run());
        assert!((400..600).contains(&dropped), "{dropped}");
    }

    /// A reply reflecting `reflected`, with client sequence counter `seq`.
    fn reply(seq: u32, reflected: u32, q: &Joints) -> Vec<u8> {
        use crate::messages::{FriCommandMessage, LBR_COMMAND_MESSAGE_ID, MessageCommandData};
        let msg = FriCommandMessage {
            header: Some(
                codec::Header {
                    message_identifier: LBR_COMMAND_MESSAGE_ID,
                    sequence_counter: seq,
                    reflected_sequence_counter: reflected,
                }
                .to_message(),
            ),
            command_data: Some(MessageCommandData {
                joint_position: Some(JointValues::from_array(q)),
                ..Default::default()
            }),
            end_of_message_data: None,
        };
        let mut buf = [0u8; crate::messages::MAX_DATAGRAM_SIZE];
        let n = codec::encode_command(&msg, &mut buf).unwrap();
        buf[..n].to_vec()
    }

    #[test]
    fn audit_blames_a_missed_reply_on_the_side_that_was_late() {
        let t0 = Instant::now();
        let mut sim = SimulatedController::new(SimConfig::default(), t0).unwrap();
        let q = sim.q();
        let mut buf = [0u8; crate::messages::MAX_DATAGRAM_SIZE];
        let period = sim.send_period();
        let mut t = t0;
        let mut client_seq = 0;
        let mut answer = |sim: &mut SimulatedController, at: Instant| {
            let reflected = sim.seq.wrapping_sub(1);
            sim.handle_datagram(at, &reply(client_seq, reflected, &q))
                .unwrap();
            client_seq += 1;
        };
        // On time: sent when due, answered within a millisecond.
        for _ in 0..10 {
            sim.poll_transmit(t, &mut buf).unwrap();
            answer(&mut sim, t + Duration::from_millis(1));
            t += period;
        }
        let s = sim.stats();
        assert_eq!((s.missed_replies, s.late_sends, s.late_replies), (0, 0, 0));
        assert_eq!(s.max_reply_latency, Duration::from_millis(1));
        // The client is late: its reply arrives after the next message went out.
        sim.poll_transmit(t, &mut buf).unwrap();
        sim.poll_transmit(t + period, &mut buf).unwrap();
        answer(&mut sim, t + period + Duration::from_millis(1));
        t += period * 2;
        sim.poll_transmit(t, &mut buf).unwrap();
        let s = sim.stats();
        assert_eq!((s.missed_replies, s.missed_after_late_send), (1, 0));
        // The controller is late: it sends 4 ms after the due time, the client answers
        // 2 ms later, after the next message was due and sent.
        answer(&mut sim, t + Duration::from_millis(1));
        t += period;
        sim.poll_transmit(t + Duration::from_millis(4), &mut buf)
            .unwrap();
        sim.poll_transmit(t + period, &mut buf).unwrap();
        answer(&mut sim, t + period + Duration::from_millis(1));
        sim.poll_transmit(t + period * 2, &mut buf).unwrap();
        let s = sim.stats();
        assert_eq!((s.missed_replies, s.missed_after_late_send), (2, 1));
        assert_eq!(s.late_sends, 1);
        assert_eq!(s.max_send_lateness, Duration::from_millis(4));
    }

    #[test]
    fn rejects_bad_config() {
        let now = Instant::now();
        let bad = SimConfig {
            send_period_ms: 0,
            ..SimConfig::default()
        };
        assert!(SimulatedController::new(bad, now).is_err());
        let bad = SimConfig {
            send_period_ms: 50,
            receive_multiplier: 3,
            ..SimConfig::default()
        };
        assert!(SimulatedController::new(bad, now).is_err());
    }
}
