//! The result in the formats users' tools already read, beside RESULT.json: a
//! ROS-style YAML transform, an OpenCV FileStorage YAML, a ROS 2 launch file
//! publishing the fixed base-to-base link (`tf2_ros static_transform_publisher`)
//! and a URDF with that link as a fixed joint. And what the coordinator prints:
//! results (with their warnings), verification, plans, the history.

use std::path::{Path, PathBuf};

use b2b_protocol::CalibrationResult;

use crate::{Result, ServiceError};

/// The files written beside `RESULT.json`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Siblings {
    /// `RESULT.ros.yaml`: a `geometry_msgs/TransformStamped`-shaped YAML.
    pub ros_yaml: PathBuf,
    /// `RESULT.opencv.yml`: `cv::FileStorage` with the 4x4 and the covariance.
    pub opencv_yml: PathBuf,
    /// `RESULT.launch.py`: a ROS 2 launch file with the static transform.
    pub ros2_launch: PathBuf,
    /// `RESULT.urdf`: the link as a fixed joint between `base1` and `base2`.
    pub urdf: PathBuf,
}

/// `RESULT.json` -> `RESULT.ros.yaml`, `RESULT.opencv.yml`, `RESULT.launch.py`,
/// `RESULT.urdf`.
pub fn sibling_paths(result: &Path) -> Siblings {
    let stem = result
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "result".into());
    let dir = result.parent().unwrap_or(Path::new(""));
    let file = |ext: &str| dir.join(format!("{stem}.{ext}"));
    Siblings {
        ros_yaml: file("ros.yaml"),
        opencv_yml: file("opencv.yml"),
        ros2_launch: file("launch.py"),
        urdf: file("urdf"),
    }
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
pub fn opencv_yaml(r: &CalibrationResult) -> Result<String> {
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

/// A ROS 2 launch file (Python) that publishes `base1_from_base2` as a static
/// transform from `base1` to `base2` (`tf2_ros static_transform_publisher`,
/// the named-argument form of ROS 2 Humble and later; quaternion x, y, z, w).
pub fn ros2_launch(r: &CalibrationResult) -> String {
    let t = r.base1_from_base2.t;
    let q = r.base1_from_base2.q;
    format!(
        "# base1_from_base2 (method {}): maps base2 coordinates into base1 (metres,\n\
         # quaternion x y z w). Run with `ros2 launch RESULT.launch.py`, or include it.\n\
         from launch import LaunchDescription\n\
         from launch_ros.actions import Node\n\
         \n\
         \n\
         def generate_launch_description():\n\
         \x20   return LaunchDescription([\n\
         \x20       Node(\n\
         \x20           package=\"tf2_ros\",\n\
         \x20           executable=\"static_transform_publisher\",\n\
         \x20           name=\"base1_to_base2\",\n\
         \x20           arguments=[\n\
         \x20               \"--x\", \"{:?}\", \"--y\", \"{:?}\", \"--z\", \"{:?}\",\n\
         \x20               \"--qx\", \"{:?}\", \"--qy\", \"{:?}\", \"--qz\", \"{:?}\", \"--qw\", \"{:?}\",\n\
         \x20               \"--frame-id\", \"base1\", \"--child-frame-id\", \"base2\",\n\
         \x20           ],\n\
         \x20       ),\n\
         \x20   ])\n",
        r.method, t[0], t[1], t[2], q[0], q[1], q[2], q[3]
    )
}

/// A URDF holding `base1_from_base2` as the fixed joint `base1_to_base2` from link
/// `base1` to link `base2` (copy the joint into the cell's URDF). `rpy` is URDF's:
/// roll about x, pitch about y, yaw about z, fixed axes (`R = Rz Ry Rx`).
pub fn urdf(r: &CalibrationResult) -> Result<String> {
    let iso = r.base1_from_base2.to_isometry("T_base1_base2")?;
    let t = iso.translation.vector;
    let (roll, pitch, yaw) = iso.rotation.euler_angles();
    Ok(format!(
        "<?xml version=\"1.0\"?>\n\
         <!-- base1_from_base2 (method {}): base2's pose in base1 (metres, radians) -->\n\
         <robot name=\"b2b_base_to_base\">\n\
         \x20 <link name=\"base1\"/>\n\
         \x20 <link name=\"base2\"/>\n\
         \x20 <joint name=\"base1_to_base2\" type=\"fixed\">\n\
         \x20   <parent link=\"base1\"/>\n\
         \x20   <child link=\"base2\"/>\n\
         \x20   <origin xyz=\"{:?} {:?} {:?}\" rpy=\"{:?} {:?} {:?}\"/>\n\
         \x20 </joint>\n\
         </robot>\n",
        r.method, t.x, t.y, t.z, roll, pitch, yaw
    ))
}

/// Writes RESULT.json and its siblings ([`Siblings`]) together
/// ([`write_together`]): all are replaced, or none.
pub fn write_result(path: &Path, r: &CalibrationResult) -> Result<()> {
    let files = sibling_paths(path);
    let json = serde_json::to_string_pretty(r)? + "\n";
    write_together(&[
        (path.to_owned(), json.into_bytes()),
        (files.ros_yaml, ros_yaml(r).into_bytes()),
        (files.opencv_yml, opencv_yaml(r)?.into_bytes()),
        (files.ros2_launch, ros2_launch(r).into_bytes()),
        (files.urdf, urdf(r)?.into_bytes()),
    ])
}

/// The temporary files of one [`write_together`] and the backups of the files
/// it replaces; whatever is still listed when it is dropped is removed.
#[derive(Debug, Default)]
struct Leftovers(Vec<PathBuf>);

impl Leftovers {
    fn keep(&mut self, path: &Path) {
        self.0.retain(|p| p != path);
    }
}

impl Drop for Leftovers {
    fn drop(&mut self) {
        for p in &self.0 {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// `.NAME.SUFFIX-PID` beside `path` (hidden, in the same folder so that a rename
/// replaces `path` in one step).
fn beside(path: &Path, suffix: &str) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.{suffix}-{}", std::process::id()))
}

/// Writes the files of one result so that a reader never sees a mix of old and
/// new files, nor half a file: each file's bytes go to a temporary file in its
/// destination's folder (created when missing), flushed to disk; only when all
/// are written are they renamed over their destinations. A destination that is
/// a directory (or a pipe, a device) is refused before anything is written; a
/// failed write (a full disk) removes the temporary files and leaves every
/// previous file as it was; a rename failing half-way puts back the files
/// already replaced (kept as hard links until the end).
pub fn write_together(files: &[(PathBuf, Vec<u8>)]) -> Result<()> {
    use std::io::Write;
    let paths: Vec<&Path> = files.iter().map(|(p, _)| p.as_path()).collect();
    check_destinations(&paths).map_err(|e| ServiceError::NothingWritten {
        files: files.iter().map(|(p, _)| p.clone()).collect(),
        source: Box::new(e),
    })?;
    let mut leftovers = Leftovers::default();
    let mut temps = Vec::with_capacity(files.len());
    for (path, bytes) in files {
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(ServiceError::io("create", parent))?;
        }
        let tmp = beside(path, "tmp");
        let _ = std::fs::remove_file(&tmp);
        leftovers.0.push(tmp.clone());
        let written = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
            .and_then(|mut f| {
                f.write_all(bytes)?;
                f.sync_all()
            });
        written.map_err(|source| ServiceError::WriteThrough {
            path: path.clone(),
            temporary: tmp.clone(),
            source,
        })?;
        temps.push(tmp);
    }
    // Keep each previous file under a second name until every rename is done.
    let mut backups: Vec<Option<PathBuf>> = Vec::with_capacity(files.len());
    for (path, _) in files {
        let backup = if path.is_file() {
            let b = beside(path, "previous");
            let _ = std::fs::remove_file(&b);
            leftovers.0.push(b.clone());
            std::fs::hard_link(path, &b)
                .or_else(|_| std::fs::copy(path, &b).map(|_| ()))
                .map_err(|source| ServiceError::KeepPrevious {
                    path: path.clone(),
                    source,
                })?;
            Some(b)
        } else {
            None
        };
        backups.push(backup);
    }
    for (k, ((path, _), tmp)) in files.iter().zip(&temps).enumerate() {
        if let Err(e) = std::fs::rename(tmp, path) {
            // Put back what was replaced.
            for ((done, _), backup) in files.iter().zip(&backups).take(k) {
                match backup {
                    Some(b) => {
                        if std::fs::rename(b, done).is_ok() {
                            leftovers.keep(b);
                        }
                    }
                    None => {
                        let _ = std::fs::remove_file(done);
                    }
                }
            }
            return Err(ServiceError::Replace {
                path: path.clone(),
                source: e,
            });
        }
        leftovers.keep(tmp);
    }
    Ok(())
}

/// Refuses destinations that could not be replaced by a file: a directory, a
/// named pipe, a device. Called by [`write_together`], and by the commands
/// before any work so that a long run does not end in a refusal.
pub fn check_destinations(paths: &[&Path]) -> Result<()> {
    for path in paths {
        if let Ok(meta) = std::fs::metadata(path)
            && let Some(kind) = b2b_dataset::not_a_regular_file(&meta)
        {
            return Err(ServiceError::NotReplaceable {
                path: path.to_path_buf(),
                kind,
            });
        }
    }
    Ok(())
}

/// RESULT.json and its siblings ([`Siblings`]), for [`check_destinations`].
pub fn result_paths(result: &Path) -> Vec<PathBuf> {
    let s = sibling_paths(result);
    vec![
        result.to_owned(),
        s.ros_yaml,
        s.opencv_yml,
        s.ros2_launch,
        s.urdf,
    ]
}

/// `path` made absolute with every symlink resolved, component by component:
/// each existing prefix is canonicalised, so a later `..` steps out of the
/// real folder, and the part that does not exist (no symlinks there) is
/// applied as written.
fn resolved(path: &Path) -> PathBuf {
    use std::path::Component;
    let abs = std::path::absolute(path).unwrap_or_else(|_| path.to_owned());
    let mut real = PathBuf::new();
    for part in abs.components() {
        match part {
            Component::Prefix(_) | Component::RootDir => real.push(part),
            Component::CurDir => {}
            Component::ParentDir => {
                real.pop();
            }
            Component::Normal(name) => {
                real.push(name);
                if let Ok(c) = real.canonicalize() {
                    real = c;
                }
            }
        }
    }
    real
}

/// Refuses an output `path` (given with `flag`) that is inside the input
/// dataset folder `dataset` or is one of the `inputs` files, after resolving
/// symlinks and `..`: a result is never written over what it was computed from.
/// Called before any work.
pub fn refuse_output_over_input(
    flag: &str,
    path: &Path,
    dataset: Option<&Path>,
    inputs: &[&Path],
) -> Result<()> {
    let out = resolved(path);
    if let Some(dir) = dataset {
        let real = resolved(dir);
        if out.starts_with(&real) {
            return Err(ServiceError::OutputInsideDataset {
                flag: flag.to_owned(),
                path: path.to_owned(),
                dataset: dir.to_owned(),
                resolved: out,
            });
        }
    }
    for input in inputs {
        if out == resolved(input) {
            return Err(ServiceError::OutputIsInput {
                flag: flag.to_owned(),
                path: path.to_owned(),
                input: input.to_path_buf(),
            });
        }
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sibling_names() {
        let s = sibling_paths(Path::new("out/RESULT.json"));
        assert_eq!(s.ros_yaml, Path::new("out/RESULT.ros.yaml"));
        assert_eq!(s.opencv_yml, Path::new("out/RESULT.opencv.yml"));
        assert_eq!(s.ros2_launch, Path::new("out/RESULT.launch.py"));
        assert_eq!(s.urdf, Path::new("out/RESULT.urdf"));
    }

    /// The files of `dir`, by name, with their bytes (hidden ones included).
    fn listing(dir: &Path) -> Vec<(String, Vec<u8>)> {
        let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                let bytes = if e.path().is_file() {
                    std::fs::read(e.path()).unwrap()
                } else {
                    vec![]
                };
                (e.file_name().to_string_lossy().into_owned(), bytes)
            })
            .collect();
        out.sort();
        out
    }

    /// A write that fails half-way (the third file's folder cannot be made: a
    /// file is in the way) replaces nothing and leaves no temporary file.
    #[test]
    fn a_failed_write_replaces_nothing_and_leaves_no_temporary_file() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::write(dir.join("a.json"), "old a").unwrap();
        std::fs::write(dir.join("b.yaml"), "old b").unwrap();
        std::fs::write(dir.join("blocker"), "a file, not a folder").unwrap();
        let before = listing(dir);
        let e = write_together(&[
            (dir.join("a.json"), b"new a".to_vec()),
            (dir.join("b.yaml"), b"new b".to_vec()),
            (dir.join("blocker/c.urdf"), b"new c".to_vec()),
        ])
        .unwrap_err();
        let text = b2b_pipeline::error_chain(&e);
        assert!(text.contains("blocker"), "{text}");
        assert_eq!(listing(dir), before);
    }

    /// A directory in the way of one file: refused before anything is written,
    /// naming it; the others are byte-identical.
    #[test]
    fn a_directory_in_the_way_replaces_nothing() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::write(dir.join("a.json"), "old a").unwrap();
        std::fs::create_dir(dir.join("c.urdf")).unwrap();
        let before = listing(dir);
        let e = write_together(&[
            (dir.join("a.json"), b"new a".to_vec()),
            (dir.join("c.urdf"), b"new c".to_vec()),
        ])
        .unwrap_err();
        let text = b2b_pipeline::error_chain(&e);
        assert!(
            text.contains("c.urdf is a directory") && text.contains("nothing was written"),
            "{text}"
        );
        assert_eq!(listing(dir), before);
    }

    /// The normal case: every file replaced, new ones created with their
    /// folder, no temporary or backup file left.
    #[test]
    fn a_write_replaces_every_file_and_leaves_nothing_else() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::write(dir.join("a.json"), "old a").unwrap();
        write_together(&[
            (dir.join("a.json"), b"new a".to_vec()),
            (dir.join("sub/b.yaml"), b"new b".to_vec()),
        ])
        .unwrap();
        assert_eq!(
            listing(dir),
            vec![("a.json".into(), b"new a".to_vec()), ("sub".into(), vec![])]
        );
        assert_eq!(std::fs::read(dir.join("sub/b.yaml")).unwrap(), b"new b");
    }

    /// An output inside the dataset folder is refused, whether named directly,
    /// through `..` or through a symlink to the folder; beside it is fine.
    #[test]
    fn an_output_inside_the_dataset_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = tmp.path().join("ds");
        std::fs::create_dir_all(ds.join("robot1")).unwrap();
        std::fs::write(ds.join("dataset.json"), "{}").unwrap();
        let link = tmp.path().join("link");
        std::os::unix::fs::symlink(&ds, &link).unwrap();
        for out in [
            ds.join("dataset.json"),
            ds.join("robot1/captures.csv"),
            ds.join("new/RESULT.json"),
            tmp.path().join("x/../ds/RESULT.json"),
            link.join("RESULT.json"),
        ] {
            let e = refuse_output_over_input("--out", &out, Some(&ds), &[]).unwrap_err();
            assert!(e.to_string().contains("inside the dataset folder"), "{e}");
        }
        refuse_output_over_input("--out", &tmp.path().join("RESULT.json"), Some(&ds), &[]).unwrap();
        refuse_output_over_input("--out", &tmp.path().join("ds2/R.json"), Some(&ds), &[]).unwrap();
        let input = tmp.path().join("RESULT.json");
        std::fs::write(&input, "{}").unwrap();
        let e = refuse_output_over_input("--json", &link.join("../RESULT.json"), None, &[&input])
            .unwrap_err();
        assert!(e.to_string().contains("is the input"), "{e}");
    }

    /// A result with a rotation far from the identity in every axis.
    fn result() -> CalibrationResult {
        let text = include_str!("../../report/tests/fixtures/RESULT.json");
        let mut r: CalibrationResult = serde_json::from_str(text).unwrap();
        let q = nalgebra::UnitQuaternion::from_euler_angles(0.3, -1.1, 2.9);
        let q = q.coords;
        r.base1_from_base2.t = [1.04, -0.035, 0.012];
        r.base1_from_base2.q = [q.x, q.y, q.z, q.w];
        r
    }

    /// The numbers after `key` in `text`, parsed.
    fn numbers_after(text: &str, key: &str, n: usize) -> Vec<f64> {
        let rest = &text[text.find(key).unwrap_or_else(|| panic!("{key} in {text}")) + key.len()..];
        rest.split(|c: char| !(c.is_ascii_digit() || "+-.e".contains(c)))
            .filter(|w| !w.is_empty())
            .take(n)
            .map(|w| w.parse().unwrap())
            .collect()
    }

    #[test]
    fn the_urdf_joint_is_the_result_by_urdfs_own_rpy_convention() {
        let r = result();
        let text = urdf(&r).unwrap();
        assert!(text.contains(r#"<joint name="base1_to_base2" type="fixed">"#));
        assert!(
            text.contains(r#"<parent link="base1"/>"#) && text.contains(r#"<child link="base2"/>"#)
        );
        let xyz = numbers_after(&text, "xyz=\"", 3);
        let rpy = numbers_after(&text, "rpy=\"", 3);
        // URDF: fixed axes, roll about x, then pitch about y, then yaw about z.
        let axis = |v: nalgebra::Vector3<f64>, a: f64| {
            nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(v), a)
        };
        let rotation = axis(nalgebra::Vector3::z(), rpy[2])
            * axis(nalgebra::Vector3::y(), rpy[1])
            * axis(nalgebra::Vector3::x(), rpy[0]);
        let truth = r.base1_from_base2.to_isometry("T").unwrap();
        let back = nalgebra::UnitQuaternion::from_rotation_matrix(&rotation);
        assert!(back.angle_to(&truth.rotation) < 1e-12, "{rpy:?}");
        assert_eq!(xyz, r.base1_from_base2.t.to_vec());
    }

    #[test]
    fn the_ros2_launch_file_publishes_the_result_from_base1_to_base2() {
        let r = result();
        let text = ros2_launch(&r);
        assert!(text.contains("def generate_launch_description():"));
        assert!(text.contains("executable=\"static_transform_publisher\""));
        assert!(text.contains("\"--frame-id\", \"base1\", \"--child-frame-id\", \"base2\""));
        for (key, value) in [
            ("--x", r.base1_from_base2.t[0]),
            ("--y", r.base1_from_base2.t[1]),
            ("--z", r.base1_from_base2.t[2]),
            ("--qx", r.base1_from_base2.q[0]),
            ("--qy", r.base1_from_base2.q[1]),
            ("--qz", r.base1_from_base2.q[2]),
            ("--qw", r.base1_from_base2.q[3]),
        ] {
            let got = numbers_after(&text, &format!("\"{key}\", \""), 1)[0];
            assert_eq!(got, value, "{key}");
        }
        // Four-space indentation, as Python requires it to be consistent.
        assert!(text.contains("\n    return LaunchDescription([\n        Node(\n"));
    }
}
