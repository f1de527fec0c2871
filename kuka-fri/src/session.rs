//! The client side of an FRI session, without sockets or clocks.
//!
//! # Why sans-I/O
//! Like `quinn-proto`, [`ClientSession`] never touches a socket and never reads a clock: it is
//! fed datagrams and instants and asked what to send and when it next needs waking. The same
//! code therefore runs behind the UDP driver ([`crate::udp`]), in a virtual-clock test against
//! the simulated controller over a lossy link, and in a benchmark, deterministically.
//!
//! # The protocol as implemented
//! * The controller sends first; each datagram is checked by [`crate::codec`].
//! * A datagram whose sequence counter is not newer than the last accepted one (within a
//!   window of [`REORDER_WINDOW`]) is reordered or duplicated: it is ignored
//!   ([`Event::Stale`]). Bigger backward jumps are taken as a controller restart.
//! * The client answers every `receiveMultiplier`-th accepted message and **never in IDLE**;
//!   the reply carries its own incrementing `sequenceCounter` and reflects the controller's.
//! * What the reply commands depends on the state, as in KUKA's SDK defaults:
//!   MONITORING_* echo `commandedJointPosition` (FRI 2.x lacks it: the interpolator position
//!   is used), COMMANDING_WAIT echoes the interpolator position, and only in
//!   COMMANDING_ACTIVE does the client's own command go out.
//! * A COMMANDING_ACTIVE command is an absolute joint target (the controller takes the
//!   overlay as its difference to the application's interpolated position). The first one
//!   is the interpolated position of the message it answers, so the overlay starts at
//!   zero; from then on the client holds the arm where it last commanded it, whether or
//!   not the application's interpolated position moves. The robot application is expected
//!   to hold a pose under the overlay (KUKA's position hold with a joint overlay).
//! * Every COMMANDING_ACTIVE command passes [`SafetyGuard::check`] against the previously
//!   sent command, over the controller time between the two messages they answer. A command
//!   that fails is replaced by holding the previous one (zero velocity) and reported; if even
//!   that fails, nothing is sent, and the controller, missing replies, stops the overlay.
//! * If nothing arrives for the timeout, the session reports [`Event::ConnectionLost`],
//!   falls back to IDLE locally and aborts any motion.
//!
//! Time on the trajectory advances with the controller's sequence counter (× send period),
//! not with host time, so lost datagrams or host jitter never make the arm jump.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use b2b_robot::Joints;

use crate::codec::{self, MONITORING};
use crate::error::{FriError, Result};
use crate::guard::SafetyGuard;
use crate::joints::{ControllerTime, JointHistory, JointState};
use crate::messages::{
    ConnectionQuality, FriCommandMessage, FriMonitoringMessage, JointValues,
    LBR_COMMAND_MESSAGE_ID, MessageCommandData, SessionState,
};
use crate::trajectory::Trajectory;

/// How far back (in sequence numbers) a datagram counts as reordered rather than a restart.
pub const REORDER_WINDOW: u32 = 64;

/// Largest joint step (rad) between path points checked before a motion starts.
const PATH_CHECK_STEP: f64 = 1e-3;

/// Settings of a [`ClientSession`].
#[derive(Clone, Debug)]
pub struct SessionConfig {
    /// The connection counts as lost after `max(min_timeout, timeout_periods × sendPeriod)`
    /// without a valid datagram.
    pub min_timeout: Duration,
    /// See `min_timeout`.
    pub timeout_periods: u32,
    /// Joint states kept for [`ClientSession::is_still`].
    pub history_capacity: usize,
}

impl Default for SessionConfig {
    fn default() -> Self {
        Self {
            min_timeout: Duration::from_millis(100),
            timeout_periods: 20,
            history_capacity: 8192,
        }
    }
}

/// The contents of the last accepted monitoring message that the session uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MonitorSnapshot {
    /// Controller's sequence counter.
    pub sequence: u32,
    /// The client sequence counter the controller last received.
    pub reflected_sequence: u32,
    /// Session state.
    pub state: SessionState,
    /// Connection quality as the controller judges it.
    pub quality: ConnectionQuality,
    /// Send period (ms).
    pub send_period_ms: u32,
    /// The client answers every `receive_multiplier`-th message.
    pub receive_multiplier: u32,
    /// Measured joint positions (rad).
    pub measured: Option<Joints>,
    /// Commanded joint positions (rad; FRI 1.x only).
    pub commanded: Option<Joints>,
    /// Interpolator joint positions (rad).
    pub ipo: Option<Joints>,
    /// Controller time stamp.
    pub timestamp: Option<ControllerTime>,
    /// Tracking performance (0..1).
    pub tracking_performance: f64,
    /// Host time it was handled.
    pub received_at: Instant,
}

