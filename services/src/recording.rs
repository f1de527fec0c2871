//! rerun recordings of the commands: where they go (`--rerun-save`,
//! `--rerun-connect`), what each command logs, and closing them.

use b2b_calib::Iso3;
use b2b_calib::metrics::TouchMetrics;
use b2b_dataset::Dataset;
use b2b_pipeline::{RobotObservations, error_chain};
use b2b_protocol::{CalibrationResult, HandEyeResult};

use crate::{Result, ServiceError};

/// Where a command's rerun recording goes: `--rerun-save FILE.rrd` and/or
/// `--rerun-connect ADDR` (a running viewer); neither: no recording.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct RerunArgs {
    /// Write a rerun recording of this run to FILE.rrd.
    #[arg(long, value_name = "FILE.rrd", conflicts_with = "rerun_connect")]
    pub rerun_save: Option<std::path::PathBuf>,
    /// Stream the recording to a running rerun viewer
    /// (e.g. rerun+http://127.0.0.1:9876/proxy).
    #[arg(long, value_name = "ADDR")]
    pub rerun_connect: Option<String>,
}

impl RerunArgs {
    /// The recorder these flags ask for.
    pub fn recorder(&self, app_id: &str) -> Result<b2b_viz::Recorder> {
        Ok(match (&self.rerun_save, &self.rerun_connect) {
            (Some(path), _) => b2b_viz::Recorder::save(app_id, path).map_err(|source| {
                ServiceError::RecordingSave {
                    path: path.clone(),
                    source: Box::new(source),
                }
            })?,
            (None, Some(addr)) => b2b_viz::Recorder::connect(app_id, addr).map_err(|source| {
                ServiceError::RecordingConnect {
                    addr: addr.clone(),
                    source: Box::new(source),
                }
            })?,
            (None, None) => b2b_viz::Recorder::disabled(),
        })
    }
}

/// Closes a recording; a viewer that went away is a warning, not a failed run.
pub fn finish_recording(rec: b2b_viz::Recorder) {
    if !rec.is_enabled() {
        return;
    }
    if let Err(e) = rec.finish() {
        eprintln!(
            "warning: the rerun recording did not finish cleanly: {}",
            error_chain(&e)
        );
    }
}

/// Logs a result (both bases, hand-eyes, uncertainty) to a recording; robot 1 is
/// the first id of `order` (default: sorted ids).
pub fn log_result(rec: &b2b_viz::Recorder, result: &CalibrationResult, order: Option<&[String]>) {
    if !rec.is_enabled() {
        return;
    }
    let ids: Vec<String> = match order {
        Some(o) if o.len() >= 2 => o.to_vec(),
        _ => result.hand_eye.keys().cloned().collect(),
    };
    if ids.len() >= 2
        && let Err(e) = rec.log_result(result, [ids[0].as_str(), ids[1].as_str()], 1.0)
    {
        tracing::warn!("rerun: {}", error_chain(&e));
    }
}

