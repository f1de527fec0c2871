//! The bus between processes, measured.
//!
//! 1. zenoh pose-message latency on loopback: this process publishes a flange-pose
//!    capture message on `b2b/bench/ping`, a separate `b2b-bus-echo` process sends
//!    it back, and half the round trip is the one-way latency. Reported as p50 /
//!    p99 (goal p99 <= 1 ms), on plain TCP and on the secured bus (`coordinator
//!    pki init`: mutual TLS and access control, so this process speaks as the
//!    coordinator and the echo as cart robot1, and every message is signed and
//!    checked: both ends use the services' `ZenohBus`), each with the time from
//!    opening a session to its first peer (the TCP or TLS handshake, median of 5).
//!    Then signing and checking alone, in this process.
//! 2. A full live replay of `datasets/sim-checkerboard-2x12`: coordinator and two
//!    agents as processes, detection and the joint solve included, wall time until
//!    the coordinator has written its result.
//!
//! `cargo bench -p b2b-services --bench bus` measures (2000 messages, 3 replays);
//! under `cargo test --benches` it runs a smoke pass (50 messages, 1 replay).
//! A custom harness, because criterion reports means, not percentiles.

use std::net::TcpListener;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use b2b_protocol::Pose;
use b2b_protocol::messages::{Capture, Envelope, Intrinsics};
use zenoh::Wait;

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .unwrap_or(17448)
}

