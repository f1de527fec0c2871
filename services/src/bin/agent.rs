//! `agent`: one per cart. `handeye` works offline on a dataset; `run` publishes a
//! cart's captures over zenoh (sources: `--replay DIR` now; `--sim` and `--fri`
//! arrive with the simulator and the camera process).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use b2b_calib::refine::RefineOptions;
use b2b_pipeline::{HandEyeChoice, hand_eye, load_dataset, observe_robot};
use b2b_services::{RobotNoiseArgs, init_logging, run_main, write_json};
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(name = "agent", version, about = "Calibration agent of one robot cart")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Publish this cart's captures (flange pose, board observation,
    /// base_from_target, hand-eye, status) over zenoh until the coordinator answers.
    Run {
        /// Robot id (as in the dataset; used in key expressions).
        #[arg(long)]
        robot: String,
        /// Replay a b2b-dataset/1 folder's captures for this robot.
        #[arg(long, conflicts_with_all = ["sim", "fri"])]
        replay: Option<PathBuf>,
        /// Simulated cart from a scene file (not available in this build).
        #[arg(long)]
        sim: Option<PathBuf>,
        /// A real controller over KUKA FRI (not available in this build).
        #[arg(long)]
        fri: Option<String>,
        /// zenoh configuration file (JSON5); default: loopback peer connecting to
        /// the coordinator on tcp/127.0.0.1:7447.
        #[arg(long)]
        zenoh: Option<PathBuf>,
        /// Where the agent keeps its sequence number.
        #[arg(long, default_value = "agent-state")]
        state_dir: PathBuf,
        /// Milliseconds between replayed captures.
        #[arg(long, default_value_t = 0)]
        pace_ms: u64,
        /// Seconds to wait for the coordinator's result after the last capture.
        #[arg(long, default_value_t = 600)]
        wait_result_s: u64,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
    },
    /// Hand-eye (T_flange_camera) of one robot from a b2b-dataset/1 folder.
    Handeye {
        /// The dataset folder.
        #[arg(long)]
        dataset: PathBuf,
        /// Robot id as listed in dataset.json.
        #[arg(long)]
        robot: String,
        /// tsai, park, horaud, andreff, daniilidis, shah, li or refined (joint
        /// reprojection-error refinement seeded by Park).
        #[arg(long, default_value = "refined")]
        method: String,
        /// Also refine the camera intrinsics (fx, fy, cx, cy, k1, k2, p1, p2, k3).
        #[arg(long)]
        refine_intrinsics: bool,
        /// Where to write HANDEYE.json.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        noise: RobotNoiseArgs,
    },
}

fn main() -> std::process::ExitCode {
    init_logging();
    let cli = Cli::parse();
    run_main(|| match cli.command {
        Command::Run {
            robot,
            replay,
            sim,
            fri,
            zenoh,
            state_dir,
            pace_ms,
            wait_result_s,
            quiet,
        } => {
            if sim.is_some() || fri.is_some() {
                anyhow::bail!("--sim and --fri are not available in this build; use --replay DIR");
            }
            let Some(dataset) = replay else {
                anyhow::bail!("give a source: --replay DIR");
            };
            let stop = b2b_services::stop_flag();
            let opts = b2b_services::agent::ReplayOptions {
                robot: robot.clone(),
                dataset,
                zenoh,
                state_dir,
                pace: Duration::from_millis(pace_ms),
                wait_result: Duration::from_secs(wait_result_s),
                progress: !quiet,
            };
            match b2b_services::agent::run_replay(&opts, &stop)? {
                Some(r) => {
                    let t = r.base1_from_base2.t;
                    println!(
                        "{robot}: coordinator result T_base1_base2 t = [{:.6}, {:.6}, {:.6}] m",
                        t[0], t[1], t[2]
                    );
                    Ok(())
                }
                None => anyhow::bail!("no result from the coordinator within {wait_result_s} s"),
            }
        }
        Command::Handeye {
            dataset,
            robot,
            method,
            refine_intrinsics,
            out,
            noise,
        } => {
            let choice: HandEyeChoice = method.parse().map_err(anyhow::Error::msg)?;
            let ds = load_dataset(&dataset)?;
            let obs = observe_robot(&ds, &robot)?;
            let options = RefineOptions {
                refine_intrinsics,
                ..noise.options()?
            };
            let run = hand_eye(&obs, choice, &options)?;
            write_json(&out, &run.result).context("writing the hand-eye result")?;
            let r = &run.result;
            let t = r.flange_from_camera.t;
            let q = r.flange_from_camera.q;
            println!("robot {robot}: method {}", r.method);
            println!(
                "captures: {} used, {} rejected",
                obs.observations.len(),
                r.captures.rejected.len()
            );
            for rej in &r.captures.rejected {
                println!(
                    "  rejected {}: {}",
                    rej.image.as_deref().unwrap_or("-"),
                    rej.reason
                );
            }
            println!(
                "T_flange_camera t = [{:.6}, {:.6}, {:.6}] m",
                t[0], t[1], t[2]
            );
            println!(
                "                q = [{:.8}, {:.8}, {:.8}, {:.8}] (x, y, z, w)",
                q[0], q[1], q[2], q[3]
            );
            b2b_services::outputs::print_sigma(&r.covariance);
            println!(
                "reprojection RMS {:.3} px; detect {:.0} ms, solve {:.0} ms",
                r.reprojection_rms_px, r.timings_ms.detect, r.timings_ms.solve
            );
            println!("wrote {}", out.display());
            Ok(())
        }
    })
}
