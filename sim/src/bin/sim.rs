//! `sim`: the simulator's command line. Thin glue over `b2b_sim::generate`.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(name = "sim", about = "Two simulated iiwa carts with rendered cameras")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Writes a b2b-dataset/1 folder (with ground_truth.json) for a scene file.
    Generate {
        /// The scene file (JSON).
        #[arg(long)]
        scene: PathBuf,
        /// The random seed; the output is a pure function of scene and seed.
        #[arg(long)]
        seed: u64,
        /// The output folder (created if needed).
        #[arg(long)]
        out: PathBuf,
    },
}

fn main() -> std::process::ExitCode {
    match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // `{:#}` prints the chain "a: b: c"; every library message leaves its
            // source out, so each cause appears once.
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Generate { scene, seed, out } => {
            let summary = b2b_sim::generate::generate(&scene, seed, &out).with_context(|| {
                format!("generating {} from {}", out.display(), scene.display())
            })?;
            println!(
                "wrote {}: captures {:?} (planning attempts {:?}), {} touch pairs",
                out.display(),
                summary.captures,
                summary.attempts,
                summary.touches
            );
        }
    }
    Ok(())
}
