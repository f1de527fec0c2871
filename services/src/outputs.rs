//! What the binaries print: results (with their warnings), hand-eyes,
//! verification, plans, the history; and the report's inputs gathered from
//! files and the history. The result's files themselves (RESULT.json and its
//! siblings, written all or nothing) are `b2b_report::formats` and
//! `b2b_report::write`.

use std::path::{Path, PathBuf};

use b2b_protocol::CalibrationResult;

use crate::{Result, ServiceError};

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
    if let Some(m) = &r.model_selection {
        print_model_selection(m);
    }
    print_pose("T_base1_base2", &r.base1_from_base2);
    print_sigma(&r.covariance);
    print_predicted(&r.predicted_touch_error_m);
    // More than two robots: every other base in the reference's, and the pairs
    // without it.
    if let (Some(reference), false) = (&r.reference, r.bases.is_empty()) {
        for (id, b) in &r.bases {
            print_pose(&format!("T_{reference}_{id}"), &b.ref_from_base);
            print_sigma(&b.covariance);
            print_predicted(&b.predicted_touch_error_m);
        }
        for p in &r.pairs {
            print_pose(&format!("T_{}_{}", p.a, p.b), &p.a_from_b);
            print_sigma(&p.covariance);
            print_predicted(&p.predicted_touch_error_m);
        }
    }
    println!(
        "timings: detect {:.0} ms, solve {:.0} ms, total {:.0} ms",
        r.timings_ms.detect, r.timings_ms.solve, r.timings_ms.total
    );
    print_warnings(r);
}

/// Which estimator the held-out captures chose, and each candidate's figure.
fn print_model_selection(m: &b2b_protocol::ModelSelection) {
    let mut figures: Vec<(&String, &f64)> = m.held_out_px.iter().collect();
    figures.sort_by(|a, b| a.1.total_cmp(b.1));
    println!(
        "estimator: {} (held-out captures' corners, {}-fold cross-validation, RMS px: {}){}",
        m.chosen,
        m.folds,
        figures
            .iter()
            .map(|(c, v)| format!("{c} {v:.3}"))
            .collect::<Vec<_>>()
            .join(", "),
        match (m.spread_scale, m.fold_scatter) {
            (Some(s), _) => format!("; covariance scaled by {s:.2} to the folds' scatter"),
            (None, Some(s)) => format!(
                "; the folds' scatter ({s:.2}x the covariance) not applied: \
                 too few captures per fold for it to be evidence"
            ),
            (None, None) => String::new(),
        }
    );
    if !m.agreeing.is_empty() {
        println!(
            "  the held-out captures cannot tell {} from {}: the bases are their mean, their spread is part of the bound",
            m.agreeing.join(", "),
            m.chosen
        );
    }
}

fn print_predicted(p: &b2b_protocol::PredictedError) {
    println!(
        "predicted touch error: mean {:.3} mm, p95 {:.3} mm",
        p.mean * 1e3,
        p.p95 * 1e3
    );
}

/// The result's warnings, last so an operator sees them (also in RESULT.json
/// and the report).
pub fn print_warnings(r: &CalibrationResult) {
    for w in &r.warnings {
        println!("WARNING: {w}");
    }
}

/// A pose as `t = [x, y, z] mm, rotation vector [a, b, c] deg`.
fn pose_mm_deg(pose: &b2b_protocol::Pose) -> String {
    let q = pose.q;
    let rot = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        q[3], q[0], q[1], q[2],
    ));
    let v = rot.scaled_axis();
    format!(
        "t = [{:.3}, {:.3}, {:.3}] mm, rotation vector [{:.4}, {:.4}, {:.4}] deg",
        pose.t[0] * 1e3,
        pose.t[1] * 1e3,
        pose.t[2] * 1e3,
        v.x.to_degrees(),
        v.y.to_degrees(),
        v.z.to_degrees()
    )
}