impl MonitorSnapshot {
    /// Send period in seconds.
    pub fn send_period(&self) -> f64 {
        f64::from(self.send_period_ms) * 1e-3
    }

    fn from_message(
        msg: &FriMonitoringMessage,
        header: codec::Header,
        now: Instant,
    ) -> Result<Self> {
        const M: &str = MONITORING;
        let missing = |field| FriError::MissingField { message: M, field };
        let ci = msg
            .connection_info
            .as_ref()
            .ok_or(missing("connectionInfo"))?;
        let state = ci
            .session_state
            .and_then(|v| SessionState::try_from(v).ok())
            .ok_or(missing("connectionInfo.sessionState"))?;
        let quality = ci
            .quality
            .and_then(|v| ConnectionQuality::try_from(v).ok())
            .ok_or(missing("connectionInfo.quality"))?;
        let send_period_ms = ci.send_period.ok_or(missing("connectionInfo.sendPeriod"))?;
        let receive_multiplier = ci
            .receive_multiplier
            .ok_or(missing("connectionInfo.receiveMultiplier"))?;
        let md = msg.monitor_data.as_ref();
        let joints =
            |v: Option<&JointValues>, field| v.map(|v| codec::joints(M, field, v)).transpose();
        let measured = joints(
            md.and_then(|m| m.measured_joint_position.as_ref()),
            "monitorData.measuredJointPosition",
        )?;
        let commanded = joints(
            md.and_then(|m| m.commanded_joint_position.as_ref()),
            "monitorData.commandedJointPosition",
        )?;
        let ipo = joints(
            msg.ipo_data
                .as_ref()
                .and_then(|i| i.joint_position.as_ref()),
            "ipoData.jointPosition",
        )?;
        let timestamp = md.and_then(|m| m.timestamp.as_ref()).and_then(|t| {
            Some(ControllerTime {
                sec: t.sec?,
                nanosec: t.nanosec?,
            })
        });
        Ok(Self {
            sequence: header.sequence_counter,
            reflected_sequence: header.reflected_sequence_counter,
            state,
            quality,
            send_period_ms,
            receive_multiplier,
            measured,
            commanded,
            ipo,
            timestamp,
            tracking_performance: msg
                .ipo_data
                .as_ref()
                .and_then(|i| i.tracking_performance)
                .unwrap_or(0.0),
            received_at: now,
        })
    }
}

/// What happened.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// A monitoring message was accepted.
    Monitoring {
        /// Its sequence counter.
        sequence: u32,
        /// The state it reports.
        state: SessionState,
        /// Whether a reply is now waiting in [`ClientSession::poll_transmit`].
        reply_due: bool,
    },
    /// A reordered or duplicated datagram was ignored.
    Stale {
        /// Its sequence counter.
        sequence: u32,
        /// The newest accepted sequence counter.
        latest: u32,
    },
    /// The controller reported a new session state (or the connection was lost → IDLE).
    StateChanged {
        /// Previous state.
        from: SessionState,
        /// New state.
        to: SessionState,
    },
    /// The running motion reached its target.
    MotionFinished {
        /// Identifier returned by [`ClientSession::start_motion`].
        id: u64,
    },
    /// The running motion stopped early.
    MotionAborted {
        /// Identifier returned by [`ClientSession::start_motion`].
        id: u64,
        /// Why.
        reason: String,
    },
    /// A command failed the safety guard; the previous command was held instead (or nothing
    /// was sent if that failed too).
    CommandRejected {
        /// The guard's verdict.
        reason: String,
    },
    /// No valid datagram for the timeout.
    ConnectionLost {
        /// Time since the last valid datagram.
        silent_for: Duration,
    },
}

