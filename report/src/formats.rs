//! The result in the formats users' tools already read, beside RESULT.json: a
//! ROS-style YAML transform, an OpenCV FileStorage YAML, a ROS 2 launch file
//! publishing the fixed base-to-base link (`tf2_ros static_transform_publisher`)
//! and a URDF with that link as a fixed joint. Text only: [`crate::write`] puts
//! them on disk together.

use std::path::{Path, PathBuf};

use b2b_protocol::CalibrationResult;

use crate::ReportError;

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
pub fn opencv_yaml(r: &CalibrationResult) -> Result<String, ReportError> {
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
pub fn urdf(r: &CalibrationResult) -> Result<String, ReportError> {
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

/// RESULT.json and its siblings ([`Siblings`]), for
/// [`check_destinations`](crate::write::check_destinations).
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

    /// A result with a rotation far from the identity in every axis.
    fn result() -> CalibrationResult {
        let text = include_str!("../tests/fixtures/RESULT.json");
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
