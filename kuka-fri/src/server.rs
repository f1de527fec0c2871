//! The simulated controller behind a UDP socket, on a cycle thread of its own.
//!
//! # Why a dedicated thread that shares nothing it waits for
//! A real controller's FRI cycle is hard real time. The simulated one must come close, or
//! it sends late whenever the machine is busy and then counts the client's replies missing
//! (see [`crate::realtime`]). So [`SimServer`]'s thread does nothing but the cycle: sleep
//! until the next deadline, take in the replies that arrived meanwhile, send. It runs under
//! SCHED_FIFO where permitted, works in stack buffers (no allocation per cycle on a perfect
//! link), and publishes what the rest of the process needs ([`SimSnapshot`]: joints, state,
//! counters) with a `try_lock`, so a reader that holds the lock, or is preempted while
//! holding it, costs it one skipped publication, never a wait. The application side
//! (rendering in the simulated cart, the `fri-sim-controller` binary) reads the snapshot
//! and sends its requests ([`SimServer::move_app_to`], [`SimServer::close_session`], ...)
//! through a channel the thread drains without blocking.
//!
//! # The period
//! Deadlines lie on a fixed grid: the controller keeps `next += period` and sleeps until
//! `next`, so the work of a cycle never lengthens the period (a sleep *after* the work
//! would). Late sends and skipped deadlines are counted ([`crate::SimStats`]); the benchmark
//! `benches/period.rs` measures the messages per 10 s this loop achieves.
//!
//! # The port
//! A real controller sends from its FRI port (30200 by default, the same number as the
//! client's), and KUKA's client, given the controller's address, `connect()`s its socket
//! to that port and drops datagrams from any other. So the server binds the controller's
//! FRI port ([`SimServerConfig::new`]: 30200) and sends from that socket; tests bind port 0.
//! Datagrams from any address other than the configured client's are not taken in, as a
//! real controller configured for one client would not ([`SimSnapshot::foreign`]).

use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, Sender, TryRecvError};
use std::sync::{Arc, Mutex, MutexGuard, TryLockError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use b2b_robot::Joints;

use crate::error::{FriError, Result};
use crate::messages::{ConnectionQuality, DEFAULT_PORT, MAX_DATAGRAM_SIZE, SessionState};
use crate::realtime::{CycleScheduling, DEFAULT_CYCLE_PRIORITY, promote_current_thread};
use crate::sim::{Link, LinkConfig, SimConfig, SimStats, SimulatedController};

/// Settings of a [`SimServer`].
#[derive(Clone, Debug)]
pub struct SimServerConfig {
    /// The controller's own address: its FRI port, which it sends from.
    pub bind: SocketAddr,
    /// The FRI client to send monitoring messages to; datagrams from elsewhere are ignored.
    pub client: SocketAddr,
    /// The simulated controller.
    pub sim: SimConfig,
    /// Start the FRI overlay whenever MONITORING_READY is reached, as a robot application
    /// that runs an overlay motion does.
    pub auto_command: bool,
    /// Impairments of the controller → client direction (perfect by default).
    pub downlink: LinkConfig,
    /// Impairments of the client → controller direction (perfect by default).
    pub uplink: LinkConfig,
    /// SCHED_FIFO priority of the cycle thread; `None` keeps normal scheduling.
    pub realtime_priority: Option<u8>,
}

impl SimServerConfig {
    /// Defaults: the controller's FRI port [`DEFAULT_PORT`] on loopback, perfect links,
    /// overlay started automatically, SCHED_FIFO at [`DEFAULT_CYCLE_PRIORITY`].
    pub fn new(client: SocketAddr, sim: SimConfig) -> Self {
        Self {
            bind: SocketAddr::from(([127, 0, 0, 1], DEFAULT_PORT)),
            client,
            sim,
            auto_command: true,
            downlink: LinkConfig::perfect(),
            uplink: LinkConfig::perfect(),
            realtime_priority: Some(DEFAULT_CYCLE_PRIORITY),
        }
    }
}

/// What the cycle thread last published.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimSnapshot {
    /// True joint positions (rad).
    pub q: Joints,
    /// The robot application's interpolated position (rad).
    pub ipo: Joints,
    /// Session state.
    pub state: SessionState,
    /// Connection quality.
    pub quality: ConnectionQuality,
    /// Counters, including the missed-reply audit.
    pub stats: SimStats,
    /// When a datagram from the client last arrived, if ever.
    pub heard: Option<Instant>,
    /// Datagrams from addresses other than the client's (not taken in).
    pub foreign: u64,
    /// How the cycle thread is scheduled.
    pub scheduling: CycleScheduling,
}

