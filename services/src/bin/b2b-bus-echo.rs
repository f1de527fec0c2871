//! Benchmark helper: echoes every message on `PREFIX/ping` back on
//! `--pong` (default `PREFIX/pong`), as a separate process, until `PREFIX/stop`
//! arrives or `--seconds` pass; `PREFIX` is `b2b/bench` unless given. Used by
//! `services/benches/bus.rs` to measure zenoh latency between processes, on the
//! plain and on the secured bus (where a cart may say things only under its own
//! keys, so the pong goes there).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use b2b_services::bus;
use clap::Parser;
use zenoh::Wait;

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
    b2b_services::run_main(|| {
        let session = bus::open(bus::config(Some(&cli.zenoh), bus::Role::Agent)?)?;
        let prefix = &cli.prefix;
        let pong_key = cli.pong.clone().unwrap_or_else(|| format!("{prefix}/pong"));
        let (ping_key, stop_key) = (format!("{prefix}/ping"), format!("{prefix}/stop"));
        let pong = session
            .declare_publisher(pong_key)
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let ping = session
            .declare_subscriber(format!("{prefix}/**"))
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let deadline = Instant::now() + Duration::from_secs(cli.seconds);
        while Instant::now() < deadline {
            if let Ok(Some(sample)) = ping.recv_timeout(Duration::from_millis(100)) {
                let key = sample.key_expr().as_str();
                if key == ping_key {
                    pong.put(sample.payload().clone())
                        .wait()
                        .map_err(|e| anyhow::anyhow!("{e}"))?;
                } else if key == stop_key {
                    break;
                }
            }
        }
        Ok(())
    })
}
