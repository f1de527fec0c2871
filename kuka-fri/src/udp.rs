//! A blocking UDP driver around [`ClientSession`], and the client API the agent uses.
//!
//! # Why a plain thread
//! FRI is one datagram in, at most one datagram out, every 1–5 ms. A dedicated OS thread
//! with a blocking socket and a short read timeout is the simplest thing that meets that
//! deadline; it needs no async runtime in the agent and keeps all protocol logic in the
//! sans-I/O core. The thread owns the socket; the session sits behind a mutex that the
//! thread holds only while handling one datagram, so API calls never wait longer than that.
//!
//! As in KUKA's SDK, the client binds a local port (default 30200) and replies to whichever
//! address the controller's datagrams come from, unless a controller address is configured,
//! in which case datagrams from other addresses are ignored.

use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use b2b_robot::Joints;

use crate::error::{FriError, Result};
use crate::guard::SafetyGuard;
use crate::joints::JointState;
use crate::messages::{MAX_DATAGRAM_SIZE, SessionState};
use crate::session::{ClientSession, Event, SessionConfig, SessionStats};

/// Settings of a [`FriClient`].
#[derive(Clone, Debug)]
pub struct FriClientConfig {
    /// Local address to bind (port 30200 on a real cell; port 0 in tests).
    pub bind: SocketAddr,
    /// Accept datagrams only from this controller address.
    pub controller: Option<SocketAddr>,
    /// Session settings.
    pub session: SessionConfig,
    /// Longest the driver thread blocks in `recv` before checking timeouts and shutdown.
    pub poll_interval: Duration,
    /// Extra time granted to a motion beyond its planned duration before `move_to` gives up.
    pub motion_grace: Duration,
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
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
enum MotionStatus {
    Idle,
    Running(u64),
    Finished(u64),
    Aborted(u64, String),
}

#[derive(Debug)]
struct Inner {
    session: ClientSession,
    motion: MotionStatus,
    last_error: Option<String>,
}

#[derive(Debug)]
struct Shared {
    inner: Mutex<Inner>,
    changed: Condvar,
    stop: AtomicBool,
    running: AtomicBool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Inner> {
        // No code path panics while holding the lock; recover the data if one ever did.
        self.inner
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// An FRI client running on its own thread.
#[derive(Debug)]
pub struct FriClient {
    shared: Arc<Shared>,
    local_addr: SocketAddr,
    motion_grace: Duration,
    thread: Option<JoinHandle<()>>,
}

impl FriClient {
    /// Binds the socket and starts the driver thread.
    pub fn start(config: FriClientConfig, guard: SafetyGuard) -> Result<Self> {
        let socket = UdpSocket::bind(config.bind)?;
        let local_addr = socket.local_addr()?;
        let shared = Arc::new(Shared {
            inner: Mutex::new(Inner {
                session: ClientSession::new(config.session.clone(), guard),
                motion: MotionStatus::Idle,
                last_error: None,
            }),
            changed: Condvar::new(),
            stop: AtomicBool::new(false),
            running: AtomicBool::new(true),
        });
        let thread_shared = Arc::clone(&shared);
        let poll = config.poll_interval.max(Duration::from_millis(1));
        let controller = config.controller;
        let thread = std::thread::Builder::new()
            .name("fri-client".into())
            .spawn(move || {
                drive(&thread_shared, &socket, controller, poll);
                thread_shared.running.store(false, Ordering::SeqCst);
                thread_shared.changed.notify_all();
            })?;
        Ok(Self {
            shared,
            local_addr,
            motion_grace: config.motion_grace,
            thread: Some(thread),
        })
    }

    /// The bound local address (useful with port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The session state.
    pub fn state(&self) -> SessionState {
        self.shared.lock().session.state()
    }

    /// Traffic counters.
    pub fn stats(&self) -> SessionStats {
        self.shared.lock().session.stats()
    }

    /// The last driver-level problem (socket error or rejected datagram), if any.
    pub fn last_error(&self) -> Option<String> {
        self.shared.lock().last_error.clone()
    }

    /// The newest measured joints with the controller time stamp.
    pub fn latest(&self) -> Option<JointState> {
        self.shared.lock().session.latest_joint_state()
    }

    /// Whether every joint stayed within `tol` rad over the last `window` of controller time.
    pub fn is_still(&self, window: Duration, tol: f64) -> bool {
        self.shared.lock().session.is_still(window, tol)
    }

    fn wait_until<T>(
        &self,
        timeout: Duration,
        what: &'static str,
        mut check: impl FnMut(&mut Inner) -> Option<T>,
    ) -> Result<T> {
        let deadline = Instant::now() + timeout;
        let mut guard = self.shared.lock();
        loop {
            if let Some(v) = check(&mut guard) {
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
            guard = match self.shared.changed.wait_timeout(guard, wait) {
                Ok((g, _)) => g,
                Err(poisoned) => poisoned.into_inner().0,
            };
        }
    }

    /// Waits until the session reports `state`.
    pub fn wait_for_state(&self, state: SessionState, timeout: Duration) -> Result<()> {
        self.wait_until(timeout, "session state", |i| {
            (i.session.state() == state).then_some(())
        })
    }

    /// Waits until the first measured joint state arrives.
    pub fn wait_for_joints(&self, timeout: Duration) -> Result<JointState> {
        self.wait_until(timeout, "measured joints", |i| {
            i.session.latest_joint_state()
        })
    }

    /// Moves to `target` along a synchronised trajectory and waits until it is reached.
    ///
    /// Fails at once outside COMMANDING_ACTIVE or if the target or the path violates the
    /// guard; fails later if the motion is aborted (state change, rejected command,
    /// connection loss) or takes longer than planned plus the configured grace.
    pub fn move_to(&self, target: Joints) -> Result<()> {
        let (id, duration) = {
            let mut inner = self.shared.lock();
            let (id, duration) = inner.session.start_motion(target)?;
            inner.motion = MotionStatus::Running(id);
            (id, duration)
        };
        let result = self.wait_until(duration + self.motion_grace, "motion", |i| {
            match &i.motion {
                MotionStatus::Finished(done) if *done == id => Some(Ok(())),
                MotionStatus::Aborted(done, reason) if *done == id => {
                    Some(Err(FriError::MotionAborted {
                        reason: reason.clone(),
                    }))
                }
                _ => None,
            }
        });
        match result {
            Ok(r) => r,
            Err(e) => {
                self.shared.lock().session.stop_motion();
                Err(e)
            }
        }
    }

    /// Brakes the running motion, if any.
    pub fn stop_motion(&self) {
        self.shared.lock().session.stop_motion();
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

fn drain_events(inner: &mut Inner) {
    while let Some(event) = inner.session.poll_event() {
        match event {
            Event::MotionFinished { id } => inner.motion = MotionStatus::Finished(id),
            Event::MotionAborted { id, reason } => inner.motion = MotionStatus::Aborted(id, reason),
            Event::StateChanged { from, to } => tracing::info!(%from, %to, "FRI session state"),
            Event::ConnectionLost { silent_for } => {
                tracing::warn!(?silent_for, "FRI connection lost");
            }
            Event::CommandRejected { reason } => inner.last_error = Some(reason),
            Event::Monitoring { .. } | Event::Stale { .. } => {}
        }
    }
}

fn drive(shared: &Shared, socket: &UdpSocket, controller: Option<SocketAddr>, poll: Duration) {
    // One byte more than FRI allows, so an oversized datagram is seen as such, not cut.
    let mut rx = vec![0u8; MAX_DATAGRAM_SIZE + 1];
    let mut tx = vec![0u8; MAX_DATAGRAM_SIZE];
    while !shared.stop.load(Ordering::SeqCst) {
        let wait = {
            let inner = shared.lock();
            let now = Instant::now();
            inner
                .session
                .poll_timeout()
                .map_or(poll, |t| t.saturating_duration_since(now).min(poll))
        };
        if let Err(e) = socket.set_read_timeout(Some(wait.max(Duration::from_millis(1)))) {
            shared.lock().last_error = Some(format!("set_read_timeout: {e}"));
            return;
        }
        match socket.recv_from(&mut rx) {
            Ok((n, from)) => {
                if controller.is_some_and(|c| c != from) {
                    continue;
                }
                let mut inner = shared.lock();
                let now = Instant::now();
                match inner.session.handle_datagram(now, &rx[..n]) {
                    Ok(_) => {
                        // Reply to the sender, as the SDK does with recvfrom's address.
                        if let Some(len) = inner.session.poll_transmit(now, &mut tx)
                            && let Err(e) = socket.send_to(&tx[..len], from)
                        {
                            inner.last_error = Some(format!("send_to {from}: {e}"));
                        }
                    }
                    Err(e) => {
                        let reason = crate::error::chain(&e);
                        tracing::debug!(%reason, %from, "rejected FRI datagram");
                        inner.last_error = Some(reason);
                    }
                }
                drain_events(&mut inner);
                drop(inner);
                shared.changed.notify_all();
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(e) => {
                // E.g. ICMP port unreachable reported on a later recv: keep serving.
                shared.lock().last_error = Some(format!("recv_from: {e}"));
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        let mut inner = shared.lock();
        inner.session.handle_timeout(Instant::now());
        drain_events(&mut inner);
        drop(inner);
        shared.changed.notify_all();
    }
}
