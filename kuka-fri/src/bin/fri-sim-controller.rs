//! `fri-sim-controller`: the simulated KUKA controller behind a UDP socket.
//!
//! Sends FRI monitoring messages to a client from the controller's FRI port, as a real
//! controller does, and follows its commands. Used by the two-process loopback test, by
//! hand against the agent, and against KUKA's own client SDK examples. `--help` lists
//! every flag.
//!
//! The session opens in MONITORING_WAIT; with `--command` the robot application starts an
//! FRI overlay (a held pose with a joint overlay) as soon as MONITORING_READY is reached
//! and `--command-after-ms` has passed. After `--duration-ms` the session closes (IDLE
//! messages for ten periods) and one summary line is printed:
//! `sim-summary key=value ...`. The exit code is 1 if any command violated the limits,
//! any datagram was malformed or any reply reflected a message never sent.

use std::net::{IpAddr, SocketAddr};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Parser;

use kuka_fri::messages::DEFAULT_PORT;
use kuka_fri::{
    DEFAULT_CYCLE_PRIORITY, LinkConfig, SessionState, SimConfig, SimServer, SimServerConfig,
};

/// The simulated KUKA controller (FRI 1.15) serving one client over UDP.
///
/// A controller and a client on one host cannot both hold the same port: KUKA's client
/// binds 30200 on every address. When `--client` is a loopback address on the
/// controller's own port and `--port` is not given, the controller therefore sends from
/// an ephemeral port (and says so); a client given the controller's address needs the
/// controller on another host or network namespace, as on a real cell.
#[derive(Debug, Parser)]
#[command(name = "fri-sim-controller", version)]
struct Cli {
    /// The FRI client's address (IP:PORT) to send monitoring messages to; replies from
    /// any other address are not taken in.
    #[arg(long)]
    client: SocketAddr,
    /// The controller's FRI port, which it binds and sends from [default: 30200].
    #[arg(long)]
    port: Option<u16>,
    /// The controller's address to bind: an IP (with `--port`), or IP:PORT (port 0 for an
    /// ephemeral one).
    #[arg(long, default_value = "0.0.0.0", value_parser = parse_bind)]
    bind: Bind,
    /// Send period in ms (1..=100).
    #[arg(long, default_value_t = 5)]
    send_period_ms: u32,
    /// The client answers every MULTIPLIER-th message (receive period ≤ 100 ms).
    #[arg(long, default_value_t = 1)]
    multiplier: u32,
    /// How long the session stays open, in ms; then it closes (IDLE) and the summary is
    /// printed.
    #[arg(long, default_value_t = 10_000)]
    duration_ms: u64,
    /// Start an FRI overlay (COMMANDING_WAIT, then COMMANDING_ACTIVE) once
    /// MONITORING_READY is reached.
    #[arg(long)]
    command: bool,
    /// Start the overlay no earlier than this many ms after the start.
    #[arg(long, default_value_t = 0)]
    command_after_ms: u64,
    /// Probability that a datagram is lost, in each direction.
    #[arg(long, default_value_t = 0.0)]
    loss: f64,
    /// One-way delay in ms, in each direction.
    #[arg(long, default_value_t = 0)]
    delay_ms: u64,
    /// Extra uniformly distributed one-way delay up to this many ms.
    #[arg(long, default_value_t = 0)]
    jitter_ms: u64,
    /// Probability that a datagram is held back two periods (reordered).
    #[arg(long, default_value_t = 0.0)]
    reorder: f64,
    /// Seed of the link impairments and the encoder noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Standard deviation of the encoder noise on measured positions, rad.
    #[arg(long, default_value_t = 2e-5)]
    noise: f64,
    /// Run the cycle thread with normal scheduling instead of SCHED_FIFO.
    #[arg(long)]
    normal_scheduling: bool,
}

/// `--bind`: an address with or without a port.
#[derive(Clone, Copy, Debug)]
enum Bind {
    Ip(IpAddr),
    Addr(SocketAddr),
}

fn parse_bind(s: &str) -> Result<Bind, String> {
    if let Ok(ip) = s.parse::<IpAddr>() {
        return Ok(Bind::Ip(ip));
    }
    s.parse::<SocketAddr>()
        .map(Bind::Addr)
        .map_err(|_| format!("`{s}` is neither an IP address nor IP:PORT"))
}

impl Cli {
    /// The address the controller binds, and a note when the default port had to give way.
    fn bind_address(&self) -> (SocketAddr, Option<String>) {
        match (self.bind, self.port) {
            (Bind::Addr(a), _) => (a, None),
            (Bind::Ip(ip), Some(port)) => (SocketAddr::new(ip, port), None),
            (Bind::Ip(ip), None) => {
                let same_host = self.client.ip().is_loopback() || self.client.ip() == ip;
                if same_host && self.client.port() == DEFAULT_PORT {
                    let note = format!(
                        "the client {} holds port {DEFAULT_PORT} on this host; sending from an \
                         ephemeral port instead (a client that connect()s to the controller's \
                         address needs the controller on another host or network namespace)",
                        self.client
                    );
                    (SocketAddr::new(ip, 0), Some(note))
                } else {
                    (SocketAddr::new(ip, DEFAULT_PORT), None)
                }
            }
        }
    }

    fn link(&self, seed: u64) -> LinkConfig {
        LinkConfig {
            loss: self.loss,
            delay: Duration::from_millis(self.delay_ms),
            jitter: Duration::from_millis(self.jitter_ms),
            reorder: self.reorder,
            reorder_delay: Duration::from_millis(u64::from(self.send_period_ms) * 2),
            seed,
        }
    }
}

