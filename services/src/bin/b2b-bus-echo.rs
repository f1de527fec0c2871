//! Benchmark helper: echoes every message on `b2b/bench/ping` back on
//! `b2b/bench/pong`, as a separate process, until `b2b/bench/stop` arrives or
//! `--seconds` pass. Used by `services/benches/bus.rs` to measure zenoh latency
//! between processes.

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
}

fn main() -> std::process::ExitCode {
    b2b_services::init_logging();
    let cli = Cli::parse();
    b2b_services::run_main(|| {
        let session = bus::open(bus::config(Some(&cli.zenoh), bus::Role::Agent)?)?;
        let pong = session
            .declare_publisher("b2b/bench/pong")
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let ping = session
            .declare_subscriber("b2b/bench/**")
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let deadline = Instant::now() + Duration::from_secs(cli.seconds);
        while Instant::now() < deadline {
            if let Ok(Some(sample)) = ping.recv_timeout(Duration::from_millis(100)) {
                match sample.key_expr().as_str() {
                    "b2b/bench/ping" => {
                        pong.put(sample.payload().clone())
                            .wait()
                            .map_err(|e| anyhow::anyhow!("{e}"))?;
                    }
                    "b2b/bench/stop" => break,
                    _ => {}
                }
            }
        }
        Ok(())
    })
}
