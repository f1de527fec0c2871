//! rerun recordings of the commands: where they go (`--rerun-save`,
//! `--rerun-connect`), what each command logs, and closing them.

use anyhow::Context;
use b2b_calib::metrics::TouchMetrics;
use b2b_pipeline::{RobotObservations, error_chain};
use b2b_protocol::{CalibrationResult, HandEyeResult};

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
    pub fn recorder(&self, app_id: &str) -> anyhow::Result<b2b_viz::Recorder> {
        Ok(match (&self.rerun_save, &self.rerun_connect) {
            (Some(path), _) => b2b_viz::Recorder::save(app_id, path)
                .with_context(|| format!("cannot write the recording {}", path.display()))?,
            (None, Some(addr)) => b2b_viz::Recorder::connect(app_id, addr)
                .with_context(|| format!("cannot stream to the rerun viewer at {addr}"))?,
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

/// Logs an offline hand-eye (`agent handeye`): the estimate with the camera's
/// intrinsics, and each capture's flange, corners and residual on the capture
/// timeline (robot 1's side of the scene). A viewer that went away is a warning.
pub fn log_hand_eye_run(
    rec: &b2b_viz::Recorder,
    obs: &RobotObservations,
    result: &HandEyeResult,
) -> anyhow::Result<()> {
    if !rec.is_enabled() {
        return Ok(());
    }
    let x = result.flange_from_camera.to_isometry("T_flange_camera")?;
    let intr = crate::agent::intrinsics(&obs.camera);
    let base = b2b_viz::Base::One;
    let logged = rec.log_hand_eye(base, &x, &intr).and_then(|()| {
        obs.observations.iter().enumerate().try_for_each(|(i, o)| {
            rec.set_capture_time(i as u64, i as f64);
            rec.log_flange(base, &o.board.base_from_flange)?;
            let corners: Vec<[f64; 2]> = o.board.pixels.iter().map(|p| [p.x, p.y]).collect();
            rec.log_corners(base, &corners, &[])?;
            rec.log_residual(base, o.pnp_rms_px)
        })
    });
    if let Err(e) = logged {
        eprintln!("warning: rerun: {}", error_chain(&e));
    }
    Ok(())
}

/// Logs a verification (`coordinator verify`): the result, and each touch pair
/// with its error against the predicted bound.
pub fn log_verification(
    rec: &b2b_viz::Recorder,
    result: &CalibrationResult,
    touches: &[b2b_dataset::TouchPair],
    metrics: &TouchMetrics,
) -> anyhow::Result<()> {
    if !rec.is_enabled() {
        return Ok(());
    }
    log_result(rec, result, None);
    let b = result.base1_from_base2.to_isometry("T_base1_base2")?;
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
