//! Conformance over real loopback UDP: the simulated controller's cycle thread
//! ([`SimServer`]) against a client that does what KUKA's SDK does (`common::sdk`),
//! including `connect()`ing its socket to the controller's FRI port.
//!
//! Every assertion is on behaviour (states, positions, counters that do not depend on
//! how busy the machine is); wall-clock limits only bound a hang.

mod common;

use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use common::sdk::{Seen, SineOverlayClient};
use kuka_fri::messages::MAX_DATAGRAM_SIZE;
use kuka_fri::{
    ConnectionQuality, DEFAULT_CYCLE_PRIORITY, SessionState, SimConfig, SimServer, SimServerConfig,
};

fn loopback() -> SocketAddr {
    "127.0.0.1:0".parse().expect("addr")
}

/// The SDK-like client on its own thread.
struct ClientThread {
    stop: Arc<AtomicBool>,
    /// Messages seen in COMMANDING_ACTIVE so far.
    active: Arc<AtomicU64>,
    /// Send replies from this other socket instead of the receiving one.
    answer_from_other_port: Arc<AtomicBool>,
    thread: JoinHandle<SineOverlayClient>,
}

impl ClientThread {
    /// `socket` is bound (and, like the SDK given an address, connected to the controller);
    /// replies go out from another socket when `from_other_port`.
    fn start(socket: UdpSocket, controller: SocketAddr, from_other_port: bool) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let active = Arc::new(AtomicU64::new(0));
        let answer_from_other_port = Arc::new(AtomicBool::new(from_other_port));
        let other = UdpSocket::bind(loopback()).expect("second socket");
        let (s, a, o) = (
            Arc::clone(&stop),
            Arc::clone(&active),
            Arc::clone(&answer_from_other_port),
        );
        let thread = std::thread::spawn(move || {
            // As the controller's: a busy machine must not make the test client late.
            kuka_fri::realtime::promote_current_thread(
                "SDK-like test client",
                Some(DEFAULT_CYCLE_PRIORITY),
            );
            let mut client = SineOverlayClient::lbr_joint_sine_overlay();
            socket
                .set_read_timeout(Some(Duration::from_millis(50)))
                .expect("timeout");
            let mut rx = [0u8; MAX_DATAGRAM_SIZE + 1];
            let mut tx = [0u8; MAX_DATAGRAM_SIZE];
            while !s.load(Ordering::Relaxed) {
                let n = match socket.recv(&mut rx) {
                    Ok(n) => n,
                    Err(_) => continue, // timeout, or ICMP before the controller is up
                };
                if let Some(len) = client.on_datagram(&rx[..n], &mut tx) {
                    let _ = if o.load(Ordering::Relaxed) {
                        other.send_to(&tx[..len], controller)
                    } else {
                        socket.send(&tx[..len])
                    };
                }
                if client.state() == SessionState::CommandingActive {
                    a.fetch_add(1, Ordering::Relaxed);
                }
            }
            client
        });
        Self {
            stop,
            active,
            answer_from_other_port,
            thread,
        }
    }

    fn finish(self) -> SineOverlayClient {
        self.stop.store(true, Ordering::SeqCst);
        self.thread.join().expect("client thread")
    }
}

/// A controller on an ephemeral FRI port and a client socket connected to it.
fn controller_and_client(auto_command: bool) -> (SimServer, UdpSocket) {
    let socket = UdpSocket::bind(loopback()).expect("client binds");
    let server = SimServer::start(SimServerConfig {
        bind: loopback(),
        auto_command,
        ..SimServerConfig::new(
            socket.local_addr().expect("addr"),
            SimConfig {
                encoder_noise: 0.0,
                ..SimConfig::default()
            },
        )
    })
    .expect("controller starts");
    // As KUKA's SDK given the controller's address: only the controller's FRI port is heard.
    socket.connect(server.local_addr()).expect("connect");
    (server, socket)
}

