//! A blocking UDP driver around [`ClientSession`], and the client API the agent uses.
//!
//! # Why a cycle thread that owns the session
//! FRI is one datagram in, one datagram out, every 1–5 ms, and a reply that misses the
//! controller's next cycle counts as missing. So the driver's thread does nothing but the
//! cycle and never waits for another thread: it owns the socket and the session outright,
//! replies to each datagram as soon as it is decoded, works in stack buffers, and runs
//! under SCHED_FIFO where permitted ([`crate::realtime`]).
//!
//! The API reaches it in two ways that cannot block it:
//! * Reads (state, joints, stillness, counters) come from a [`View`] that the cycle thread
//!   publishes with `try_lock` after replying: a reader holding the lock (or preempted while
//!   holding it) delays a publication by a cycle, never a reply. Joint states and events
//!   that could not be published yet wait in preallocated queues.
//! * Motions are planned and path-checked on the caller's thread (milliseconds for a long
//!   move), with a clone of the session's guard, and handed over through a channel; the
//!   cycle thread only begins them ([`ClientSession::begin_motion`]), and every command it
//!   sends still passes the guard.
//!
//! As in KUKA's SDK, the client binds a local port (default 30200) and replies to whichever
//! address the controller's datagrams come from, unless a controller address is configured:
//! then the socket is `connect()`ed to it, as the SDK does, and datagrams from any other
//! address (another port of the controller's host included) never reach the client. A
//! controller sends from its FRI port, so the address to configure is `controller:30200`.

use std::collections::VecDeque;
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender, SyncSender, TryRecvError};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, TryLockError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use b2b_robot::Joints;

use crate::error::{FriError, Result};
use crate::guard::SafetyGuard;
use crate::joints::{JointHistory, JointState};
use crate::messages::{MAX_DATAGRAM_SIZE, SessionState};
use crate::realtime::{CycleScheduling, DEFAULT_CYCLE_PRIORITY, promote_current_thread};
use crate::session::{ClientSession, Event, PlannedMotion, SessionConfig, SessionStats};

/// Joint states kept for the view while it cannot be published (a second at 1 ms).
const PENDING_STATES: usize = 1024;
/// Finished or aborted motions remembered in the view.
const OUTCOMES: usize = 16;
/// Times a motion is planned again because the command origin moved meanwhile.
const PLAN_ATTEMPTS: usize = 3;

/// Settings of a [`FriClient`].
#[derive(Clone, Debug)]
pub struct FriClientConfig {
    /// Local address to bind (port 30200 on a real cell; port 0 in tests).
    pub bind: SocketAddr,
    /// Accept datagrams only from this controller address (its FRI port); the socket is
    /// connected to it.
    pub controller: Option<SocketAddr>,
    /// Session settings.
    pub session: SessionConfig,
    /// Longest the driver thread blocks in `recv` before checking timeouts, requests and
    /// shutdown.
    pub poll_interval: Duration,
    /// Extra time granted to a motion beyond its planned duration before `move_to` gives up.
    pub motion_grace: Duration,
    /// SCHED_FIFO priority of the cycle thread; `None` keeps normal scheduling.
    pub realtime_priority: Option<u8>,
}

impl FriClientConfig {
    /// Defaults for binding `bind`.
    pub fn new(bind: SocketAddr) -> Self {
        Self {
            bind,
            controller: None,
            session: SessionConfig::default(),
            poll_interval: Duration::from_millis(20),
            motion_grace: Duration::from_secs(2),
            realtime_priority: Some(DEFAULT_CYCLE_PRIORITY),
        }
    }
}

/// What the API reads: the cycle thread's latest publication.
#[derive(Debug)]
struct View {
    state: SessionState,
    stats: SessionStats,
    history: JointHistory,
    /// Where a motion begun now would start, if known.
    origin: Option<Joints>,
    /// Whether a motion is running.
    busy: bool,
    /// Finished (`None`) or aborted (`Some(reason)`) motions, newest last.
    outcomes: VecDeque<(u64, Option<String>)>,
    last_error: Option<String>,
    scheduling: CycleScheduling,
}

