//! `coordinator`: turns both robots' data into `base1_from_base2`, live over zenoh
//! (`run`) or offline from a dataset (`calibrate`), and checks a result against
//! touch points (`verify`).

use std::path::PathBuf;

use anyhow::Context;
use b2b_pipeline::{B2bMethod, base_to_base_run, load_dataset, verify};
use b2b_protocol::CalibrationResult;
use b2b_services::outputs::{print_result, write_result};
use b2b_services::{
    RerunArgs, RobotNoiseArgs, finish_recording, init_logging, log_result, read_json, run_main,
    stop_flag, write_json,
};
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
    /// Listen to the agents over zenoh; once every agent heard from has finished,
    /// compute base1_from_base2, publish it and write RESULT.json (Ctrl-C: compute
    /// with what has arrived).
    Run {
        /// board, multimarker or rgbd (rgbd: the agents publish features with
        /// `agent run --features`, and their board observations give the hand-eyes).
        #[arg(long, default_value = "board", value_parser = ["board", "multimarker", "rgbd"])]
        method: String,
        /// zenoh configuration file (JSON5); default: loopback peer listening on
        /// tcp/127.0.0.1:7447.
        #[arg(long)]
        zenoh: Option<PathBuf>,
        /// Where every received sample is journalled (a restart resumes from it).
        #[arg(long, default_value = "coordinator-state")]
        state_dir: PathBuf,
        /// Robot ids in order (robot 1 first); default: sorted ids.
        #[arg(long, value_delimiter = ',')]
        robots: Option<Vec<String>>,
        /// Where to write RESULT.json (and RESULT.ros.yaml, RESULT.opencv.yml).
        #[arg(long)]
        out: PathBuf,
        /// board, multimarker: also refine each camera's intrinsics (fx, fy, cx, cy,
        /// k1, k2, p1, p2, k3) with the hand-eyes and base-to-base, starting from the
        /// intrinsics each capture carries (the camera's own, e.g. a RealSense's
        /// factory calibration, which can be slightly off).
        #[arg(long)]
        refine_intrinsics: bool,
        #[command(flatten)]
        noise: RobotNoiseArgs,
        #[command(flatten)]
        rerun: RerunArgs,
    },
    /// base1_from_base2 from a two-robot b2b-dataset/1 folder (never reads
    /// ground_truth.json or reference.json).
    Calibrate {
        /// The b2b-dataset/1 folder (dataset.json, robotN/captures.csv, images).
        #[arg(long)]
        dataset: PathBuf,
        /// board, multimarker or rgbd (default: from the dataset's target kind).
        #[arg(long, value_parser = ["board", "multimarker", "rgbd"])]
        method: Option<String>,
        /// rgbd only: each robot's HANDEYE.json (`agent handeye`, from an earlier
        /// calibration; matched by its robot id) instead of a hand-eye from the
        /// dataset's target: the base-to-base step then needs no target at all.
        #[arg(long = "hand-eye")]
        hand_eye: Vec<PathBuf>,
        /// board, multimarker: also refine each camera's intrinsics (fx, fy, cx, cy,
        /// k1, k2, p1, p2, k3) with the hand-eyes and base-to-base. A robot without
        /// intrinsics in dataset.json always gets them estimated from its images
        /// and refined so.
        #[arg(long)]
        refine_intrinsics: bool,
        /// Where to write RESULT.json (and RESULT.ros.yaml, RESULT.opencv.yml).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        noise: RobotNoiseArgs,
        #[command(flatten)]
        rerun: RerunArgs,
    },
    /// Checks a result against pointer-tip touch pairs (touch_points.csv format).
    Verify {
        /// The RESULT.json to check (from run or calibrate).
        #[arg(long)]
        result: PathBuf,
        /// Pointer-tip touch pairs (CSV: each row a point touched by both robots,
        /// in each robot's base; shared/dataset-format.md).
        #[arg(long = "touch-points")]
        touch_points: PathBuf,
        /// Also write the metrics as JSON.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Each pointer tip's noise (1 sigma, mm), added to the predicted bounds.
        #[arg(long, default_value_t = 0.0)]
        tip_sigma_mm: f64,
        #[command(flatten)]
        rerun: RerunArgs,
    },
    /// An HTML report of a result (and its verification): plots of residuals,
    /// error distributions, touch errors against the predicted bound, view
    /// coverage, rejected captures, and the numbers.
    Report {
        /// The RESULT.json to report on.
        #[arg(long)]
        result: PathBuf,
        /// verify --json output.
        #[arg(long)]
        verify: Option<PathBuf>,
        /// HANDEYE.json files (agent handeye) adding per-capture residuals.
        #[arg(long = "hand-eye")]
        hand_eye: Vec<PathBuf>,
        /// Touch points (touch_points.csv) adding per-touch errors.
        #[arg(long = "touch-points")]
        touch_points: Option<PathBuf>,
        /// Each pointer tip's noise (1 sigma, mm), for the per-touch bounds.
        #[arg(long, default_value_t = 0.0)]
        tip_sigma_mm: f64,
        /// Output folder (index.html and the plots).
        #[arg(long)]
        out: PathBuf,
    },
}

