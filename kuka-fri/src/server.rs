//! The simulated controller behind a UDP socket, on a cycle thread of its own.
//!
//! # Why a dedicated thread that shares nothing it waits for
//! A real controller's FRI cycle is hard real time. The simulated one must come close, or
//! it sends late whenever the machine is busy and then counts the client's replies missing
//! (see [`crate::realtime`]). So [`SimServer`]'s thread does nothing but the cycle: sleep
//! until due, take in the replies, send. It runs under SCHED_FIFO where permitted,
//! works in stack buffers (no allocation per cycle), and publishes what the rest of the
//! process needs ([`SimSnapshot`]: joints, state, counters) with a `try_lock`, so a reader
//! that holds the lock, or is preempted while holding it, costs it one skipped
//! publication, never a wait. The application side (rendering, in the simulated cart)
//! reads the snapshot from its own threads.

use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, TryLockError};
use std::thread::JoinHandle;
use std::time::Instant;

use b2b_robot::Joints;

use crate::error::{FriError, Result};
use crate::messages::{ConnectionQuality, MAX_DATAGRAM_SIZE, SessionState};
use crate::realtime::{CycleScheduling, DEFAULT_CYCLE_PRIORITY, promote_current_thread};
use crate::sim::{SimConfig, SimStats, SimulatedController};

/// Settings of a [`SimServer`].
#[derive(Clone, Debug)]
pub struct SimServerConfig {
    /// The controller's own address.
    pub bind: SocketAddr,
    /// The FRI client to send monitoring messages to; datagrams from elsewhere are ignored.
    pub client: SocketAddr,
    /// The simulated controller.
    pub sim: SimConfig,
    /// Start the FRI overlay whenever MONITORING_READY is reached, as a robot application
    /// that runs an overlay motion does.
    pub auto_command: bool,
    /// SCHED_FIFO priority of the cycle thread; `None` keeps normal scheduling.
    pub realtime_priority: Option<u8>,
}

impl SimServerConfig {
    /// Defaults: loopback with an ephemeral port, overlay started automatically, SCHED_FIFO
    /// at [`DEFAULT_CYCLE_PRIORITY`].
    pub fn new(client: SocketAddr, sim: SimConfig) -> Self {
        Self {
            bind: SocketAddr::from(([127, 0, 0, 1], 0)),
            client,
            sim,
            auto_command: true,
            realtime_priority: Some(DEFAULT_CYCLE_PRIORITY),
        }
    }
}

/// What the cycle thread last published.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimSnapshot {
    /// True joint positions (rad).
    pub q: Joints,
    /// Session state.
    pub state: SessionState,
    /// Connection quality.
    pub quality: ConnectionQuality,
    /// Counters, including the missed-reply audit.
    pub stats: SimStats,
    /// When a datagram from the client last arrived, if ever.
    pub heard: Option<Instant>,
    /// How the cycle thread is scheduled.
    pub scheduling: CycleScheduling,
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
    local_addr: SocketAddr,
    thread: Option<JoinHandle<Result<()>>>,
}

impl SimServer {
    /// Binds the socket and starts the cycle thread; the first message is due at once.
    pub fn start(config: SimServerConfig) -> Result<Self> {
        let socket = UdpSocket::bind(config.bind)?;
        let local_addr = socket.local_addr()?;
        let controller = SimulatedController::new(config.sim.clone(), Instant::now())?;
        let shared = Arc::new(Shared {
            snapshot: Mutex::new(snapshot(&controller, None, CycleScheduling::Pending)),
            stop: AtomicBool::new(false),
        });
        let thread_shared = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("fri-sim-cycle".into())
            .spawn(move || serve(&thread_shared, &socket, controller, &config))?;
        Ok(Self {
            shared,
            local_addr,
            thread: Some(thread),
        })
    }

    /// The bound address (useful with port 0).
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

    /// Stops the cycle thread and returns the final snapshot, or the error it stopped on.
    pub fn shutdown(mut self) -> Result<SimSnapshot> {
        self.stop_thread()?;
        Ok(self.snapshot())
    }

    fn stop_thread(&mut self) -> Result<()> {
        self.shared.stop.store(true, Ordering::SeqCst);
        match self.thread.take().map(JoinHandle::join) {
            None => Ok(()),
            Some(Ok(result)) => result,
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
    scheduling: CycleScheduling,
) -> SimSnapshot {
    SimSnapshot {
        q: controller.q(),
        state: controller.state(),
        quality: controller.quality(),
        stats: controller.stats(),
        heard,
        scheduling,
    }
}

/// The cycle, as a real controller runs it: sleep until the next message is due, take in
/// the replies that arrived meanwhile, send.
///
/// The wait is a sleep (a high-resolution timer, exact under SCHED_FIFO), not a socket
/// read timeout: those count in scheduler ticks (4 ms at the common 250 Hz) and made the
/// controller send most 5 ms cycles more than half a period late even on an idle machine.
fn serve(
    shared: &Shared,
    socket: &UdpSocket,
    mut controller: SimulatedController,
    config: &SimServerConfig,
) -> Result<()> {
    let scheduling = promote_current_thread("simulated FRI controller", config.realtime_priority);
    socket.set_nonblocking(true)?;
    let mut tx = [0u8; MAX_DATAGRAM_SIZE];
    // One byte more than FRI allows, so an oversized datagram is seen as such, not cut.
    let mut rx = [0u8; MAX_DATAGRAM_SIZE + 1];
    let mut heard = None;
    while !shared.stop.load(Ordering::Relaxed) {
        let wait = controller
            .poll_timeout()
            .saturating_duration_since(Instant::now());
        if !wait.is_zero() {
            std::thread::sleep(wait);
        }
        loop {
            match socket.recv_from(&mut rx) {
                Ok((n, from)) if from == config.client => {
                    let now = Instant::now();
                    heard = Some(now);
                    if let Err(e) = controller.handle_datagram(now, &rx[..n]) {
                        tracing::warn!(
                            reason = %crate::error::chain(&e),
                            "simulated controller rejected a datagram"
                        );
                    }
                }
                Ok(_) => {}
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                // An ICMP error from a send before the client was up.
                Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => {}
                Err(e) => return Err(e.into()),
            }
        }
        if config.auto_command && controller.state() == SessionState::MonitoringReady {
            controller.start_commanding();
        }
        while let Some(n) = controller.poll_transmit(Instant::now(), &mut tx) {
            // A send error before the client binds is what hardware sees too.
            let _ = socket.send_to(&tx[..n], config.client);
        }
        publish(shared, snapshot(&controller, heard, scheduling));
    }
    // The final state, published with a wait: nobody depends on this thread's timing now.
    *shared.lock() = snapshot(&controller, heard, scheduling);
    tracing::info!(stats = ?controller.stats(), "simulated FRI controller stopped");
    Ok(())
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
