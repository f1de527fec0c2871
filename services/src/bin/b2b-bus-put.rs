//! Puts a file's bytes on one key of the bus, a number of times: for
//! operators checking what a configuration lets through, and for the tests
//! that play a rogue peer (`services/tests/secured_bus.rs`) as a process of its
//! own, with whatever configuration and certificate it was given.

use std::path::PathBuf;
use std::time::Duration;

use b2b_services::bus::{self, Bus};
use clap::Parser;

#[derive(Parser, Debug)]
#[command(
    name = "b2b-bus-put",
    about = "Put a file's bytes on a key of the bus, repeatedly"
)]
struct Cli {
    /// zenoh configuration file (JSON5).
    #[arg(long)]
    zenoh: PathBuf,
    /// The key expression to put on.
    #[arg(long)]
    key: String,
    /// The payload: this file's bytes.
    #[arg(long)]
    payload: PathBuf,
    /// How many times.
    #[arg(long, default_value_t = 10)]
    count: u32,
    /// Milliseconds between puts.
    #[arg(long, default_value_t = 200)]
    every_ms: u64,
}

fn main() -> std::process::ExitCode {
    b2b_services::init_logging();
    let cli = Cli::parse();
    b2b_services::run_main::<anyhow::Error>(|| {
        let payload = std::fs::read(&cli.payload)
            .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", cli.payload.display()))?;
        let bus = bus::ZenohBus::open(Some(&cli.zenoh), bus::Role::Agent)?;
        for _ in 0..cli.count {
            bus.put(&cli.key, payload.clone())?;
            std::thread::sleep(Duration::from_millis(cli.every_ms));
        }
        Ok(())
    })
}

b2b_services::every_flag_has_help!(Cli);
