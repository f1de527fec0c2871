//! A simulated KUKA controller (the robot side of FRI) and a lossy network link.
//!
//! # Why it lives here, on the same types
//! The simulator is the client's test partner and the project's stand-in for hardware. It
//! encodes and decodes with the same [`crate::codec`] and is sans-I/O like the client: it
//! is fed command datagrams and instants and asked for monitoring datagrams, so a test can
//! run thousands of cycles on a virtual clock in milliseconds, and [`crate::server`] and the
//! `fri-sim-controller` binary put the very same object behind a UDP socket.
//!
//! # What it models: a controller as KUKA documents it
//! Written from KUKA's documentation of FRI (shared/facts.md §1), not from our client, so
//! that the two cannot share one misreading:
//! * **Three positions, kept apart.** The robot application's interpolated position
//!   (`ipoData.jointPosition`): a held pose, or the application's own motion
//!   ([`SimulatedController::move_app_to`]), never the client's overlay. The commanded
//!   position (`monitorData.commandedJointPosition`): the interpolated position, except in
//!   COMMANDING_ACTIVE, where it is the client's command, **an absolute joint target**;
//!   the overlay is the difference ([`SimulatedController::overlay`]). The measured
//!   position: the arm following the commanded one within its velocity and acceleration
//!   capability, plus Gaussian encoder noise. A client that commands
//!   `ipo + offset` (KUKA's `LBRJointSineOverlay`) therefore moves the arm by `offset`
//!   around the application's position, and never integrates it.
//! * **A period of its own.** A message is due every `send_period_ms` on a fixed grid
//!   (`next += period`); a cycle that runs a period or more late skips the deadlines it
//!   missed and stays on the grid ([`SimStats::skipped_cycles`]); a send more than half a
//!   period after its deadline is counted in [`SimStats::late_sends`].
//! * **Connection quality from late or missing replies.** The client must answer every
//!   `receive_multiplier`-th message. A reply counts for the connection when it arrives
//!   before the controller has sent `receive_multiplier` further messages; a later one is
//!   counted in [`SimStats::late_replies`] and, like a lost one, as missing. The quality is
//!   the share of replies on time over the last `quality_window` cycles: EXCELLENT at or
//!   above `excellent_ratio`, GOOD at or above `good_ratio`, FAIR at or above half of it,
//!   else POOR. KUKA documents the four levels (FAIR "insufficient for command mode", GOOD
//!   "sufficient") but not its thresholds; these are ours.
//! * **Session states** as KUKA names them: MONITORING_WAIT (quality insufficient) →
//!   MONITORING_READY (a full window at GOOD or better) → COMMANDING_WAIT (the application
//!   starts a motion with an FRI overlay, [`SimulatedController::start_commanding`]; the
//!   client must answer with the interpolated position of the message it answers, within
//!   one period's velocity limit, for `commanding_wait_cycles` cycles) → COMMANDING_ACTIVE.
//!   Out of COMMANDING_ACTIVE: the application ends the overlay
//!   ([`SimulatedController::stop_commanding`], → MONITORING_READY); the quality drops
//!   below GOOD (missing replies, → MONITORING_WAIT); or a command is refused (→
//!   MONITORING_READY). Either abort is counted in [`SimStats::aborted`]; the arm stays
//!   where the overlay left it, which becomes the application's held pose.
//! * **Commands are checked** as the controller's supervision would: the first command of
//!   COMMANDING_ACTIVE against the interpolated position of the message it answers, each
//!   later one against the command before it, over the controller time between the
//!   messages they answer; outside the joint limits or a jump beyond the velocity limit →
//!   [`SimStats::violations`], the command is not applied and the overlay is aborted.
//! * A lost command is bridged by extrapolating the last command's motion for up to three
//!   cycles, then held; the client's replies are matched to the message they reflect.
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
    /// Position and velocity limits the arm moves within and checks commands against; the
    /// robot application's own motion uses their velocities and accelerations.
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
    /// Cycles over which the share of replies on time is measured.
    pub quality_window: u32,
    /// Share of replies on time at or above which quality is GOOD.
    pub good_ratio: f64,
    /// Share of replies on time at or above which quality is EXCELLENT.
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
    /// Of [`sent`](Self::sent), those sent in IDLE (which the client must not answer).
    pub sent_idle: u64,
    /// Valid command messages received.
    pub commands: u64,
    /// Datagrams rejected by the codec.
    pub malformed: u64,
    /// Reordered or duplicated commands ignored.
    pub stale: u64,
    /// COMMANDING_ACTIVE commands outside the joint limits, or jumping from the previous
    /// command (or, for the first, from the interpolated position) faster than the velocity
    /// limit allows. Each one is refused and aborts the overlay.
    pub violations: u64,
    /// Overlays aborted: the quality dropped below GOOD, or a command was refused.
    pub aborted: u64,
    /// Replies whose reflected sequence counter was never sent (ignored).
    pub bad_reflections: u64,
    /// Cycles (outside IDLE) that closed with no reply on time for the last
    /// `receive_multiplier` cycles: a reply the controller did not get in time, late or
    /// lost. These are the zeros of the connection-quality window.
    pub missed_replies: u64,
    /// Of [`missed_replies`](Self::missed_replies), those that followed a late send of the
    /// controller's own, which left the client less than half a period to answer.
    pub missed_after_late_send: u64,
    /// Messages sent more than half a period after they were due (the controller's own
    /// cycle ran late).
    pub late_sends: u64,
    /// Deadlines skipped because a cycle ran a period or more late (no message is sent for
    /// them; the grid of deadlines is kept).
    pub skipped_cycles: u64,
    /// Replies that arrived after `receive_multiplier` further messages had been sent:
    /// too late to count for the connection.
    pub late_replies: u64,
    /// Longest delay of a send past its due time.
    pub max_send_lateness: Duration,
    /// Longest time from sending a message to taking in the reply that reflects it (a
    /// cyclic driver takes replies in at its next cycle, so this is then about a period).
    pub max_reply_latency: Duration,
}