/// What `coordinator history` prints: the results, then each robot's hand-eyes
/// with how far each is from that robot's first. Written to `out` (stdout,
/// buffered: ten thousand results print at once).
pub fn write_history(
    out: &mut impl std::io::Write,
    listing: &crate::history::Listing,
) -> std::io::Result<()> {
    use crate::history::format_utc;
    let of = listing
        .robot
        .as_ref()
        .map_or(String::new(), |r| format!(" of {r}"));
    if listing.results.is_empty() && listing.hand_eyes.is_empty() {
        writeln!(
            out,
            "no results or hand-eyes{of} recorded in {} (coordinator calibrate and run record there)",
            listing.database
        )?;
        return Ok(());
    }
    writeln!(
        out,
        "{}: {} result{}{of}",
        listing.database,
        listing.results.len(),
        if listing.results.len() == 1 { "" } else { "s" }
    )?;
    for r in &listing.results {
        writeln!(
            out,
            "#{} {}  {} {}  robots {}",
            r.id,
            format_utc(r.recorded_at_unix_ms),
            r.command,
            r.method,
            r.robots.join(", ")
        )?;
        let (t, q) = (r.base1_from_base2.t, r.base1_from_base2.q);
        writeln!(
            out,
            "    T_base1_base2 t = [{:.6}, {:.6}, {:.6}] m, q = [{:.8}, {:.8}, {:.8}, {:.8}]; predicted p95 {:.3} mm",
            t[0],
            t[1],
            t[2],
            q[0],
            q[1],
            q[2],
            q[3],
            r.predicted_touch_error_m.p95 * 1e3
        )?;
        writeln!(out, "    {}", r.result_file)?;
        for w in &r.warnings {
            writeln!(out, "    WARNING: {w}")?;
        }
    }
    for (robot, rows) in &listing.hand_eyes {
        writeln!(out, "hand-eyes of {robot}: {}", rows.len())?;
        let first = rows
            .first()
            .and_then(|h| h.flange_from_camera.to_isometry("T_flange_camera").ok());
        for h in rows {
            let from_first = match (first, h.flange_from_camera.to_isometry("T_flange_camera")) {
                (Some(a), Ok(b)) => {
                    let (dt, dr) = b2b_calib::pose::pose_distance(&b, &a);
                    format!(
                        "; from the first {:.3} mm, {:.3} deg",
                        dt * 1e3,
                        dr.to_degrees()
                    )
                }
                _ => String::new(),
            };
            writeln!(
                out,
                "  {}  #{}  {}{}{from_first}",
                format_utc(h.recorded_at_unix_ms),
                h.result_id,
                pose_mm_deg(&h.flange_from_camera),
                if h.has_covariance {
                    ""
                } else {
                    " (no covariance)"
                },
            )?;
        }
    }
    Ok(())
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
        "robot pose error as the residuals show it: {}",
        run.estimate.noise.describe()
    );
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
    println!("{}", metrics.bound_check.describe());
    for l in &report.iso9283 {
        println!(
            "ISO 9283, location {} ({} touches): AP {:.3} mm, RP {:.3} mm",
            l.location, l.n, l.accuracy_mm, l.repeatability_mm
        );
    }
}

/// What `agent auto --dry-run` prints: the planned viewpoints and what was
/// dropped.
pub fn print_plan(robot: &str, plan: &b2b_routine::plan::Plan) {
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
) -> Result<()> {
    let r = result.ok_or(ServiceError::NoResult {
        waited_s: wait_result_s,
    })?;
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
) -> Result<b2b_report::ReportInputs> {
    let mut inputs = b2b_report::ReportInputs::from_files(result, verify)?;
    for f in hand_eye {
        inputs.add_hand_eye_file(f)?;
    }
    if let Some(tp) = touch_points {
        let touches = b2b_dataset::read_touch_points(tp)?;
        let (_, m) = b2b_pipeline::verify(&inputs.result, &touches, tip_sigma_m).map_err(|e| {
            let file = match e {
                b2b_pipeline::PipelineError::Touches { .. } => tp,
                _ => result,
            };
            ServiceError::from(e).in_file(file)
        })?;
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

/// Adds the hand-eyes the history at `db` holds for the result's robots (none
/// when the file does not exist).
pub fn add_history(
    inputs: &mut b2b_report::ReportInputs,
    db: &Path,
) -> Result<(), crate::history::HistoryError> {
    let Some(history) = crate::history::History::open_existing(db)? else {
        return Ok(());
    };
    let robots: Vec<String> = inputs.result.hand_eye.keys().cloned().collect();
    for robot in &robots {
        for h in history.hand_eyes(Some(robot))? {
            inputs
                .hand_eye_history
                .push(b2b_report::HandEyeHistoryEntry {
                    robot: h.robot,
                    recorded_at_unix_ms: h.recorded_at_unix_ms,
                    recorded_at: crate::history::format_utc(h.recorded_at_unix_ms),
                    flange_from_camera: h.flange_from_camera,
                });
        }
    }
    inputs.history_source = Some(db.display().to_string());
    Ok(())
}