/// What the application asks of the controller.
#[derive(Clone, Copy, Debug)]
enum Request {
    MoveAppTo(Joints),
    StartCommanding,
    StopCommanding,
    AutoCommand(bool),
    CloseSession,
    OpenSession,
}

#[derive(Debug)]
struct Shared {
    snapshot: Mutex<SimSnapshot>,
    stop: AtomicBool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, SimSnapshot> {
        // A snapshot is plain data; recover it if a reader ever panicked.
        self.snapshot
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// A [`SimulatedController`] serving one client over UDP from its own cycle thread.
#[derive(Debug)]
pub struct SimServer {
    shared: Arc<Shared>,
    requests: Sender<Request>,
    local_addr: SocketAddr,
    thread: Option<JoinHandle<Result<SimulatedController>>>,
    finished: Option<SimulatedController>,
}

impl SimServer {
    /// Binds the socket and starts the cycle thread; the first message is due at once.
    pub fn start(config: SimServerConfig) -> Result<Self> {
        let socket = UdpSocket::bind(config.bind)?;
        let local_addr = socket.local_addr()?;
        let controller = SimulatedController::new(config.sim.clone(), Instant::now())?;
        let shared = Arc::new(Shared {
            snapshot: Mutex::new(snapshot(&controller, None, 0, CycleScheduling::Pending)),
            stop: AtomicBool::new(false),
        });
        let (requests, inbox) = mpsc::channel();
        let thread_shared = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("fri-sim-cycle".into())
            .spawn(move || serve(&thread_shared, &socket, controller, &config, &inbox))?;
        Ok(Self {
            shared,
            requests,
            local_addr,
            thread: Some(thread),
            finished: None,
        })
    }

    /// The bound address: the controller's FRI port (useful with port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The newest published state (at most one cycle old).
    pub fn snapshot(&self) -> SimSnapshot {
        *self.shared.lock()
    }

    /// Whether the cycle thread still runs (it stops on a socket error or on shutdown).
    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    fn request(&self, r: Request) {
        // A send error means the cycle thread has stopped; `is_running` reports that.
        let _ = self.requests.send(r);
    }

    /// The robot application moves to `q` (see [`SimulatedController::move_app_to`]).
    pub fn move_app_to(&self, q: Joints) {
        self.request(Request::MoveAppTo(q));
    }

    /// The robot application starts a motion with an FRI overlay.
    pub fn start_commanding(&self) {
        self.request(Request::StartCommanding);
    }

    /// The robot application ends the overlay motion.
    pub fn stop_commanding(&self) {
        self.request(Request::StopCommanding);
    }

    /// Whether the overlay is started whenever MONITORING_READY is reached.
    pub fn set_auto_command(&self, on: bool) {
        self.request(Request::AutoCommand(on));
    }

    /// The robot application closes the FRI session (IDLE).
    pub fn close_session(&self) {
        self.request(Request::CloseSession);
    }

    /// The robot application opens a new FRI session (MONITORING_WAIT).
    pub fn open_session(&self) {
        self.request(Request::OpenSession);
    }

    /// Stops the cycle thread and returns the final snapshot, or the error it stopped on.
    pub fn shutdown(mut self) -> Result<SimSnapshot> {
        self.stop_thread()?;
        Ok(self.snapshot())
    }

    /// Stops the cycle thread and returns the controller itself (every counter, the
    /// states it reported) with the final snapshot, or the error the thread stopped on.
    pub fn finish(mut self) -> Result<(SimulatedController, SimSnapshot)> {
        self.stop_thread()?;
        let snapshot = self.snapshot();
        let controller = self.finished.take().ok_or(FriError::DriverStopped)?;
        Ok((controller, snapshot))
    }

    fn stop_thread(&mut self) -> Result<()> {
        self.shared.stop.store(true, Ordering::SeqCst);
        match self.thread.take().map(JoinHandle::join) {
            None => Ok(()),
            Some(Ok(result)) => {
                self.finished = Some(result?);
                Ok(())
            }
            // The cycle has no panicking path; report one as a stopped driver.
            Some(Err(_)) => Err(FriError::DriverStopped),
        }
    }
}

impl Drop for SimServer {
    fn drop(&mut self) {
        // An error here was the server's to report through `shutdown`.
        let _ = self.stop_thread();
    }
}

fn snapshot(
    controller: &SimulatedController,
    heard: Option<Instant>,
    foreign: u64,
    scheduling: CycleScheduling,
) -> SimSnapshot {
    SimSnapshot {
        q: controller.q(),
        ipo: controller.ipo(),
        state: controller.state(),
        quality: controller.quality(),
        stats: controller.stats(),
        heard,
        foreign,
        scheduling,
    }
}

/// A link that is perfect is bypassed (no queue, no allocation).
fn impaired(cfg: &LinkConfig) -> Option<Link> {
    (*cfg != LinkConfig::perfect()).then(|| Link::new(*cfg))
}

/// The cycle, as a real controller runs it: sleep until the next deadline, take in the
/// replies that arrived meanwhile, send.
///
/// The wait is a sleep (a high-resolution timer, exact under SCHED_FIFO), not a socket
/// read timeout: those count in scheduler ticks (4 ms at the common 250 Hz) and made the
/// controller send most 5 ms cycles more than half a period late even on an idle machine.
fn serve(
    shared: &Shared,
    socket: &UdpSocket,
    mut controller: SimulatedController,
    config: &SimServerConfig,
    inbox: &Receiver<Request>,
) -> Result<SimulatedController> {
    let scheduling = promote_current_thread("simulated FRI controller", config.realtime_priority);
    socket.set_nonblocking(true)?;
    let mut down = impaired(&config.downlink);
    let mut up = impaired(&config.uplink);
    let mut auto_command = config.auto_command;
    let mut tx = [0u8; MAX_DATAGRAM_SIZE];
    // One byte more than FRI allows, so an oversized datagram is seen as such, not cut.
    let mut rx = [0u8; MAX_DATAGRAM_SIZE + 1];
    let mut heard = None;
    let mut foreign = 0u64;
    while !shared.stop.load(Ordering::Relaxed) {
        let mut next = controller.poll_timeout();
        for link in [&down, &up].into_iter().flatten() {
            if let Some(t) = link.next_delivery() {
                next = next.min(t);
            }
        }
        let wait = next.saturating_duration_since(Instant::now());
        if !wait.is_zero() {
            // Never longer than 20 ms, so a stop request is seen.
            std::thread::sleep(wait.min(Duration::from_millis(20)));
        }
        loop {
            match socket.recv_from(&mut rx) {
                Ok((n, from)) if from == config.client => {
                    let now = Instant::now();
                    heard = Some(now);
                    match up.as_mut() {
                        Some(link) => link.send(now, &rx[..n]),
                        None => take_in(&mut controller, now, &rx[..n]),
                    }
                }
                Ok(_) => foreign += 1,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                // An ICMP error from a send before the client was up.
                Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => {}
                Err(e) => return Err(e.into()),
            }
        }
        if let Some(link) = up.as_mut() {
            let now = Instant::now();
            while let Some(d) = link.poll_deliver(now) {
                take_in(&mut controller, now, &d);
            }
        }
        loop {
            match inbox.try_recv() {
                Ok(Request::MoveAppTo(q)) => controller.move_app_to(q),
                Ok(Request::StartCommanding) => controller.start_commanding(),
                Ok(Request::StopCommanding) => controller.stop_commanding(),
                Ok(Request::AutoCommand(on)) => auto_command = on,
                Ok(Request::CloseSession) => controller.close_session(),
                Ok(Request::OpenSession) => controller.open_session(),
                Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
            }
        }
        if auto_command && controller.state() == SessionState::MonitoringReady {
            controller.start_commanding();
        }
        let now = Instant::now();
        while let Some(n) = controller.poll_transmit(now, &mut tx) {
            match down.as_mut() {
                Some(link) => link.send(now, &tx[..n]),
                // A send error before the client binds is what hardware sees too.
                None => {
                    let _ = socket.send_to(&tx[..n], config.client);
                }
            }
        }
        if let Some(link) = down.as_mut() {
            while let Some(d) = link.poll_deliver(Instant::now()) {
                let _ = socket.send_to(&d, config.client);
            }
        }
        publish(shared, snapshot(&controller, heard, foreign, scheduling));
    }
    // The final state, published with a wait: nobody depends on this thread's timing now.
    *shared.lock() = snapshot(&controller, heard, foreign, scheduling);
    tracing::info!(stats = ?controller.stats(), "simulated FRI controller stopped");
    Ok(controller)
}

fn take_in(controller: &mut SimulatedController, now: Instant, datagram: &[u8]) {
    if let Err(e) = controller.handle_datagram(now, datagram) {
        tracing::warn!(
            reason = %crate::error::chain(&e),
            "simulated controller rejected a datagram"
        );
    }
}

/// Publishes without waiting: when a reader holds the lock this cycle's snapshot is
/// skipped (the next one supersedes it).
fn publish(shared: &Shared, snap: SimSnapshot) {
    match shared.snapshot.try_lock() {
        Ok(mut s) => *s = snap,
        Err(TryLockError::Poisoned(p)) => *p.into_inner() = snap,
        Err(TryLockError::WouldBlock) => {}
    }
}