/// A sent message remembered to match the replies that reflect it.
#[derive(Clone, Copy, Debug)]
struct SentMessage {
    seq: u32,
    at: Instant,
    ipo: Joints,
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
    /// The arm: true joint positions and velocities.
    q: Joints,
    v: Joints,
    /// The robot application's interpolator: position, velocity, and where it is going.
    ipo: Joints,
    ipo_v: Joints,
    app_target: Joints,
    /// The commanded position of the current cycle (the interpolated position, or the
    /// client's command in COMMANDING_ACTIVE).
    commanded: Joints,
    /// The client's command in force and the controller message it answered.
    command: Option<(Joints, u32)>,
    /// That command minus the interpolated position of the message it answered.
    overlay: Joints,
    /// Per-cycle velocity of the command in force, for bridging lost commands.
    command_rate: Joints,
    window: VecDeque<u32>,
    replies_this_cycle: u32,
    echo_ok_cycles: u32,
    echo_ok_this_cycle: bool,
    commanding_requested: bool,
    /// Cycles since the last one in which a reply arrived on time.
    silent_cycles: u32,
    /// Whether the newest message was sent late.
    last_send_late: bool,
    /// The newest messages, indexed by sequence counter.
    sent: [Option<SentMessage>; SENT_SLOTS],
    /// Session states reported, consecutive repeats collapsed (the first [`MAX_STATES`]).
    states_seen: Vec<SessionState>,
    stats: SimStats,
}

/// Sent messages remembered to match replies (reply latency, the interpolated position a
/// command answers).
const SENT_SLOTS: usize = 64;

/// Largest backward step of the client's sequence counter treated as reordering.
const REORDER_WINDOW: u32 = 64;

/// State changes remembered in [`SimulatedController::states_seen`].
const MAX_STATES: usize = 256;