/// Counters of the session's traffic.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SessionStats {
    /// Monitoring messages accepted.
    pub received: u64,
    /// Of [`received`](Self::received), those reporting IDLE (never answered).
    pub received_idle: u64,
    /// Datagrams rejected by the codec.
    pub malformed: u64,
    /// Reordered or duplicated datagrams ignored.
    pub stale: u64,
    /// Controller sequence numbers never seen (gaps).
    pub lost: u64,
    /// Command messages produced.
    pub sent: u64,
    /// Commands replaced because the guard rejected them.
    pub rejected: u64,
    /// Connection-lost timeouts.
    pub timeouts: u64,
    /// Controller restarts detected (large backward sequence jumps).
    pub restarts: u64,
}

/// A motion planned from a command origin, its target and whole path checked by a guard:
/// ready for [`ClientSession::begin_motion`].
///
/// Planning checks the path pose by pose (milliseconds for a long move), so a driver plans
/// outside its cycle and hands the plan over; the session begins it only from the same
/// origin and with the same guard, and still checks every command it sends.
#[derive(Clone, Debug)]
pub struct PlannedMotion {
    origin: Joints,
    traj: Trajectory,
    guard: SafetyGuard,
}

impl PlannedMotion {
    /// Plans a rest-to-rest motion from `origin` to `target` within `guard`'s limits and
    /// checks the target and the path (a pose every milliradian) against it.
    pub fn plan(guard: &SafetyGuard, origin: Joints, target: Joints) -> Result<Self> {
        guard.check_pose(&target)?;
        let traj = Trajectory::plan(&origin, &target, guard.limits())?;
        for q in traj.path_points(PATH_CHECK_STEP) {
            guard.check_pose(&q)?;
        }
        Ok(Self {
            origin,
            traj,
            guard: guard.clone(),
        })
    }

    /// Where the motion starts.
    pub fn origin(&self) -> Joints {
        self.origin
    }

    /// The planned duration.
    pub fn duration(&self) -> Duration {
        Duration::from_secs_f64(self.traj.duration().min(1e6))
    }
}

#[derive(Clone, Debug)]
enum CommandSource {
    /// Repeat the last command (or the interpolator position when there is none).
    Hold,
    /// Send this position (still checked by the guard every cycle).
    Position(Joints),
    /// Follow a trajectory; `t0_seq` is the controller sequence of trajectory time 0.
    Motion {
        id: u64,
        traj: Trajectory,
        t0_seq: Option<u32>,
    },
}

#[derive(Clone, Copy, Debug)]
struct PendingReply {
    trigger_seq: u32,
}

/// The client side of an FRI session (sans-I/O).
#[derive(Debug)]
pub struct ClientSession {
    config: SessionConfig,
    guard: SafetyGuard,
    state: SessionState,
    latest: Option<MonitorSnapshot>,
    history: JointHistory,
    last_rx: Option<Instant>,
    lost: bool,
    multiplier_count: u32,
    sequence_counter: u32,
    pending: Option<PendingReply>,
    last_command: Option<(Joints, u32)>,
    command: CommandSource,
    next_motion_id: u64,
    events: VecDeque<Event>,
    stats: SessionStats,
}

/// At most this many events are queued; older ones are dropped first.
const MAX_EVENTS: usize = 1024;

impl ClientSession {
    /// A new session in IDLE. The guard checks every command sent in COMMANDING_ACTIVE.
    pub fn new(config: SessionConfig, guard: SafetyGuard) -> Self {
        let history = JointHistory::new(config.history_capacity);
        Self {
            config,
            guard,
            state: SessionState::Idle,
            latest: None,
            history,
            last_rx: None,
            lost: false,
            multiplier_count: 0,
            sequence_counter: 0,
            pending: None,
            last_command: None,
            command: CommandSource::Hold,
            next_motion_id: 1,
            events: VecDeque::new(),
            stats: SessionStats::default(),
        }
    }

    /// The session state last reported by the controller (IDLE after a connection loss).
    pub fn state(&self) -> SessionState {
        self.state
    }

    /// The last accepted monitoring message.
    pub fn latest(&self) -> Option<&MonitorSnapshot> {
        self.latest.as_ref()
    }

    /// The newest measured joint state with its controller time stamp.
    pub fn latest_joint_state(&self) -> Option<JointState> {
        self.history.latest().copied()
    }

    /// See [`JointHistory::is_still`].
    pub fn is_still(&self, window: Duration, tol: f64) -> bool {
        self.history.is_still(window, tol)
    }

    /// Traffic counters.
    pub fn stats(&self) -> SessionStats {
        self.stats
    }