#[derive(Debug)]
struct Shared {
    view: Mutex<View>,
    changed: Condvar,
    stop: AtomicBool,
    running: AtomicBool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, View> {
        // No code path panics while holding the lock; recover the data if one ever did.
        self.view
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// What the API asks of the cycle thread.
#[derive(Debug)]
enum Request {
    Begin {
        motion: Box<PlannedMotion>,
        reply: SyncSender<Result<(u64, Duration)>>,
    },
    Stop,
}

/// An FRI client running on its own thread.
#[derive(Debug)]
pub struct FriClient {
    shared: Arc<Shared>,
    requests: Sender<Request>,
    guard: SafetyGuard,
    local_addr: SocketAddr,
    motion_grace: Duration,
    poll_interval: Duration,
    thread: Option<JoinHandle<()>>,
}

impl FriClient {
    /// Binds the socket and starts the driver thread.
    pub fn start(config: FriClientConfig, guard: SafetyGuard) -> Result<Self> {
        let socket = UdpSocket::bind(config.bind)?;
        if let Some(controller) = config.controller {
            socket.connect(controller)?;
        }
        let local_addr = socket.local_addr()?;
        let shared = Arc::new(Shared {
            view: Mutex::new(View {
                state: SessionState::Idle,
                stats: SessionStats::default(),
                history: JointHistory::new(config.session.history_capacity),
                origin: None,
                busy: false,
                outcomes: VecDeque::with_capacity(OUTCOMES),
                last_error: None,
                scheduling: CycleScheduling::Pending,
            }),
            changed: Condvar::new(),
            stop: AtomicBool::new(false),
            running: AtomicBool::new(true),
        });
        let (requests, inbox) = mpsc::channel();
        let poll = config.poll_interval.max(Duration::from_millis(1));
        let driver = Driver {
            session: ClientSession::new(config.session.clone(), guard.clone()),
            socket,
            controller: config.controller,
            poll,
            inbox,
            pending_states: VecDeque::with_capacity(PENDING_STATES),
            last_state: None,
            pending_outcomes: VecDeque::with_capacity(OUTCOMES),
            pending_error: None,
            dirty: true,
        };
        let thread_shared = Arc::clone(&shared);
        let priority = config.realtime_priority;
        let thread = std::thread::Builder::new()
            .name("fri-client".into())
            .spawn(move || {
                let scheduling = promote_current_thread("FRI client", priority);
                thread_shared.lock().scheduling = scheduling;
                driver.run(&thread_shared);
                thread_shared.running.store(false, Ordering::SeqCst);
                thread_shared.changed.notify_all();
            })?;
        Ok(Self {
            shared,
            requests,
            guard,
            local_addr,
            motion_grace: config.motion_grace,
            poll_interval: poll,
            thread: Some(thread),
        })
    }

    /// The bound local address (useful with port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The session state.
    pub fn state(&self) -> SessionState {
        self.shared.lock().state
    }

    /// Traffic counters.
    pub fn stats(&self) -> SessionStats {
        self.shared.lock().stats
    }

    /// How the cycle thread is scheduled (SCHED_FIFO if it was requested and permitted).
    pub fn scheduling(&self) -> CycleScheduling {
        self.shared.lock().scheduling
    }

    /// The last driver-level problem (socket error or rejected datagram), if any.
    pub fn last_error(&self) -> Option<String> {
        self.shared.lock().last_error.clone()
    }

    /// The newest measured joints with the controller time stamp.
    pub fn latest(&self) -> Option<JointState> {
        self.shared.lock().history.latest().copied()
    }

    /// Whether every joint stayed within `tol` rad over the last `window` of controller time.
    pub fn is_still(&self, window: Duration, tol: f64) -> bool {
        self.shared.lock().history.is_still(window, tol)
    }

    fn wait_until<T>(
        &self,
        timeout: Duration,
        what: &'static str,
        mut check: impl FnMut(&View) -> Option<T>,
    ) -> Result<T> {
        let deadline = Instant::now() + timeout;
        let mut view = self.shared.lock();
        loop {
            if let Some(v) = check(&view) {
                return Ok(v);
            }
            if !self.shared.running.load(Ordering::SeqCst) {
                return Err(FriError::DriverStopped);
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(FriError::Timeout {
                    what,
                    waited: timeout,
                });
            }
            let wait = (deadline - now).min(Duration::from_millis(50));
            view = match self.shared.changed.wait_timeout(view, wait) {
                Ok((g, _)) => g,
                Err(poisoned) => poisoned.into_inner().0,
            };
        }
    }

    /// Waits until the session reports `state`.
    pub fn wait_for_state(&self, state: SessionState, timeout: Duration) -> Result<()> {
        self.wait_until(timeout, "session state", |v| {
            (v.state == state).then_some(())
        })
    }

    /// Waits until the first measured joint state arrives.
    pub fn wait_for_joints(&self, timeout: Duration) -> Result<JointState> {
        self.wait_until(timeout, "measured joints", |v| v.history.latest().copied())
    }

    /// Moves to `target` along a synchronised trajectory and waits until it is reached.
    ///
    /// Fails at once outside COMMANDING_ACTIVE or if the target or the path violates the
    /// guard; fails later if the motion is aborted (state change, rejected command,
    /// connection loss) or takes longer than planned plus the configured grace.
    pub fn move_to(&self, target: Joints) -> Result<()> {
        let (id, duration) = self.begin(target)?;
        let result = self.wait_until(duration + self.motion_grace, "motion", |v| {
            v.outcomes
                .iter()
                .find(|(done, _)| *done == id)
                .map(|(_, aborted)| match aborted {
                    None => Ok(()),
                    Some(reason) => Err(FriError::MotionAborted {
                        reason: reason.clone(),
                    }),
                })
        });
        match result {
            Ok(r) => r,
            Err(e) => {
                self.stop_motion();
                Err(e)
            }
        }
    }

    /// Plans the motion here and has the cycle thread begin it.
    fn begin(&self, target: Joints) -> Result<(u64, Duration)> {
        let mut attempt = 0;
        loop {
            attempt += 1;
            let (state, origin, busy) = {
                let view = self.shared.lock();
                (view.state, view.origin, view.busy)
            };
            if state != SessionState::CommandingActive {
                return Err(FriError::NotCommanding { state });
            }
            if busy {
                return Err(FriError::MotionInProgress);
            }
            let origin = origin.ok_or(FriError::MissingField {
                message: crate::codec::MONITORING,
                field: "ipoData.jointPosition",
            })?;
            let motion = PlannedMotion::plan(&self.guard, origin, target)?;
            let (reply, answer) = mpsc::sync_channel(1);
            self.requests
                .send(Request::Begin {
                    motion: Box::new(motion),
                    reply,
                })
                .map_err(|_| FriError::DriverStopped)?;
            // The cycle thread serves requests at least once per poll interval.
            let waited = self.poll_interval * 10 + Duration::from_secs(1);
            match answer.recv_timeout(waited) {
                Ok(Err(FriError::MotionOriginMoved)) if attempt < PLAN_ATTEMPTS => {}
                Ok(result) => return result,
                Err(RecvTimeoutError::Disconnected) => return Err(FriError::DriverStopped),
                Err(RecvTimeoutError::Timeout) => {
                    return Err(FriError::Timeout {
                        what: "the driver to begin the motion",
                        waited,
                    });
                }
            }
        }
    }

    /// Brakes the running motion, if any (within a cycle or a poll interval).
    pub fn stop_motion(&self) {
        // A send error means the driver has stopped, and with it any motion.
        let _ = self.requests.send(Request::Stop);
    }

    /// Stops the driver thread and waits for it.
    pub fn shutdown(mut self) {
        self.stop_thread();
    }

    fn stop_thread(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            // The thread only returns; a join error would mean it panicked, nothing to do.
            let _ = t.join();
        }
    }
}

impl Drop for FriClient {
    fn drop(&mut self) {
        self.stop_thread();
    }
}

/// The cycle thread's own state.
#[derive(Debug)]
struct Driver {
    session: ClientSession,
    socket: UdpSocket,
    controller: Option<SocketAddr>,
    poll: Duration,
    inbox: Receiver<Request>,
    /// Joint states not yet in the view (oldest dropped when full).
    pending_states: VecDeque<JointState>,
    /// The newest joint state taken from the session.
    last_state: Option<JointState>,
    /// Motion outcomes not yet in the view.
    pending_outcomes: VecDeque<(u64, Option<String>)>,
    pending_error: Option<String>,
    /// Whether the view is behind the session.
    dirty: bool,
}

impl Driver {
    fn run(mut self, shared: &Shared) {
        // One byte more than FRI allows, so an oversized datagram is seen as such, not cut.
        let mut rx = [0u8; MAX_DATAGRAM_SIZE + 1];
        let mut tx = [0u8; MAX_DATAGRAM_SIZE];
        let mut read_timeout = None;
        while !shared.stop.load(Ordering::Relaxed) {
            let now = Instant::now();
            let wait = self
                .session
                .poll_timeout()
                .map_or(self.poll, |t| {
                    t.saturating_duration_since(now).min(self.poll)
                })
                .max(Duration::from_millis(1));
            if read_timeout != Some(wait) {
                if let Err(e) = self.socket.set_read_timeout(Some(wait)) {
                    self.pending_error = Some(format!("set_read_timeout: {e}"));
                    self.publish(shared, true);
                    return;
                }
                read_timeout = Some(wait);
            }
            match self.socket.recv_from(&mut rx) {
                Ok((n, from)) => {
                    if self.controller.is_some_and(|c| c != from) {
                        continue;
                    }
                    self.cycle(&rx[..n], from, &mut tx);
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(e) => {
                    // E.g. ICMP port unreachable reported on a later recv: keep serving.
                    self.pending_error = Some(format!("recv_from: {e}"));
                    self.dirty = true;
                    std::thread::sleep(Duration::from_millis(1));
                }
            }
            self.serve_requests();
            self.session.handle_timeout(Instant::now());
            self.collect_events();
            self.publish(shared, false);
        }
        self.publish(shared, true);
    }

    /// One datagram in, the reply out at once; bookkeeping after.
    fn cycle(&mut self, datagram: &[u8], from: SocketAddr, tx: &mut [u8]) {
        let now = Instant::now();
        match self.session.handle_datagram(now, datagram) {
            Ok(_) => {
                // Reply to the sender, as the SDK does with recvfrom's address.
                if let Some(len) = self.session.poll_transmit(now, tx)
                    && let Err(e) = self.socket.send_to(&tx[..len], from)
                {
                    self.pending_error = Some(format!("send_to {from}: {e}"));
                }
                if let Some(state) = self.session.latest_joint_state()
                    && self.last_state != Some(state)
                {
                    self.last_state = Some(state);
                    if self.pending_states.len() == PENDING_STATES {
                        self.pending_states.pop_front();
                    }
                    self.pending_states.push_back(state);
                }
            }
            Err(e) => {
                let reason = crate::error::chain(&e);
                tracing::debug!(%reason, %from, "rejected FRI datagram");
                self.pending_error = Some(reason);
            }
        }
        self.dirty = true;
    }

    fn serve_requests(&mut self) {
        loop {
            match self.inbox.try_recv() {
                Ok(Request::Begin { motion, reply }) => {
                    let result = self.session.begin_motion(*motion);
                    // The caller may have given up waiting; nothing to do then.
                    let _ = reply.try_send(result);
                }
                Ok(Request::Stop) => self.session.stop_motion(),
                // Disconnected: the client is being dropped and sets `stop`.
                Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
            }
            self.dirty = true;
        }
    }

    fn collect_events(&mut self) {
        while let Some(event) = self.session.poll_event() {
            self.dirty = true;
            match event {
                Event::MotionFinished { id } => self.push_outcome(id, None),
                Event::MotionAborted { id, reason } => self.push_outcome(id, Some(reason)),
                Event::StateChanged { from, to } => tracing::info!(%from, %to, "FRI session state"),
                Event::ConnectionLost { silent_for } => {
                    tracing::warn!(?silent_for, "FRI connection lost");
                }
                Event::CommandRejected { reason } => self.pending_error = Some(reason),
                Event::Monitoring { .. } | Event::Stale { .. } => {}
            }
        }
    }

    fn push_outcome(&mut self, id: u64, aborted: Option<String>) {
        if self.pending_outcomes.len() == OUTCOMES {
            self.pending_outcomes.pop_front();
        }
        self.pending_outcomes.push_back((id, aborted));
    }

    /// Brings the view up to date, waiting for its lock only if `wait` (at shutdown).
    fn publish(&mut self, shared: &Shared, wait: bool) {
        if !self.dirty {
            return;
        }
        let mut view = match shared.view.try_lock() {
            Ok(v) => v,
            Err(TryLockError::Poisoned(p)) => p.into_inner(),
            Err(TryLockError::WouldBlock) if wait => shared.lock(),
            Err(TryLockError::WouldBlock) => return,
        };
        for state in self.pending_states.drain(..) {
            view.history.push(state);
        }
        for outcome in self.pending_outcomes.drain(..) {
            if view.outcomes.len() == OUTCOMES {
                view.outcomes.pop_front();
            }
            view.outcomes.push_back(outcome);
        }
        if let Some(e) = self.pending_error.take() {
            view.last_error = Some(e);
        }
        view.state = self.session.state();
        view.stats = self.session.stats();
        view.origin = self.session.command_origin();
        view.busy = self.session.motion_in_progress();
        drop(view);
        self.dirty = false;
        shared.changed.notify_all();
    }
}