/// The RGB-D method with hand-eyes read from HANDEYE.json files, one per robot of
/// the dataset.
fn rgbd_with_hand_eye_files(
    ds: &b2b_dataset::Dataset,
    files: &[PathBuf],
) -> anyhow::Result<CalibrationResult> {
    let ids: Vec<String> = ds.manifest.robots.iter().map(|r| r.id.clone()).collect();
    anyhow::ensure!(
        ids.len() == 2,
        "base-to-base needs two robots, the dataset lists {}",
        ids.len()
    );
    let mut found: Vec<Option<(nalgebra::Isometry3<f64>, nalgebra::Matrix6<f64>)>> =
        vec![None, None];
    for path in files {
        let he: b2b_protocol::HandEyeResult = read_json(path)?;
        anyhow::ensure!(
            he.format == b2b_protocol::HANDEYE_FORMAT,
            "{}: format '{}', expected '{}'",
            path.display(),
            he.format,
            b2b_protocol::HANDEYE_FORMAT
        );
        let k = ids.iter().position(|id| *id == he.robot).with_context(|| {
            format!(
                "{}: robot '{}' is not in the dataset ({})",
                path.display(),
                he.robot,
                ids.join(", ")
            )
        })?;
        anyhow::ensure!(
            found[k].is_none(),
            "{}: a second hand-eye for robot '{}'",
            path.display(),
            he.robot
        );
        let x = he
            .flange_from_camera
            .to_isometry("T_flange_camera")
            .with_context(|| path.display().to_string())?;
        let cov = nalgebra::Matrix6::from_fn(|i, j| he.covariance[i][j]);
        anyhow::ensure!(
            cov.iter().all(|v| v.is_finite()),
            "{}: covariance has a non-finite entry",
            path.display()
        );
        found[k] = Some((x, cov));
    }
    let (Some(a), Some(b)) = (found[0], found[1]) else {
        anyhow::bail!(
            "--hand-eye: need one HANDEYE.json for each of {} and {}",
            ids[0],
            ids[1]
        );
    };
    let run = b2b_pipeline::rgbd::rgbd_base_to_base_with_hand_eyes(
        ds,
        [a.0, b.0],
        Some([a.1, b.1]),
        &b2b_pipeline::rgbd::RgbdOptions::default(),
    )?;
    Ok(run.result)
}

