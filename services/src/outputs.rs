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

/// The summary both `coordinator calibrate` and `coordinator run` print.
pub fn print_result(r: &CalibrationResult) {
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