/// Cycles over which a lost command is bridged by extrapolating the last one.
const BRIDGE_CYCLES: u32 = 3;

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
            ipo: cfg.initial_q,
            ipo_v: [0.0; NUM_JOINTS],
            app_target: cfg.initial_q,
            commanded: cfg.initial_q,
            command: None,
            overlay: [0.0; NUM_JOINTS],
            command_rate: [0.0; NUM_JOINTS],
            window: VecDeque::new(),
            replies_this_cycle: 0,
            echo_ok_cycles: 0,
            echo_ok_this_cycle: false,
            commanding_requested: false,
            silent_cycles: 0,
            last_send_late: false,
            sent: [None; SENT_SLOTS],
            states_seen: Vec::new(),
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

    /// The robot application's interpolated position (rad), as sent in `ipoData`.
    pub fn ipo(&self) -> Joints {
        self.ipo
    }

    /// The commanded position of the last cycle (rad), as sent in `monitorData`.
    pub fn commanded(&self) -> Joints {
        self.commanded
    }

    /// The client's overlay in force (rad): its last command minus the interpolated
    /// position of the message that command answered; zero outside COMMANDING_ACTIVE.
    pub fn overlay(&self) -> Joints {
        self.overlay
    }

    /// The session states the messages reported so far, in order, consecutive repeats
    /// collapsed (the first 256).
    pub fn states_seen(&self) -> &[SessionState] {
        &self.states_seen
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

    /// The robot application moves to `q` (clamped to the joint limits) along its own
    /// motion: the interpolated position moves there within the velocity and acceleration
    /// limits. Outside COMMANDING_ACTIVE the arm follows it; in COMMANDING_ACTIVE the
    /// client's command decides where the arm is, and the overlay changes with it.
    pub fn move_app_to(&mut self, q: Joints) {
        let l = &self.cfg.limits;
        for (j, (dst, &v)) in self.app_target.iter_mut().zip(&q).enumerate() {
            if v.is_finite() {
                *dst = v.clamp(l.position_min[j], l.position_max[j]);
            }
        }
    }

    /// The robot application starts a motion with an FRI joint overlay (from
    /// MONITORING_READY, at once or as soon as it is reached).
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

    /// The overlay ends: the arm stays where it was commanded, which becomes the
    /// application's held pose.
    fn leave_commanding(&mut self, to: SessionState) {
        self.state = to;
        self.command = None;
        self.overlay = [0.0; NUM_JOINTS];
        self.command_rate = [0.0; NUM_JOINTS];
        self.echo_ok_cycles = 0;
        self.ipo = self.commanded;
        self.ipo_v = [0.0; NUM_JOINTS];
        self.app_target = self.commanded;
    }

    /// The overlay is aborted (by a refused command or a quality drop).
    fn abort_commanding(&mut self, to: SessionState) {
        self.stats.aborted += 1;
        self.commanding_requested = false;
        self.leave_commanding(to);
    }

    /// When the next monitoring message is due.
    pub fn poll_timeout(&self) -> Instant {
        self.next_send
    }

    /// The message with sequence counter `seq`, if it is still remembered.
    fn sent_message(&self, seq: u32) -> Option<&SentMessage> {
        self.sent[seq as usize % SENT_SLOTS]
            .as_ref()
            .filter(|m| m.seq == seq)
    }

    /// Whether `q` is within one period's velocity limit of `reference` (`cycles` periods).
    fn within_velocity(&self, q: &Joints, reference: &Joints, cycles: u32) -> bool {
        let dt = f64::from(cycles) * f64::from(self.cfg.send_period_ms) * 1e-3;
        (0..NUM_JOINTS)
            .all(|j| (q[j] - reference[j]).abs() <= self.cfg.limits.velocity[j] * dt * (1.0 + 1e-6))
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
        let reflected = header.reflected_sequence_counter;
        if reflected.wrapping_sub(self.seq) < u32::MAX / 2 {
            // Reflects a counter not sent yet.
            self.stats.bad_reflections += 1;
            return Ok(());
        }
        self.stats.commands += 1;
        let on_time = self.audit_reply(now, reflected);
        if self.state == SessionState::Idle {
            return Ok(());
        }
        if on_time {
            self.replies_this_cycle += 1;
        }
        let q = match msg.command_data.and_then(|c| c.joint_position) {
            Some(jv) => codec::joints(codec::COMMAND, "commandData.jointPosition", &jv)?,
            None => return Ok(()),
        };
        match self.state {
            SessionState::CommandingWait => {
                let ipo = self.sent_message(reflected).map_or(self.ipo, |m| m.ipo);
                self.echo_ok_this_cycle |= on_time && self.within_velocity(&q, &ipo, 1);
            }
            SessionState::CommandingActive => self.accept_command(q, reflected),
            _ => {}
        }
        Ok(())
    }

    /// Checks a COMMANDING_ACTIVE command answering message `reflected`; applies it, or
    /// refuses it and aborts the overlay.
    fn accept_command(&mut self, q: Joints, reflected: u32) {
        let answered_ipo = self.sent_message(reflected).map_or(self.ipo, |m| m.ipo);
        let (reference, cycles) = match self.command {
            Some((prev, prev_seq)) => {
                let cycles = reflected.wrapping_sub(prev_seq);
                if cycles == 0 || cycles > u32::MAX / 2 {
                    // Not newer than the command in force: out of order, ignore.
                    self.stats.stale += 1;
                    return;
                }
                (prev, cycles)
            }
            // The first command continues from the interpolated position it answers.
            None => (answered_ipo, 1),
        };
        let ok_pos = self.cfg.limits.check_position(&q, 0.0).is_ok();
        if ok_pos && self.within_velocity(&q, &reference, cycles) {
            self.command_rate = match self.command {
                Some((prev, _)) => std::array::from_fn(|j| (q[j] - prev[j]) / f64::from(cycles)),
                // The first command starts at the interpolated position: until the next
                // one arrives it moves as the interpolator does.
                None => {
                    let dt = self.send_period().as_secs_f64();
                    std::array::from_fn(|j| self.ipo_v[j] * dt)
                }
            };
            self.command = Some((q, reflected));
            self.overlay = std::array::from_fn(|j| q[j] - answered_ipo[j]);
        } else {
            self.stats.violations += 1;
            tracing::warn!(
                ?q,
                ?reference,
                cycles,
                "simulated controller refuses an FRI command and aborts the overlay"
            );
            self.abort_commanding(SessionState::MonitoringReady);
        }
    }

    /// Reply latency and lateness of a reply reflecting message `reflected`; whether it
    /// is on time (before `receive_multiplier` further messages were sent).
    fn audit_reply(&mut self, now: Instant, reflected: u32) -> bool {
        // `self.seq` is the next message's counter: messages up to `self.seq - 1` are out.
        let behind = self.seq.wrapping_sub(reflected);
        if behind > self.cfg.receive_multiplier {
            self.stats.late_replies += 1;
        }
        if let Some(sent) = self.sent_message(reflected) {
            let latency = now.saturating_duration_since(sent.at);
            self.stats.max_reply_latency = self.stats.max_reply_latency.max(latency);
        }
        behind <= self.cfg.receive_multiplier
    }

    /// Counts a missed reply when `receive_multiplier` cycles closed without one on time,
    /// and the lateness of the send at `now` of a message due at `due`.
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
    }

    fn gaussian(&mut self) -> f64 {
        // Box–Muller.
        let u1: f64 = self.rng.random::<f64>().max(f64::MIN_POSITIVE);
        let u2: f64 = self.rng.random::<f64>();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// One cycle of the robot: the application's interpolator, the commanded position,
    /// the arm following it.
    fn step(&mut self, dt: f64) {
        let l = self.cfg.limits;
        let ipo_before = self.ipo;
        for j in 0..NUM_JOINTS {
            track(
                (&mut self.ipo[j], &mut self.ipo_v[j]),
                (self.app_target[j], 0.0),
                (l.velocity[j], l.acceleration[j]),
                (l.position_min[j], l.position_max[j]),
                dt,
            );
        }
        let (commanded, rate) = match (self.state, self.command) {
            (SessionState::CommandingActive, Some((q, reflected))) => {
                // The command answering message r is applied in cycle r + 1. When newer ones
                // are missing (lost or late), extrapolate the command's motion for a few
                // cycles, as an interpolator bridging gaps would, then hold.
                let missing = self.seq.wrapping_sub(reflected).saturating_sub(1);
                let n = missing.min(BRIDGE_CYCLES);
                let rate = if missing < BRIDGE_CYCLES {
                    self.command_rate
                } else {
                    [0.0; NUM_JOINTS]
                };
                let t: Joints = std::array::from_fn(|j| {
                    (q[j] + self.command_rate[j] * f64::from(n))
                        .clamp(l.position_min[j], l.position_max[j])
                });
                (t, rate)
            }
            _ => (
                self.ipo,
                std::array::from_fn(|j| self.ipo[j] - ipo_before[j]),
            ),
        };
        self.commanded = commanded;
        for j in 0..NUM_JOINTS {
            track(
                (&mut self.q[j], &mut self.v[j]),
                (commanded[j], rate[j]),
                (l.velocity[j], self.cfg.arm_acceleration),
                (l.position_min[j], l.position_max[j]),
                dt,
            );
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
                    self.abort_commanding(SessionState::MonitoringWait);
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
    /// the message into `buf` and returns its length.
    ///
    /// Deadlines lie on a fixed grid (`next += period`). A cycle that runs a period or more
    /// late skips the deadlines it missed and stays on the grid: like a real controller,
    /// it never sends two messages less than a period apart to catch up, which would leave
    /// the client no time to answer the first.
    pub fn poll_transmit(&mut self, now: Instant, buf: &mut [u8]) -> Option<usize> {
        if now < self.next_send {
            return None;
        }
        let period = self.send_period();
        let due = self.next_send;
        self.next_send += period;
        if now >= self.next_send {
            let behind = (now - self.next_send).as_nanos() / period.as_nanos();
            let skipped = u32::try_from(behind + 1).unwrap_or(u32::MAX);
            self.next_send += period * skipped;
            self.stats.skipped_cycles += u64::from(skipped);
        }
        self.audit_cycle(now, due);
        self.step(period.as_secs_f64());
        self.update_quality_and_state();
        let msg = self.monitoring_message(now);
        self.sent[self.seq as usize % SENT_SLOTS] = Some(SentMessage {
            seq: self.seq,
            at: now,
            ipo: self.ipo,
        });
        if self.states_seen.last() != Some(&self.state) && self.states_seen.len() < MAX_STATES {
            self.states_seen.push(self.state);
        }
        self.seq = self.seq.wrapping_add(1);
        match codec::encode_monitoring(&msg, buf) {
            Ok(n) => {
                self.stats.sent += 1;
                if self.state == SessionState::Idle {
                    self.stats.sent_idle += 1;
                }
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
                commanded_joint_position: Some(JointValues::from_array(&self.commanded)),
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
                joint_position: Some(JointValues::from_array(&self.ipo)),
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

/// One joint following a target that moves by `target.1` per cycle, within a velocity
/// and an acceleration limit: the target's own velocity as feed-forward, plus closing the
/// error no faster than in one cycle and slowly enough to brake in time (discrete-time
/// stopping distance), so it never overshoots a target that stops.
fn track(
    (pos, vel): (&mut f64, &mut f64),
    (target, rate): (f64, f64),
    (vmax, amax): (f64, f64),
    (lo, hi): (f64, f64),
    dt: f64,
) {
    let feed_forward = rate / dt;
    let e = target - *pos - rate;
    let adt = amax * dt;
    let closing = (e.abs() / dt).min(adt * ((0.25 + 2.0 * e.abs() / (adt * dt)).sqrt() - 0.5));
    let desired = feed_forward + closing.copysign(e);
    let v = desired.clamp(*vel - adt, *vel + adt).clamp(-vmax, vmax);
    *vel = v;
    *pos = (*pos + v * dt).clamp(lo, hi);
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
