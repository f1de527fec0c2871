//! `coordinator`: turns both robots' data into `base1_from_base2`. This build has
//! the offline commands (`calibrate`, `verify`); the live `run` arrives with the
//! zenoh layer.

use std::path::PathBuf;

use anyhow::Context;
use b2b_calib::refine::RefineOptions;
use b2b_pipeline::{B2bMethod, base_to_base, load_dataset, verify};
use b2b_protocol::CalibrationResult;
use b2b_services::{init_logging, read_json, run_main, write_json};
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "coordinator",
    version,
    about = "Base-to-base calibration coordinator"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// base1_from_base2 from a two-robot b2b-dataset/1 folder (never reads
    /// ground_truth.json or reference.json).
    Calibrate {
        #[arg(long)]
        dataset: PathBuf,
        /// board, multimarker or rgbd (default: from the dataset's target kind).
        #[arg(long)]
        method: Option<String>,
        /// Where to write RESULT.json.
        #[arg(long)]
        out: PathBuf,
    },
    /// Checks a result against pointer-tip touch pairs (touch_points.csv format).
    Verify {
        #[arg(long)]
        result: PathBuf,
        #[arg(long = "touch-points")]
        touch_points: PathBuf,
        /// Also write the metrics as JSON.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Each pointer tip's noise (1 sigma, mm), added to the predicted bounds.
        #[arg(long, default_value_t = 0.0)]
        tip_sigma_mm: f64,
    },
}

fn print_result(r: &CalibrationResult) {
    let t = r.base1_from_base2.t;
    let q = r.base1_from_base2.q;
    println!("method {}", r.method);
    for (robot, n) in &r.captures.used {
        println!("  {robot}: {n} captures used");
    }
    for rej in &r.captures.rejected {
        println!(
            "  rejected {} {}: {}",
            rej.robot,
            rej.image.as_deref().unwrap_or("-"),
            rej.reason
        );
    }
    println!(
        "T_base1_base2 t = [{:.6}, {:.6}, {:.6}] m",
        t[0], t[1], t[2]
    );
    println!(
        "              q = [{:.8}, {:.8}, {:.8}, {:.8}] (x, y, z, w)",
        q[0], q[1], q[2], q[3]
    );
    let sd: Vec<f64> = (0..6).map(|i| r.covariance[i][i].max(0.0).sqrt()).collect();
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
        "predicted touch error: mean {:.3} mm, p95 {:.3} mm",
        r.predicted_touch_error_m.mean * 1e3,
        r.predicted_touch_error_m.p95 * 1e3
    );
    println!(
        "timings: detect {:.0} ms, solve {:.0} ms, total {:.0} ms",
        r.timings_ms.detect, r.timings_ms.solve, r.timings_ms.total
    );
}

fn main() -> std::process::ExitCode {
    init_logging();
    let cli = Cli::parse();
    run_main(|| match cli.command {
        Command::Calibrate {
            dataset,
            method,
            out,
        } => {
            let ds = load_dataset(&dataset)?;
            let method = match method {
                Some(m) => m.parse::<B2bMethod>().map_err(anyhow::Error::msg)?,
                None => B2bMethod::default_for(&ds.manifest.target),
            };
            let result = base_to_base(&ds, method, &RefineOptions::default())?;
            write_json(&out, &result).context("writing the result")?;
            print_result(&result);
            println!("wrote {}", out.display());
            Ok(())
        }
        Command::Verify {
            result,
            touch_points,
            json,
            tip_sigma_mm,
        } => {
            anyhow::ensure!(
                tip_sigma_mm.is_finite() && tip_sigma_mm >= 0.0,
                "--tip-sigma-mm must be a number >= 0"
            );
            let r: CalibrationResult = read_json(&result)?;
            r.validate()
                .with_context(|| format!("{}", result.display()))?;
            let touches = b2b_dataset::read_touch_points(&touch_points)?;
            let (report, m) = verify(&r, &touches, tip_sigma_mm * 1e-3)?;
            println!("touch  error (mm)  bound95 (mm)");
            for (i, (e, b)) in m.errors_m.iter().zip(&m.bound95_m).enumerate() {
                println!(
                    "{:>5}  {:>10.3}  {:>12.3}{}",
                    i + 1,
                    e * 1e3,
                    b * 1e3,
                    if e > b { "  outside" } else { "" }
                );
            }
            println!("n = {}", report.n);
            println!(
                "touch error: mean {:.3} mm, rms {:.3} mm, max {:.3} mm",
                report.touch_mean_mm, report.touch_rms_mm, report.touch_max_mm
            );
            println!(
                "against the Procrustes fit of the touches: {:.3} mm, {:.4} deg",
                report.procrustes_linear_error_mm, report.procrustes_angular_error_deg
            );
            println!(
                "within predicted 95% bound: {:.0}%",
                report.within_predicted_p95 * 100.0
            );
            if let Some(path) = json {
                write_json(&path, &report)?;
                println!("wrote {}", path.display());
            }
            Ok(())
        }
    })
}