    /// The safety guard.
    pub fn guard(&self) -> &SafetyGuard {
        &self.guard
    }

    /// Whether a motion is running.
    pub fn motion_in_progress(&self) -> bool {
        matches!(self.command, CommandSource::Motion { .. })
    }

    /// The last command sent in COMMANDING_ACTIVE and the controller sequence it answered.
    pub fn last_command(&self) -> Option<(Joints, u32)> {
        self.last_command
    }

    /// The next event, if any.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    fn push_event(&mut self, e: Event) {
        if self.events.len() == MAX_EVENTS {
            self.events.pop_front();
        }
        self.events.push_back(e);
    }

    fn timeout_duration(&self) -> Duration {
        let period = self.latest.map_or(0, |s| s.send_period_ms);
        let by_period =
            Duration::from_millis(u64::from(period) * u64::from(self.config.timeout_periods));
        self.config.min_timeout.max(by_period)
    }

    /// Handles one received datagram.
    ///
    /// Errors leave the session unchanged apart from [`SessionStats::malformed`].
    pub fn handle_datagram(&mut self, now: Instant, bytes: &[u8]) -> Result<Event> {
        let parsed = codec::decode_monitoring_with_header(bytes)
            .and_then(|(header, msg)| MonitorSnapshot::from_message(&msg, header, now));
        let snap = match parsed {
            Ok(s) => s,
            Err(e) => {
                self.stats.malformed += 1;
                return Err(e);
            }
        };
        if let Some(prev) = self.latest.as_ref().filter(|_| !self.lost) {
            let ahead = snap.sequence.wrapping_sub(prev.sequence);
            let behind = prev.sequence.wrapping_sub(snap.sequence);
            if ahead == 0 || (behind > 0 && behind <= REORDER_WINDOW) {
                self.stats.stale += 1;
                return Ok(Event::Stale {
                    sequence: snap.sequence,
                    latest: prev.sequence,
                });
            }
            if behind > REORDER_WINDOW && behind < u32::MAX / 2 {
                // A large step back: the controller started a new session.
                self.stats.restarts += 1;
                self.last_command = None;
                self.multiplier_count = 0;
                self.abort_motion("controller sequence counter restarted");
            } else if ahead > 1 {
                self.stats.lost += u64::from(ahead - 1);
            }
        }
        self.stats.received += 1;
        self.last_rx = Some(now);
        self.lost = false;

        if snap.state != self.state {
            self.change_state(snap.state);
        }
        if let (Some(q), Some(timestamp)) = (snap.measured, snap.timestamp) {
            self.history.push(JointState {
                q,
                timestamp,
                received_at: now,
            });
        }
        self.latest = Some(snap);

        let mut reply_due = false;
        if snap.state == SessionState::Idle {
            self.stats.received_idle += 1;
            self.multiplier_count = 0;
            self.pending = None;
        } else {
            self.multiplier_count += 1;
            if self.multiplier_count >= snap.receive_multiplier.max(1) {
                self.multiplier_count = 0;
                self.pending = Some(PendingReply {
                    trigger_seq: snap.sequence,
                });
                reply_due = true;
            }
        }
        Ok(Event::Monitoring {
            sequence: snap.sequence,
            state: snap.state,
            reply_due,
        })
    }

    fn change_state(&mut self, to: SessionState) {
        let from = self.state;
        self.state = to;
        self.push_event(Event::StateChanged { from, to });
        if from == SessionState::CommandingActive || to == SessionState::CommandingActive {
            self.abort_motion(&format!("session state changed from {from} to {to}"));
            self.command = CommandSource::Hold;
            self.last_command = None;
        }
        if to == SessionState::Idle {
            self.pending = None;
        }
    }

    fn abort_motion(&mut self, reason: &str) {
        if let CommandSource::Motion { id, .. } = self.command {
            self.command = CommandSource::Hold;
            self.push_event(Event::MotionAborted {
                id,
                reason: reason.to_owned(),
            });
        }
    }

    /// When [`handle_timeout`](Self::handle_timeout) must next be called, if ever.
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.lost {
            return None;
        }
        self.last_rx.map(|t| t + self.timeout_duration())
    }

    /// Declares the connection lost if nothing valid arrived for the timeout.
    pub fn handle_timeout(&mut self, now: Instant) {
        let Some(deadline) = self.poll_timeout() else {
            return;
        };
        if now < deadline {
            return;
        }
        let silent_for = self
            .last_rx
            .map_or(Duration::ZERO, |t| now.saturating_duration_since(t));
        self.lost = true;
        self.stats.timeouts += 1;
        self.pending = None;
        self.multiplier_count = 0;
        self.push_event(Event::ConnectionLost { silent_for });
        if self.state != SessionState::Idle {
            self.change_state(SessionState::Idle);
        }
        self.abort_motion("connection lost");
    }

    fn require_commanding(&self) -> Result<&MonitorSnapshot> {
        match self.latest.as_ref() {
            Some(s) if self.state == SessionState::CommandingActive && !self.lost => Ok(s),
            _ => Err(FriError::NotCommanding { state: self.state }),
        }
    }

    /// The pose commanding continues from: the last command, else the interpolator position.
    /// A motion planned now starts here.
    pub fn command_origin(&self) -> Option<Joints> {
        self.last_command.map(|(q, _)| q).or_else(|| {
            self.latest
                .and_then(|s| s.ipo.or(s.commanded).or(s.measured))
        })
    }

    /// Starts a synchronised trajectory to `target` (COMMANDING_ACTIVE only).
    ///
    /// The target and the whole path are checked against the guard first. Returns the motion
    /// identifier (reported in [`Event::MotionFinished`] / [`Event::MotionAborted`]) and the
    /// planned duration. Equivalent to [`PlannedMotion::plan`] from
    /// [`command_origin`](Self::command_origin) followed by
    /// [`begin_motion`](Self::begin_motion).
    pub fn start_motion(&mut self, target: Joints) -> Result<(u64, Duration)> {
        let origin = self.motion_origin()?;
        let motion = PlannedMotion::plan(&self.guard, origin, target)?;
        self.begin_motion(motion)
    }

    /// Starts a motion planned with [`PlannedMotion::plan`] (COMMANDING_ACTIVE only).
    ///
    /// Cheap, unlike planning: a driver plans away from its cycle and begins here. Fails if
    /// the motion was planned from another origin than [`command_origin`](Self::command_origin)
    /// ([`FriError::MotionOriginMoved`]: plan again) or checked by another guard than this
    /// session's.
    pub fn begin_motion(&mut self, motion: PlannedMotion) -> Result<(u64, Duration)> {
        let origin = self.motion_origin()?;
        if !motion.guard.is_same(&self.guard) {
            return Err(FriError::InvalidValue {
                what: "planned motion",
                value: "checked by another safety guard than the session's".into(),
            });
        }
        if motion.origin != origin {
            return Err(FriError::MotionOriginMoved);
        }
        let id = self.next_motion_id;
        self.next_motion_id += 1;
        let duration = motion.duration();
        let t0_seq = self.last_command.map(|(_, seq)| seq);
        self.command = CommandSource::Motion {
            id,
            traj: motion.traj,
            t0_seq,
        };
        Ok((id, duration))
    }

    /// Where a new motion would start, if one may start now.
    fn motion_origin(&self) -> Result<Joints> {
        self.require_commanding()?;
        if self.motion_in_progress() {
            return Err(FriError::MotionInProgress);
        }
        self.command_origin().ok_or(FriError::MissingField {
            message: MONITORING,
            field: "ipoData.jointPosition",
        })
    }

    /// Brakes the running motion along its path at the planned deceleration.
    pub fn stop_motion(&mut self) {
        let CommandSource::Motion { id, traj, t0_seq } = &self.command else {
            return;
        };
        let (id, braking) = match (t0_seq, self.last_command, self.latest) {
            (Some(t0), Some((_, last_seq)), Some(s)) => {
                let t = f64::from(last_seq.wrapping_sub(*t0)) * s.send_period();
                (*id, traj.braking_at(t))
            }
            _ => {
                let id = *id;
                self.command = CommandSource::Hold;
                self.push_event(Event::MotionAborted {
                    id,
                    reason: "stopped".into(),
                });
                return;
            }
        };
        let t0 = self.last_command.map(|(_, seq)| seq);
        self.command = CommandSource::Motion {
            id,
            traj: braking,
            t0_seq: t0,
        };
    }

    /// Commands a fixed joint position every cycle (COMMANDING_ACTIVE only). It is checked by
    /// the guard each cycle like any command, so a far-away target is rejected (held) rather
    /// than jumped to: use [`start_motion`](Self::start_motion) for moves.
    pub fn set_position_command(&mut self, q: Joints) -> Result<()> {
        let snap = *self.require_commanding()?;
        let prev = self.command_origin();
        let dt = f64::from(snap.receive_multiplier.max(1)) * snap.send_period();
        self.guard.check(prev.as_ref(), &q, dt)?;
        self.abort_motion("replaced by a position command");
        self.command = CommandSource::Position(q);
        Ok(())
    }

    /// Holds the last command.
    pub fn hold(&mut self) {
        self.abort_motion("hold requested");
        self.command = CommandSource::Hold;
    }

    /// The command for the reply to controller message `seq`, after the guard.
    fn next_command(&mut self, snap: &MonitorSnapshot, seq: u32) -> Option<Joints> {
        let (desired, finished) = match &mut self.command {
            CommandSource::Hold => (self.command_origin()?, None),
            CommandSource::Position(q) => (*q, None),
            CommandSource::Motion { id, traj, t0_seq } => {
                let t0 = *t0_seq.get_or_insert(seq);
                let t = f64::from(seq.wrapping_sub(t0)) * snap.send_period();
                let q = traj.sample(t);
                (q, (t >= traj.duration()).then_some(*id))
            }
        };
        let previous = self.last_command;
        let dt_since = |prev_seq: u32| f64::from(seq.wrapping_sub(prev_seq)) * snap.send_period();
        let verdict = self.guard.check(
            previous.as_ref().map(|(q, _)| q),
            &desired,
            previous.map_or(snap.send_period(), |(_, s)| dt_since(s)),
        );
        match verdict {
            Ok(()) => {
                if let Some(id) = finished {
                    self.command = CommandSource::Hold;
                    self.push_event(Event::MotionFinished { id });
                }
                Some(desired)
            }
            Err(err) => {
                self.stats.rejected += 1;
                tracing::warn!(%err, "FRI command rejected by the safety guard; holding");
                self.push_event(Event::CommandRejected {
                    reason: err.to_string(),
                });
                self.abort_motion(&format!("command rejected: {err}"));
                self.command = CommandSource::Hold;
                // Holding the previous command is zero velocity; without one, hold the
                // interpolator position if it is itself acceptable.
                match previous {
                    Some((q, _)) => Some(q),
                    None => {
                        let q = snap.ipo.or(snap.commanded).or(snap.measured)?;
                        self.guard.check_pose(&q).ok().map(|()| q)
                    }
                }
            }
        }
    }

    /// Writes the pending reply, if one is due, into `buf` and returns its length.
    ///
    /// `buf` should hold [`crate::messages::MAX_DATAGRAM_SIZE`] bytes; if the message does
    /// not fit, nothing is sent and [`Event::CommandRejected`] is queued.
    pub fn poll_transmit(&mut self, _now: Instant, buf: &mut [u8]) -> Option<usize> {
        let pending = self.pending.take()?;
        let snap = self.latest?;
        let joints = match snap.state {
            SessionState::Idle => return None,
            SessionState::MonitoringWait | SessionState::MonitoringReady => {
                snap.commanded.or(snap.ipo).or(snap.measured)
            }
            SessionState::CommandingWait => snap.ipo.or(snap.commanded).or(snap.measured),
            SessionState::CommandingActive => Some(self.next_command(&snap, pending.trigger_seq)?),
        };
        let msg = FriCommandMessage {
            header: Some(
                codec::Header {
                    message_identifier: LBR_COMMAND_MESSAGE_ID,
                    sequence_counter: self.sequence_counter,
                    reflected_sequence_counter: pending.trigger_seq,
                }
                .to_message(),
            ),
            command_data: Some(MessageCommandData {
                joint_position: joints.as_ref().map(JointValues::from_array),
                ..Default::default()
            }),
            end_of_message_data: None,
        };
        match codec::encode_command(&msg, buf) {
            Ok(n) => {
                self.sequence_counter = self.sequence_counter.wrapping_add(1);
                self.stats.sent += 1;
                if snap.state == SessionState::CommandingActive
                    && let Some(q) = joints
                {
                    self.last_command = Some((q, pending.trigger_seq));
                }
                Some(n)
            }
            Err(err) => {
                self.push_event(Event::CommandRejected {
                    reason: err.to_string(),
                });
                None
            }
        }
    }
}
