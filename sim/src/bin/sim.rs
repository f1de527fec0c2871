//! `sim`: the simulator's command line. Thin glue over `b2b_sim::generate`.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(
    name = "sim",
    about = "Simulated iiwa carts (two or more) with rendered cameras"
)]
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
            println!("wrote {}", out.display());
            for ((id, captures), attempts) in summary
                .robots
                .iter()
                .zip(&summary.captures)
                .zip(&summary.attempts)
            {
                println!("  {id}: {captures} captures ({attempts} planning attempts)");
            }
            if let [first, second, ..] = summary.robots.as_slice() {
                println!(
                    "  {first} + {second}: {} touch pairs (touch_points.csv)",
                    summary.touches
                );
            }
            for ((a, b), n) in &summary.pair_touches {
                println!(
                    "  {a} + {b}: {n} touch pairs ({})",
                    b2b_dataset::pair_touch_file_name(a, b)
                );
            }
        }
    }
    Ok(())
}
