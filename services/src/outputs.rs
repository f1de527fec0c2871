//! The result in the formats users' tools already read, beside RESULT.json:
//! a ROS-style YAML transform and an OpenCV FileStorage YAML.

use std::path::{Path, PathBuf};

use anyhow::Context;
use b2b_protocol::CalibrationResult;

/// `RESULT.json` -> `RESULT.ros.yaml` and `RESULT.opencv.yml`.
pub fn sibling_paths(result: &Path) -> (PathBuf, PathBuf) {
    let stem = result
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "result".into());
    let dir = result.parent().unwrap_or(Path::new(""));
    (
        dir.join(format!("{stem}.ros.yaml")),
        dir.join(format!("{stem}.opencv.yml")),
    )
}

/// A `geometry_msgs/TransformStamped`-shaped YAML (parent `base1`, child `base2`).
pub fn ros_yaml(r: &CalibrationResult) -> String {
    let t = r.base1_from_base2.t;
    let q = r.base1_from_base2.q;
    format!(
        "# base1_from_base2: maps base2 coordinates into base1 (metres, quaternion x y z w)\n\
         header:\n  frame_id: base1\nchild_frame_id: base2\ntransform:\n  translation:\n    x: {:?}\n    y: {:?}\n    z: {:?}\n  rotation:\n    x: {:?}\n    y: {:?}\n    z: {:?}\n    w: {:?}\n",
        t[0], t[1], t[2], q[0], q[1], q[2], q[3]
    )
}

fn opencv_matrix(name: &str, rows: usize, cols: usize, data: &[f64]) -> String {
    let values: Vec<String> = data.iter().map(|v| format!("{v:?}")).collect();
    format!(
        "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]\n",
        values.join(", ")
    )
}

/// An OpenCV FileStorage YAML with the 4x4 `T_base1_base2` and the 6x6 covariance
/// (`cv::FileStorage(path, READ)["T_base1_base2"]`).
pub fn opencv_yaml(r: &CalibrationResult) -> anyhow::Result<String> {
    let iso = r.base1_from_base2.to_isometry("T_base1_base2")?;
    let m = iso.to_homogeneous();
    let rows: Vec<f64> = (0..4)
        .flat_map(|i| (0..4).map(move |j| m[(i, j)]))
        .collect();
    let cov: Vec<f64> = r.covariance.iter().flatten().copied().collect();
    Ok(format!(
        "%YAML:1.0\n---\n{}{}method: {}\n",
        opencv_matrix("T_base1_base2", 4, 4, &rows),
        opencv_matrix("covariance", 6, 6, &cov),
        r.method
    ))
}

/// Writes RESULT.json and its two siblings.
pub fn write_result(path: &Path, r: &CalibrationResult) -> anyhow::Result<()> {
    crate::write_json(path, r)?;
    let (ros, cv) = sibling_paths(path);
    std::fs::write(&ros, ros_yaml(r)).with_context(|| format!("cannot write {}", ros.display()))?;
    std::fs::write(&cv, opencv_yaml(r)?)
        .with_context(|| format!("cannot write {}", cv.display()))?;
    Ok(())
}

/// Prints the 1-sigma of a pose covariance `[rx, ry, rz, tx, ty, tz]`.
pub fn print_sigma(covariance: &b2b_protocol::Covariance6) {
    let sd: Vec<f64> = (0..6).map(|i| covariance[i][i].max(0.0).sqrt()).collect();
    println!(
        "1-sigma: rotation [{:.4}, {:.4}, {:.4}] deg, translation [{:.3}, {:.3}, {:.3}] mm",
        sd[0].to_degrees(),
        sd[1].to_degrees(),
        sd[2].to_degrees(),
        sd[3] * 1e3,
        sd[4] * 1e3,
        sd[5] * 1e3
    );
}

/// A transform as two lines: `NAME t = [...] m`, then its quaternion (x, y, z, w)
/// aligned under it.
fn print_pose(name: &str, pose: &b2b_protocol::Pose) {
    let (t, q) = (pose.t, pose.q);
    println!("{name} t = [{:.6}, {:.6}, {:.6}] m", t[0], t[1], t[2]);
    println!(
        "{:w$}q = [{:.8}, {:.8}, {:.8}, {:.8}] (x, y, z, w)",
        "",
        q[0],
        q[1],
        q[2],
        q[3],
        w = name.len() + 1
    );
}

