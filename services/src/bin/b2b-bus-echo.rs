//! Benchmark helper: echoes every message on `PREFIX/ping` back on
//! `--pong` (default `PREFIX/pong`), as a separate process, until `PREFIX/stop`
//! arrives or `--seconds` pass; `PREFIX` is `b2b/bench` unless given. Used by
//! `services/benches/bus.rs` to measure zenoh latency between processes, on the
//! plain and on the secured bus (where a cart may say things only under its own
//! keys, so the pong goes there, and every message is signed and checked).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use b2b_services::bus::{self, Bus};
use clap::Parser;

#[derive(Parser, Debug)]
#[command(
    name = "b2b-bus-echo",
    about = "Echo b2b/bench/ping to b2b/bench/pong (benchmark helper)"
)]
struct Cli {
    /// zenoh configuration file (JSON5).
    #[arg(long)]
    zenoh: PathBuf,
    /// Give up after this many seconds.
    #[arg(long, default_value_t = 60)]
    seconds: u64,
    /// Where the pings (`PREFIX/ping`) and the stop (`PREFIX/stop`) come from.
    #[arg(long, default_value = "b2b/bench")]
    prefix: String,
    /// Where the pongs go (default `PREFIX/pong`).
    #[arg(long)]
    pong: Option<String>,
}

fn main() -> std::process::ExitCode {
    b2b_services::init_logging();
    let cli = Cli::parse();
    b2b_services::run_main::<anyhow::Error>(|| {
        // Through the services' own bus: on a secured configuration every
        // ping's signature is checked and every pong signed, as the services do.
        let bus = bus::ZenohBus::open(Some(&cli.zenoh), bus::Role::Agent)?;
        let prefix = &cli.prefix;
        let pong_key = cli.pong.clone().unwrap_or_else(|| format!("{prefix}/pong"));
        let (ping_key, stop_key) = (format!("{prefix}/ping"), format!("{prefix}/stop"));
        let pings = bus.subscribe(&format!("{prefix}/**"))?;
        let deadline = Instant::now() + Duration::from_secs(cli.seconds);
        while Instant::now() < deadline {
            if let Some(m) = pings.recv_timeout(Duration::from_millis(100))? {
                if m.key == ping_key {
                    bus.put(&pong_key, m.payload)?;
                } else if m.key == stop_key {
                    break;
                }
            }
        }
        Ok(())
    })
}