fn wait_for(what: &str, limit: Duration, mut cond: impl FnMut() -> bool) {
    let end = Instant::now() + limit;
    while !cond() {
        assert!(Instant::now() < end, "no {what} within {limit:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn max_dev(seen: &[Seen], of: impl Fn(&Seen) -> f64) -> f64 {
    seen.iter()
        .filter(|m| m.state == SessionState::CommandingActive)
        .map(of)
        .fold(0.0, f64::max)
}

#[test]
fn lbr_joint_sine_overlay_over_udp_connected_to_the_controller_port() {
    let (server, socket) = controller_and_client(true);
    let client = ClientThread::start(socket, server.local_addr(), false);
    // 10 s of controller time in COMMANDING_ACTIVE at 5 ms: 2,000 messages.
    let active = Arc::clone(&client.active);
    wait_for("10 s of COMMANDING_ACTIVE", Duration::from_secs(90), || {
        active.load(Ordering::Relaxed) >= 2000 || !server.is_running()
    });
    let (controller, snap) = server.finish().expect("controller ran");
    let client = client.finish();
    let s = controller.stats();
    let ctx = format!("{s:?}, foreign {}", snap.foreign);
    assert_eq!(
        (s.violations, s.malformed, s.bad_reflections),
        (0, 0, 0),
        "{ctx}"
    );
    assert_eq!(snap.foreign, 0, "{ctx}");
    let amplitude = client.amplitude;
    // Each run of COMMANDING_ACTIVE holds the application's interpolated position. A busy
    // machine can miss enough replies to drop the quality below GOOD, which aborts the
    // overlay (the sim's documented semantics, never a violation: asserted above); the arm
    // stays where the overlay left it and the next run holds that. So each message is
    // measured against its own interpolated position. The measured joint 4 stays within
    // the amplitude of it; the other joints do not move.
    let joint4 = max_dev(&client.seen, |m| (m.measured[3] - m.ipo[3]).abs());
    let others = max_dev(&client.seen, |m| {
        (0..7)
            .filter(|&j| j != 3)
            .map(|j| (m.measured[j] - m.ipo[j]).abs())
            .fold(0.0, f64::max)
    });
    // The interpolated position does not move with the overlay within a run.
    let ipo = client
        .seen
        .windows(2)
        .filter(|w| w.iter().all(|m| m.state == SessionState::CommandingActive))
        .map(|w| {
            (0..7)
                .map(|j| (w[1].ipo[j] - w[0].ipo[j]).abs())
                .fold(0.0, f64::max)
        })
        .fold(0.0, f64::max);
    assert!(
        client
            .seen
            .iter()
            .any(|m| m.state == SessionState::CommandingActive),
        "COMMANDING_ACTIVE never reached: {ctx}"
    );
    let omega = std::f64::consts::TAU * client.frequency;
    let dt = f64::from(SimConfig::default().send_period_ms) * 1e-3;
    let bridged = if s.missed_replies == 0 {
        0.0
    } else {
        amplitude * ((1.0 + (3.0 * omega * dt).powi(2)).sqrt() - 1.0)
            + (amplitude * omega).powi(2) / (2.0 * SimConfig::default().arm_acceleration)
    };
    assert!(
        joint4 <= amplitude + bridged + 1e-9,
        "joint 4 at {joint4} rad (bound {}): {ctx}",
        amplitude + bridged
    );
    assert!(
        joint4 >= 0.9 * amplitude,
        "sine not applied ({joint4}): {ctx}"
    );
    assert!(others < 1e-9, "other joints moved {others} rad");
    assert_eq!(ipo, 0.0, "ipoData moved with the overlay");
    // Sequence counters: every reply reflects a message the client had received, and the
    // client's own counter counts up by one.
    for (k, c) in client.sent.iter().enumerate() {
        assert_eq!(c.sequence, k as u32);
        assert!(client.seen.iter().any(|m| m.sequence == c.reflected));
    }
    println!(
        "sine over UDP: {} messages, {} replies, {} late sends, {} missed replies, {} \
         aborted",
        s.sent, s.commands, s.late_sends, s.missed_replies, s.aborted
    );
}

#[test]
fn a_client_answering_from_another_port_is_never_heard() {
    let (server, socket) = controller_and_client(true);
    let client = ClientThread::start(socket, server.local_addr(), true);
    // Two quality windows of messages, and the client's answers to half of them (a
    // client thread the machine holds back answers late, not never).
    wait_for("100 messages, 50 answers", Duration::from_secs(30), || {
        let snap = server.snapshot();
        snap.stats.sent >= 100 && snap.foreign >= 50
    });
    let snap = server.snapshot();
    assert_eq!(snap.state, SessionState::MonitoringWait, "{snap:?}");
    assert_eq!(snap.quality, ConnectionQuality::Poor, "{snap:?}");
    assert_eq!(snap.stats.commands, 0, "{snap:?}");
    assert!(snap.foreign >= 50, "{snap:?}");
    // The same client answering from the port it receives on is heard, and commands.
    client.answer_from_other_port.store(false, Ordering::SeqCst);
    let active = Arc::clone(&client.active);
    wait_for("COMMANDING_ACTIVE", Duration::from_secs(30), || {
        active.load(Ordering::Relaxed) > 0
    });
    let client = client.finish();
    let (controller, _) = server.finish().expect("controller ran");
    assert_eq!(controller.stats().violations, 0);
    let early: Vec<_> = client.seen.iter().take(100).collect();
    assert!(
        early
            .iter()
            .all(|m| m.state == SessionState::MonitoringWait),
        "the client saw another state while unheard"
    );
    assert_eq!(
        early.last().map(|m| m.quality),
        Some(ConnectionQuality::Poor)
    );
}