/// Logs one robot's captures of an offline run as the agents log theirs, on the
/// `capture` timeline (the capture's row): the flange, the image read again from
/// the dataset, the detected corners with the model points reprojected by the
/// capture's board pose, the RMS, and each capture rejected before the fit with
/// its image and reason. `flange_from_camera` places the camera (the hand-eye
/// found). A viewer that went away, or an image that cannot be read again, is a
/// warning, not a failed run.
pub fn log_robot_captures(
    rec: &b2b_viz::Recorder,
    ds: &Dataset,
    base: b2b_viz::Base,
    obs: &RobotObservations,
    flange_from_camera: Option<&nalgebra::Isometry3<f64>>,
) {
    if !rec.is_enabled() {
        return;
    }
    let intr = b2b_dataset::intrinsics_of(&obs.camera, 5);
    let robot = obs.robot.as_str();
    let image_of = |row: usize| -> Option<b2b_vision::GrayImage> {
        let capture = ds.robot(robot)?.captures.iter().find(|c| c.row == row)?;
        let path = ds.image_path(robot, capture)?;
        b2b_vision::load_gray(&path)
            .map_err(|e| tracing::warn!("rerun: {}: {}", path.display(), error_chain(&e)))
            .ok()
    };
    let log_image = |img: &b2b_vision::GrayImage| {
        rec.log_image(
            base,
            b2b_viz::ImageView {
                pixels: img.pixels(),
                width: img.width(),
                height: img.height(),
                format: b2b_viz::PixelFormat::Gray,
            },
        )
    };
    let mut logged = flange_from_camera
        .map_or(Ok(()), |x| rec.log_hand_eye(base, x, &intr))
        .and_then(|()| rec.log_pinhole(base, &intr));
    for o in &obs.observations {
        if logged.is_err() {
            break;
        }
        rec.set_capture_time(o.row as u64, o.row as f64);
        let detected: Vec<[f64; 2]> = o.board.pixels.iter().map(|p| [p.x, p.y]).collect();
        let pairs: Vec<([f64; 2], [f64; 2])> = o
            .board
            .target_points
            .iter()
            .zip(&detected)
            .filter_map(|(p, d)| {
                let q = obs.camera.project(&(o.camera_from_target * p))?;
                Some((*d, [q.x, q.y]))
            })
            .collect();
        let (detected, reprojected): (Vec<_>, Vec<_>) = pairs.into_iter().unzip();
        let what = format!(
            "row {} ({})",
            o.row,
            o.image.as_deref().unwrap_or("no image")
        );
        logged = rec
            .log_flange(base, &o.board.base_from_flange)
            .and_then(|()| match image_of(o.row) {
                Some(img) => log_image(&img),
                None => Ok(()),
            })
            .and_then(|()| rec.log_corners(base, &detected, &reprojected))
            .and_then(|()| rec.log_residual(base, o.pnp_rms_px))
            .and_then(|()| {
                rec.log_text(
                    base,
                    &format!(
                        "{what}: {} corners, rms {:.3} px",
                        detected.len(),
                        o.pnp_rms_px
                    ),
                )
            });
    }
    for r in &obs.rejected {
        if logged.is_err() {
            break;
        }
        let row = r.row.unwrap_or(0);
        rec.set_capture_time(row as u64, row as f64);
        let what = format!("row {row} ({})", r.image.as_deref().unwrap_or("no image"));
        logged = match image_of(row) {
            Some(img) => log_image(&img),
            None => Ok(()),
        }
        .and_then(|()| rec.log_rejection(base, &what, &r.reason));
    }
    if let Err(e) = logged {
        eprintln!("warning: rerun: {}", error_chain(&e));
    }
}

/// Logs an offline base-to-base calibration (`coordinator calibrate`): the result
/// and each robot's captures ([`log_robot_captures`]), robot 1 as `base1`.
pub fn log_offline_calibration(
    rec: &b2b_viz::Recorder,
    ds: &Dataset,
    run: &b2b_pipeline::CalibrationRun,
) {
    let order: Vec<String> = ds.robots.iter().map(|r| r.id.clone()).collect();
    log_result(rec, &run.result, Some(&order));
    for (obs, base) in run
        .observations
        .iter()
        .zip([b2b_viz::Base::One, b2b_viz::Base::Two])
    {
        let x = run
            .result
            .hand_eye
            .get(&obs.robot)
            .and_then(|p| p.to_isometry("T_flange_camera").ok());
        log_robot_captures(rec, ds, base, obs, x.as_ref());
    }
}

/// Logs an offline hand-eye (`agent handeye`): the robot's captures
/// ([`log_robot_captures`], as `base1`) with the hand-eye found.
pub fn log_hand_eye_run(
    rec: &b2b_viz::Recorder,
    ds: &Dataset,
    obs: &RobotObservations,
    result: &HandEyeResult,
) -> Result<()> {
    let x = result.flange_from_camera.to_isometry("T_flange_camera")?;
    log_robot_captures(rec, ds, b2b_viz::Base::One, obs, Some(&x));
    Ok(())
}

/// Logs a verification (`coordinator verify`): the result, and each touch pair
/// with its error against the predicted bound.
pub fn log_verification(
    rec: &b2b_viz::Recorder,
    result: &CalibrationResult,
    a_from_b: &Iso3,
    touches: &[b2b_dataset::TouchPair],
    metrics: &TouchMetrics,
) -> Result<()> {
    if !rec.is_enabled() {
        return Ok(());
    }
    log_result(rec, result, None);
    let b = *a_from_b;
    let rows: Vec<b2b_viz::Touch> = touches
        .iter()
        .zip(&metrics.bound95_m)
        .map(|(t, bound)| b2b_viz::Touch {
            row: t.row,
            tip1_in_base1: t.tip1_in_base1,
            tip2_in_base2: t.tip2_in_base2,
            bound95_m: *bound,
        })
        .collect();
    if let Err(e) = rec.log_touches(&b, &rows) {
        eprintln!("warning: rerun: {}", error_chain(&e));
    }
    Ok(())
}

/// Logs a command's verdict (`result/verdict`; [`b2b_viz::Recorder::log_verdict`]);
/// a viewer that went away is a warning, not a failed run.
pub fn log_verdict(rec: &b2b_viz::Recorder, verdict: &b2b_protocol::Verdict, line: &str) {
    if !rec.is_enabled() {
        return;
    }
    if let Err(e) = rec.log_verdict(verdict, line) {
        eprintln!("warning: rerun: {}", error_chain(&e));
    }
}