fn configs(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let port = free_port();
    let listen = dir.join("listen.json5");
    let connect = dir.join("connect.json5");
    std::fs::write(
        &listen,
        format!(r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#),
    )
    .expect("write config");
    std::fs::write(
        &connect,
        // Listening on nothing, as a cart on the secured bus: the two
        // transports' sessions differ only in their links.
        format!(r#"{{ mode: "peer", listen: {{ endpoints: [] }}, connect: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#),
    )
    .expect("write config");
    (listen, connect)
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

fn pose_message() -> Vec<u8> {
    let body = Capture {
        index: 7,
        controller_time_s: Some(1.79e9),
        image: None,
        base_from_flange: Pose {
            t: [0.51, -0.1, 0.64],
            q: [0.0, 1.0, 0.0, 0.0],
        },
        camera: Intrinsics {
            width: 1280,
            height: 720,
            fx: 910.0,
            fy: 910.0,
            cx: 640.0,
            cy: 360.0,
            dist: vec![0.0; 5],
            estimated: false,
        },
        observation: None,
        rejected: Some("latency probe".into()),
        base_from_target: None,
        features: None,
    };
    serde_json::to_vec(&Envelope::new("robot1", 1, body)).expect("serialise")
}

/// The plain bus, or the secured one with its keys.
#[derive(Clone, Copy, PartialEq)]
enum Transport {
    Tcp,
    Tls,
}

/// Configurations for this process and the other one, and the keys each may
/// speak on: (listen, connect, ping prefix, pong key).
fn bus_for(
    transport: Transport,
    dir: &Path,
) -> (std::path::PathBuf, std::path::PathBuf, String, String) {
    match transport {
        Transport::Tcp => {
            let (listen, connect) = configs(dir);
            (listen, connect, "b2b/bench".into(), "b2b/bench/pong".into())
        }
        Transport::Tls => {
            let endpoint = format!("tls/127.0.0.1:{}", free_port());
            let endpoints = b2b_services::pki::Endpoints::at(&endpoint).expect("endpoint");
            let pki = dir.join("pki");
            b2b_services::pki::init(&pki, &["robot1".to_owned()], &endpoints).expect("pki");
            (
                pki.join("coordinator.json5"),
                pki.join("robot1.json5"),
                "b2b/coordinator/bench".into(),
                "b2b/agent/robot1/bench/pong".into(),
            )
        }
    }
}

/// Median time from opening a session with `connect` to its first peer (the
/// listener with `listen` running), over `runs` sessions.
fn handshake_ms(listen: &Path, connect: &Path, runs: usize) -> f64 {
    use b2b_services::bus::{Role, config, open};
    let _listener = open(config(Some(listen), Role::Coordinator).expect("config")).expect("listen");
    let mut ms = Vec::with_capacity(runs);
    for _ in 0..runs {
        let t0 = Instant::now();
        let s = open(config(Some(connect), Role::Agent).expect("config")).expect("session");
        while s.info().peers_zid().wait().next().is_none() {
            assert!(t0.elapsed() < Duration::from_secs(10), "never connected");
            std::thread::sleep(Duration::from_micros(200));
        }
        ms.push(t0.elapsed().as_secs_f64() * 1e3);
        let _ = s.close().wait();
    }
    percentile(&mut ms, 0.5)
}

fn latency(messages: usize, transport: Transport) {
    use b2b_services::bus::{Bus, Role, ZenohBus};
    let dir = tempfile::tempdir().expect("tempdir");
    let (listen, connect, prefix, pong_key) = bus_for(transport, dir.path());
    let handshake = handshake_ms(&listen, &connect, 5);
    // The services' own bus: on the secured configuration each message is
    // signed by its sender and checked by its receiver, both ways.
    let bus = ZenohBus::open(Some(&listen), Role::Coordinator).expect("session");
    assert_eq!(bus.signs(), transport == Transport::Tls);
    let pongs = bus.subscribe(&pong_key).expect("subscribe");
    let ping_key = format!("{prefix}/ping");
    let mut echo = Command::new(env!("CARGO_BIN_EXE_b2b-bus-echo"))
        .arg("--zenoh")
        .arg(&connect)
        .args(["--prefix", &prefix, "--pong", &pong_key])
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn echo");
    let payload = pose_message();
    // Wait until the echo answers.
    let start = Instant::now();
    loop {
        bus.put(&ping_key, payload.clone()).expect("put");
        if let Ok(Some(_)) = pongs.recv_timeout(Duration::from_millis(100)) {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "echo process never answered"
        );
    }
    while let Ok(Some(_)) = pongs.recv_timeout(Duration::from_millis(50)) {}
    let mut one_way_us = Vec::with_capacity(messages);
    for _ in 0..messages {
        let t0 = Instant::now();
        bus.put(&ping_key, payload.clone()).expect("put");
        match pongs.recv_timeout(Duration::from_secs(2)) {
            Ok(Some(m)) => {
                one_way_us.push(t0.elapsed().as_secs_f64() * 1e6 / 2.0);
                if transport == Transport::Tls {
                    assert_eq!(m.signer.as_deref(), Some("robot1"));
                }
            }
            _ => panic!("a ping was lost"),
        }
    }
    let _ = bus.put(&format!("{prefix}/stop"), b"stop".to_vec());
    let _ = echo.wait();
    println!(
        "zenoh pose message ({} bytes) between processes, one-way over loopback, {}, {} messages: session to first peer {:.1} ms; p50 {:.0} us, p99 {:.0} us, max {:.0} us",
        payload.len(),
        match transport {
            Transport::Tcp => "plain TCP",
            Transport::Tls => "mutual TLS + access control + signed messages",
        },
        messages,
        handshake,
        percentile(&mut one_way_us, 0.5),
        percentile(&mut one_way_us, 0.99),
        one_way_us.iter().copied().fold(0.0, f64::max)
    );
    if transport == Transport::Tls {
        signing_cost(&dir.path().join("pki"), &payload, messages);
    }
}

/// The per-message checks alone, in this process: signing a pose message, and
/// checking its signature (the certificate already checked once), p50 and p99.
fn signing_cost(pki: &Path, payload: &[u8], messages: usize) {
    use b2b_services::signing::{Identity, Verifier};
    let me =
        Identity::from_files(&pki.join("robot1.pem"), &pki.join("robot1.key")).expect("identity");
    let verifier = Verifier::from_file(&pki.join("ca.pem")).expect("authority");
    let key = "b2b/agent/robot1/capture";
    let (mut sign_us, mut verify_us) = (Vec::new(), Vec::new());
    for _ in 0..messages {
        let t0 = Instant::now();
        let signature = me.sign(key, payload).expect("sign");
        sign_us.push(t0.elapsed().as_secs_f64() * 1e6);
        let t0 = Instant::now();
        let signer = verifier
            .verify(key, payload, Some(&signature))
            .expect("verify");
        verify_us.push(t0.elapsed().as_secs_f64() * 1e6);
        assert_eq!(signer, "robot1");
    }
    println!(
        "per-message signature, {messages} pose messages: sign p50 {:.0} us, p99 {:.0} us; check p50 {:.0} us, p99 {:.0} us",
        percentile(&mut sign_us, 0.5),
        percentile(&mut sign_us, 0.99),
        percentile(&mut verify_us, 0.5),
        percentile(&mut verify_us, 0.99)
    );
}

fn replay(runs: usize) {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-checkerboard-2x12");
    let mut times = Vec::new();
    for _ in 0..runs {
        let dir = tempfile::tempdir().expect("tempdir");
        let (listen, connect) = configs(dir.path());
        let t0 = Instant::now();
        let mut coordinator = Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["run", "--robots", "robot1,robot2", "--zenoh"])
            .arg(&listen)
            .arg("--state-dir")
            .arg(dir.path().join("c"))
            .arg("--out")
            .arg(dir.path().join("RESULT.json"))
            .stdout(Stdio::null())
            .spawn()
            .expect("coordinator");
        let agents: Vec<_> = ["robot1", "robot2"]
            .iter()
            .map(|robot| {
                Command::new(env!("CARGO_BIN_EXE_agent"))
                    .args(["run", "--quiet", "--robot", robot, "--replay"])
                    .arg(&data)
                    .arg("--zenoh")
                    .arg(&connect)
                    .arg("--state-dir")
                    .arg(dir.path().join(robot))
                    .stdout(Stdio::null())
                    .spawn()
                    .expect("agent")
            })
            .collect();
        assert!(
            coordinator.wait().expect("wait").success(),
            "coordinator failed"
        );
        times.push(t0.elapsed().as_secs_f64());
        for mut a in agents {
            let _ = a.wait();
        }
    }
    let best = times.iter().copied().fold(f64::INFINITY, f64::min);
    println!(
        "live replay of 2 x 12 rendered captures (processes, zenoh, detection, joint solve): best of {runs}: {best:.2} s"
    );
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    for transport in [Transport::Tcp, Transport::Tls] {
        latency(if full { 2000 } else { 50 }, transport);
    }
    replay(if full { 3 } else { 1 });
}
