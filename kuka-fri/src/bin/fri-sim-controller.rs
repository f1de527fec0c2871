//! `fri-sim-controller`: the simulated KUKA controller behind a UDP socket.
//!
//! Sends FRI monitoring messages to a client, as a real controller does, and follows its
//! commands. Used by the two-process loopback test and by hand against the agent.
//!
//! ```text
//! fri-sim-controller --client 127.0.0.1:30200 [--bind 127.0.0.1:0] [--send-period-ms 5]
//!     [--multiplier 1] [--duration-ms 10000] [--command] [--command-after-ms 0]
//!     [--loss 0.0] [--delay-ms 0] [--jitter-ms 0] [--reorder 0.0] [--seed 1] [--noise 2e-5]
//! ```
//! The session opens in MONITORING_WAIT; with `--command` the robot application starts an
//! FRI overlay as soon as MONITORING_READY is reached (and `--command-after-ms` has passed).
//! After `--duration-ms` the session closes (a few IDLE messages are sent) and one summary
//! line is printed: `sim-summary key=value ...`. The exit code is 1 if any command violated
//! the limits or any datagram was malformed.

use b2b_errors::chain;
use std::net::{SocketAddr, UdpSocket};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use kuka_fri::messages::MAX_DATAGRAM_SIZE;
use kuka_fri::{Link, LinkConfig, SessionState, SimConfig, SimulatedController};

#[derive(Debug)]
struct Args {
    client: SocketAddr,
    bind: SocketAddr,
    send_period_ms: u32,
    multiplier: u32,
    duration: Duration,
    command: bool,
    command_after: Duration,
    link: LinkConfig,
    seed: u64,
    noise: f64,
}

fn parse() -> Result<Args, String> {
    let mut client = None;
    let mut a = Args {
        client: SocketAddr::from(([127, 0, 0, 1], 30200)),
        bind: SocketAddr::from(([127, 0, 0, 1], 0)),
        send_period_ms: 5,
        multiplier: 1,
        duration: Duration::from_secs(10),
        command: false,
        command_after: Duration::ZERO,
        link: LinkConfig::perfect(),
        seed: 1,
        noise: 2e-5,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        if flag == "--command" {
            a.command = true;
            continue;
        }
        if flag == "--help" || flag == "-h" {
            return Err("see the module documentation of fri-sim-controller".into());
        }
        let value = it.next().ok_or_else(|| format!("{flag} needs a value"))?;
        let bad = |e: &dyn std::fmt::Display| format!("{flag} {value}: {e}");
        let ms = |v: &str| {
            v.parse::<u64>()
                .map(Duration::from_millis)
                .map_err(|e| bad(&e))
        };
        match flag.as_str() {
            "--client" => client = Some(value.parse().map_err(|e| bad(&e))?),
            "--bind" => a.bind = value.parse().map_err(|e| bad(&e))?,
            "--send-period-ms" => a.send_period_ms = value.parse().map_err(|e| bad(&e))?,
            "--multiplier" => a.multiplier = value.parse().map_err(|e| bad(&e))?,
            "--duration-ms" => a.duration = ms(&value)?,
            "--command-after-ms" => a.command_after = ms(&value)?,
            "--loss" => a.link.loss = value.parse().map_err(|e| bad(&e))?,
            "--delay-ms" => a.link.delay = ms(&value)?,
            "--jitter-ms" => a.link.jitter = ms(&value)?,
            "--reorder" => a.link.reorder = value.parse().map_err(|e| bad(&e))?,
            "--seed" => a.seed = value.parse().map_err(|e| bad(&e))?,
            "--noise" => a.noise = value.parse().map_err(|e| bad(&e))?,
            other => return Err(format!("unknown argument {other}")),
        }
    }
    a.client = client.ok_or("--client ADDR is required")?;
    a.link.seed = a.seed.wrapping_add(1);
    a.link.reorder_delay = Duration::from_millis(u64::from(a.send_period_ms) * 2);
    Ok(a)
}

fn run(args: &Args) -> Result<bool, Box<dyn std::error::Error>> {
    let socket = UdpSocket::bind(args.bind)?;
    let start = Instant::now();
    let cfg = SimConfig {
        send_period_ms: args.send_period_ms,
        receive_multiplier: args.multiplier,
        encoder_noise: args.noise,
        seed: args.seed,
        ..SimConfig::default()
    };
    let mut sim = SimulatedController::new(cfg, start)?;
    let mut link = Link::new(args.link);
    let mut buf = vec![0u8; MAX_DATAGRAM_SIZE];
    let mut rx = vec![0u8; MAX_DATAGRAM_SIZE + 1];
    let mut states_seen = vec![sim.state()];
    let close_at = start + args.duration;
    let end = close_at + sim.send_period() * 10;
    let mut closed = false;
    loop {
        let now = Instant::now();
        if now >= end {
            break;
        }
        if !closed && now >= close_at {
            sim.close_session();
            closed = true;
        }
        if args.command
            && !closed
            && sim.state() == SessionState::MonitoringReady
            && now >= start + args.command_after
        {
            sim.start_commanding();
        }
        while let Some(n) = sim.poll_transmit(now, &mut buf) {
            link.send(now, &buf[..n]);
        }
        if states_seen.last() != Some(&sim.state()) {
            states_seen.push(sim.state());
        }
        while let Some(d) = link.poll_deliver(now) {
            // A send error (client not yet bound) is what a real controller would see too.
            let _ = socket.send_to(&d, args.client);
        }
        let next = link
            .next_delivery()
            .map_or(sim.poll_timeout(), |t| t.min(sim.poll_timeout()));
        let wait = next
            .saturating_duration_since(Instant::now())
            .max(Duration::from_micros(100));
        socket.set_read_timeout(Some(wait))?;
        match socket.recv_from(&mut rx) {
            Ok((n, from)) if from == args.client => {
                if let Err(e) = sim.handle_datagram(Instant::now(), &rx[..n]) {
                    eprintln!("fri-sim-controller: rejected datagram: {}", chain(&e));
                }
            }
            Ok(_) => {}
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => {} // ICMP port unreachable while the client is not up yet.
        }
    }
    let stats = sim.stats();
    let q = sim.q();
    let states: Vec<&str> = states_seen.iter().map(|s| s.proto_name()).collect();
    println!(
        "sim-summary sent={} commands={} malformed={} stale={} violations={} aborted={} bad_reflections={} states={} q={}",
        stats.sent,
        stats.commands,
        stats.malformed,
        stats.stale,
        stats.violations,
        stats.aborted,
        stats.bad_reflections,
        states.join(","),
        q.iter()
            .map(|v| format!("{v:.6}"))
            .collect::<Vec<_>>()
            .join(","),
    );
    Ok(stats.violations == 0 && stats.malformed == 0 && stats.bad_reflections == 0)
}

fn main() -> ExitCode {
    let args = match parse() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("fri-sim-controller: {e}");
            return ExitCode::from(2);
        }
    };
    match run(&args) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("fri-sim-controller: {}", chain(e.as_ref()));
            ExitCode::from(2)
        }
    }
}