/// Runs the session; `Ok(false)` when a command violated the limits or a datagram was bad.
fn run(cli: &Cli) -> anyhow::Result<bool> {
    for (what, p) in [("--loss", cli.loss), ("--reorder", cli.reorder)] {
        anyhow::ensure!(
            (0.0..=1.0).contains(&p),
            "{what} {p}: a probability in 0..=1"
        );
    }
    let (bind, note) = cli.bind_address();
    if let Some(note) = note {
        eprintln!("fri-sim-controller: {note}");
    }
    let sim = SimConfig {
        send_period_ms: cli.send_period_ms,
        receive_multiplier: cli.multiplier,
        encoder_noise: cli.noise,
        seed: cli.seed,
        ..SimConfig::default()
    };
    let delayed_start = cli.command && cli.command_after_ms > 0;
    let server = SimServer::start(SimServerConfig {
        bind,
        auto_command: cli.command && !delayed_start,
        downlink: cli.link(cli.seed.wrapping_add(1)),
        uplink: cli.link(cli.seed.wrapping_add(2)),
        realtime_priority: (!cli.normal_scheduling).then_some(DEFAULT_CYCLE_PRIORITY),
        ..SimServerConfig::new(cli.client, sim)
    })
    .with_context(|| format!("cannot start the controller on {bind}"))?;
    eprintln!(
        "fri-sim-controller: FRI port {} sending to {} every {} ms",
        server.local_addr(),
        cli.client,
        cli.send_period_ms
    );
    let start = Instant::now();
    let command_at = start + Duration::from_millis(cli.command_after_ms);
    let close_at = start + Duration::from_millis(cli.duration_ms);
    let period = Duration::from_millis(u64::from(cli.send_period_ms));
    let mut overlay_pending = delayed_start;
    while Instant::now() < close_at {
        anyhow::ensure!(server.is_running(), "the controller's cycle thread stopped");
        if overlay_pending && Instant::now() >= command_at {
            server.set_auto_command(true);
            overlay_pending = false;
        }
        std::thread::sleep(
            close_at
                .saturating_duration_since(Instant::now())
                .min(Duration::from_millis(10)),
        );
    }
    server.close_session();
    std::thread::sleep(period * 10);
    let (controller, snap) = server.finish().context("the controller's cycle thread")?;
    let stats = controller.stats();
    let states: Vec<&str> = controller
        .states_seen()
        .iter()
        .map(|s| s.proto_name())
        .collect();
    let q = controller.q();
    println!(
        "sim-summary sent={} sent_idle={} commands={} malformed={} stale={} violations={} \
         aborted={} bad_reflections={} missed_replies={} late_replies={} late_sends={} \
         skipped_cycles={} max_send_lateness_us={} foreign={} states={} q={}",
        stats.sent,
        stats.sent_idle,
        stats.commands,
        stats.malformed,
        stats.stale,
        stats.violations,
        stats.aborted,
        stats.bad_reflections,
        stats.missed_replies,
        stats.late_replies,
        stats.late_sends,
        stats.skipped_cycles,
        stats.max_send_lateness.as_micros(),
        snap.foreign,
        states.join(","),
        q.iter()
            .map(|v| format!("{v:.6}"))
            .collect::<Vec<_>>()
            .join(","),
    );
    if controller.state() != SessionState::Idle {
        eprintln!("fri-sim-controller: the session did not close");
    }
    Ok(stats.violations == 0 && stats.malformed == 0 && stats.bad_reflections == 0)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(&cli) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("fri-sim-controller: {e:#}");
            ExitCode::from(2)
        }
    }
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    use super::*;

    #[test]
    fn every_flag_has_help() {
        let cmd = Cli::command();
        let missing: Vec<_> = cmd
            .get_arguments()
            .filter(|a| {
                a.get_help().is_none() && !["help", "version"].contains(&a.get_id().as_str())
            })
            .map(|a| a.get_id().to_string())
            .collect();
        assert!(missing.is_empty(), "flags without help: {missing:?}");
    }

    #[test]
    fn the_controller_binds_its_fri_port_unless_a_local_client_holds_it() {
        let cli = |args: &[&str]| {
            Cli::try_parse_from(["fri-sim-controller"].iter().chain(args)).expect("parses")
        };
        let (a, note) = cli(&["--client", "192.168.1.5:30200"]).bind_address();
        assert_eq!((a.to_string(), note), ("0.0.0.0:30200".into(), None));
        let (a, note) = cli(&["--client", "127.0.0.1:30200"]).bind_address();
        assert_eq!(a.port(), 0);
        assert!(note.is_some());
        let (a, _) = cli(&["--client", "127.0.0.1:30200", "--port", "30201"]).bind_address();
        assert_eq!(a.to_string(), "0.0.0.0:30201");
        let (a, _) = cli(&["--client", "127.0.0.1:40000", "--bind", "127.0.0.1:0"]).bind_address();
        assert_eq!(a.to_string(), "127.0.0.1:0");
        let (a, _) = cli(&["--client", "127.0.0.1:40000", "--bind", "127.0.0.1"]).bind_address();
        assert_eq!(a.to_string(), "127.0.0.1:30200");
        assert!(
            Cli::try_parse_from(["x", "--client", "127.0.0.1:1", "--bind", "nowhere"]).is_err()
        );
    }
}
