//! `agent`: one per cart. This build has the offline hand-eye command; the live
//! sources (`run`, `auto`) arrive with the FRI, camera and zenoh layers.

use std::path::PathBuf;

use anyhow::Context;
use b2b_calib::refine::RefineOptions;
use b2b_pipeline::{HandEyeChoice, hand_eye, load_dataset, observe_robot};
use b2b_services::{init_logging, run_main, write_json};
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(name = "agent", version, about = "Calibration agent of one robot cart")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
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
    },
}

fn main() -> std::process::ExitCode {
    init_logging();
    let cli = Cli::parse();
    run_main(|| match cli.command {
        Command::Handeye {
            dataset,
            robot,
            method,
            refine_intrinsics,
            out,
        } => {
            let choice: HandEyeChoice = method.parse().map_err(anyhow::Error::msg)?;
            let ds = load_dataset(&dataset)?;
            let obs = observe_robot(&ds, &robot)?;
            let options = RefineOptions {
                refine_intrinsics,
                ..Default::default()
            };
            let run = hand_eye(&obs, choice, &options)?;
            write_json(&out, &run.result).context("writing the hand-eye result")?;
            let r = &run.result;
            let t = r.flange_from_camera.t;
            let q = r.flange_from_camera.q;
            let sd: Vec<f64> = (0..6).map(|i| r.covariance[i][i].max(0.0).sqrt()).collect();
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
            println!(
                "1-sigma: rotation [{:.4}, {:.4}, {:.4}] deg, translation [{:.3}, {:.3}, {:.3}] mm",
                sd[0].to_degrees(),
                sd[1].to_degrees(),
                sd[2].to_degrees(),
                sd[3] * 1e3,
                sd[4] * 1e3,
                sd[5] * 1e3
            );
            println!(
                "reprojection RMS {:.3} px; detect {:.0} ms, solve {:.0} ms",
                r.reprojection_rms_px, r.timings_ms.detect, r.timings_ms.solve
            );
            println!("wrote {}", out.display());
            Ok(())
        }
    })
}