/// The summary both `coordinator calibrate` and `coordinator run` print.
pub fn print_result(r: &CalibrationResult) {
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
    print_pose("T_base1_base2", &r.base1_from_base2);
    print_sigma(&r.covariance);
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

/// What `agent handeye` prints: the estimate, its captures, sigma, residual and
/// timings, and the camera when its intrinsics were estimated or refined.
pub fn print_hand_eye(run: &b2b_pipeline::HandEyeRun, obs: &b2b_pipeline::RobotObservations) {
    let r = &run.result;
    println!("robot {}: method {}", r.robot, r.method);
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
    print_pose("T_flange_camera", &r.flange_from_camera);
    print_sigma(&r.covariance);
    println!(
        "reprojection RMS {:.3} px; detect {:.0} ms, solve {:.0} ms",
        r.reprojection_rms_px, r.timings_ms.detect, r.timings_ms.solve
    );
}

/// What `coordinator verify` prints: each touch's error against its bound, then
/// the summary and ISO 9283 figures.
pub fn print_verification(
    report: &b2b_protocol::VerifyReport,
    metrics: &b2b_calib::metrics::TouchMetrics,
) {
    println!("touch  error (mm)  bound95 (mm)");
    for (i, (e, b)) in metrics.errors_m.iter().zip(&metrics.bound95_m).enumerate() {
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
}

/// What `agent auto --dry-run` prints: the planned viewpoints and what was
/// dropped.
pub fn print_plan(robot: &str, plan: &crate::plan::Plan) {
    println!(
        "{robot}: {} viewpoints planned from {} candidates; joint travel {:.2} rad",
        plan.viewpoints.len(),
        plan.candidates,
        plan.travel_rad
    );
    for (reason, n) in &plan.dropped {
        println!("  dropped {n}: {reason}");
    }
    for (i, v) in plan.viewpoints.iter().enumerate() {
        let t = v.base_from_flange.translation.vector;
        let q: Vec<String> = v.q.iter().map(|x| format!("{x:.3}")).collect();
        println!(
            "  {:2}: q = [{}] rad; flange at [{:.3}, {:.3}, {:.3}] m; distance {:.2} m, tilt {:.0} deg, roll {:.0} deg",
            i + 1,
            q.join(", "),
            t.x,
            t.y,
            t.z,
            v.distance_m,
            v.tilt_rad.to_degrees(),
            v.roll_rad.to_degrees()
        );
    }
}

/// What an agent prints when the coordinator's result arrives, or the error
/// when it does not within `wait_result_s`.
pub fn print_agent_result(
    robot: &str,
    result: Option<CalibrationResult>,
    wait_result_s: u64,
) -> anyhow::Result<()> {
    let r = result
        .with_context(|| format!("no result from the coordinator within {wait_result_s} s"))?;
    let t = r.base1_from_base2.t;
    println!(
        "{robot}: coordinator result T_base1_base2 t = [{:.6}, {:.6}, {:.6}] m",
        t[0], t[1], t[2]
    );
    Ok(())
}

/// What `coordinator report` reports on: the result, its verification, the
/// hand-eyes' per-capture residuals and each touch's error against its bound.
pub fn report_inputs(
    result: &Path,
    verify: Option<&Path>,
    hand_eye: &[PathBuf],
    touch_points: Option<&Path>,
    tip_sigma_m: f64,
) -> anyhow::Result<b2b_report::ReportInputs> {
    let mut inputs = b2b_report::ReportInputs::from_files(result, verify)?;
    for f in hand_eye {
        inputs.add_hand_eye_file(f)?;
    }
    if let Some(tp) = touch_points {
        let touches = b2b_dataset::read_touch_points(tp)?;
        let (_, m) = b2b_pipeline::verify(&inputs.result, &touches, tip_sigma_m)?;
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
    Ok(inputs)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sibling_names() {
        let (a, b) = sibling_paths(Path::new("out/RESULT.json"));
        assert_eq!(a, Path::new("out/RESULT.ros.yaml"));
        assert_eq!(b, Path::new("out/RESULT.opencv.yml"));
    }
}