/// `--refine-intrinsics` is for the methods that fit the cameras.
fn check_refine_intrinsics(refine_intrinsics: bool, method: B2bMethod) -> anyhow::Result<()> {
    anyhow::ensure!(
        !(refine_intrinsics && method == B2bMethod::Rgbd),
        "--refine-intrinsics is for --method board or multimarker (the rgbd method uses the given intrinsics)"
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    init_logging();
    let cli = Cli::parse();
    run_main(|| match cli.command {
        Command::Run {
            method,
            zenoh,
            state_dir,
            robots,
            out,
            refine_intrinsics,
            noise,
            rerun,
        } => {
            let recorder = rerun.recorder("b2b-coordinator")?;
            let method: B2bMethod = method.parse().map_err(anyhow::Error::msg)?;
            check_refine_intrinsics(refine_intrinsics, method)?;
            let stop = stop_flag();
            let opts = b2b_services::coordinator::RunOptions {
                zenoh,
                state_dir,
                robots: 2,
                order: robots.clone(),
                refine: b2b_calib::refine::RefineOptions {
                    refine_intrinsics,
                    ..noise.options()?
                },
                method,
                rgbd: b2b_pipeline::rgbd::RgbdOptions::default(),
            };
            let (result, counters) = b2b_services::coordinator::run(&opts, &stop)?;
            write_result(&out, &result).context("writing the result")?;
            log_result(&recorder, &result, robots.as_deref());
            finish_recording(recorder);
            print_result(&result);
            println!(
                "messages: {} accepted, {} duplicates dropped, {} rejected",
                counters.accepted, counters.duplicates, counters.rejected
            );
            println!("wrote {}", out.display());
            Ok(())
        }
        Command::Calibrate {
            dataset,
            method,
            hand_eye,
            refine_intrinsics,
            out,
            noise,
            rerun,
        } => {
            let recorder = rerun.recorder("b2b-coordinator")?;
            let ds = load_dataset(&dataset)?;
            let method = match method {
                Some(m) => m.parse::<B2bMethod>().map_err(anyhow::Error::msg)?,
                None => B2bMethod::default_for(&ds.manifest.target),
            };
            check_refine_intrinsics(refine_intrinsics, method)?;
            let mut cameras = Vec::new();
            let result = if hand_eye.is_empty() {
                let options = b2b_calib::refine::RefineOptions {
                    refine_intrinsics,
                    ..noise.options()?
                };
                let run = base_to_base_run(&ds, method, &options)?;
                cameras = run.cameras;
                run.result
            } else {
                anyhow::ensure!(
                    method == B2bMethod::Rgbd,
                    "--hand-eye is for --method rgbd (the {} method estimates the hand-eyes from its target)",
                    method.name()
                );
                rgbd_with_hand_eye_files(&ds, &hand_eye)?
            };
            write_result(&out, &result).context("writing the result")?;
            let order: Vec<String> = ds.robots.iter().map(|r| r.id.clone()).collect();
            log_result(&recorder, &result, Some(&order));
            finish_recording(recorder);
            print_result(&result);
            for c in cameras
                .iter()
                .filter(|c| c.refined || c.estimated.is_some())
            {
                println!("{}", c.describe());
            }
            println!("wrote {}", out.display());
            Ok(())
        }
        Command::Verify {
            result,
            touch_points,
            json,
            tip_sigma_mm,
            rerun,
        } => {
            let recorder = rerun.recorder("b2b-verify")?;
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
            for l in &report.iso9283 {
                println!(
                    "ISO 9283, location {} ({} touches): AP {:.3} mm, RP {:.3} mm",
                    l.location, l.n, l.accuracy_mm, l.repeatability_mm
                );
            }
            if let Some(path) = json {
                write_json(&path, &report)?;
                println!("wrote {}", path.display());
            }
            if recorder.is_enabled() {
                log_result(&recorder, &r, None);
                let b = r.base1_from_base2.to_isometry("T_base1_base2")?;
                let rows: Vec<b2b_viz::Touch> = touches
                    .iter()
                    .zip(&m.bound95_m)
                    .map(|(t, bound)| b2b_viz::Touch {
                        row: t.row,
                        tip1_in_base1: t.tip1_in_base1,
                        tip2_in_base2: t.tip2_in_base2,
                        bound95_m: *bound,
                    })
                    .collect();
                if let Err(e) = recorder.log_touches(&b, &rows) {
                    eprintln!("warning: rerun: {}", b2b_pipeline::error_chain(&e));
                }
            }
            finish_recording(recorder);
            Ok(())
        }
        Command::Report {
            result,
            verify: verify_file,
            hand_eye,
            touch_points,
            tip_sigma_mm,
            out,
        } => {
            let mut inputs = b2b_report::ReportInputs::from_files(&result, verify_file.as_deref())?;
            for f in &hand_eye {
                inputs.add_hand_eye_file(f)?;
            }
            if let Some(tp) = touch_points {
                anyhow::ensure!(
                    tip_sigma_mm.is_finite() && tip_sigma_mm >= 0.0,
                    "--tip-sigma-mm must be a number >= 0"
                );
                let touches = b2b_dataset::read_touch_points(&tp)?;
                let (_, m) = verify(&inputs.result, &touches, tip_sigma_mm * 1e-3)?;
                inputs.touches = touches
                    .iter()
                    .zip(m.errors_m.iter().zip(&m.bound95_m))
                    .map(|(t, (e, b))| b2b_report::TouchDetail {
                        row: t.row,
                        error_m: *e,
                        bound95_m: *b,
                    })
                    .collect();
            }
            let files = b2b_report::write_report(&inputs, &out)?;
            println!("wrote {}", files.index.display());
            Ok(())
        }
    })
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    #[test]
    fn every_flag_has_help() {
        let missing = b2b_services::undocumented_args(&super::Cli::command());
        assert!(missing.is_empty(), "flags without help: {missing:?}");
    }
}
