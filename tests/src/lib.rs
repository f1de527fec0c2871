//! Shared helpers for the cross-crate tests and benchmarks.
//!
//! OpenCV appears here only as a reference to check the math core against.
//! `b2b-calib` itself never depends on it.

/// Conversions between this project's poses and OpenCV matrices, plus thin
/// wrappers that call OpenCV's hand-eye solvers with this project's frame names.
///
/// OpenCV names the same transforms differently. This table maps them (see
/// `shared/facts.md` §5):
///
/// | OpenCV | here |
/// |---|---|
/// | `gripper2base` | `base_from_flange` (forward kinematics) |
/// | `target2cam`, `world2cam` | `camera_from_target` (PnP) |
/// | `cam2gripper` (output) | `flange_from_camera` |
/// | `base2gripper` (input of `calibrateRobotWorldHandEye`) | `flange_from_base = base_from_flange⁻¹` |
/// | `base2world` (output) | `target_from_base` |
/// | `gripper2cam` (output) | `camera_from_flange` |
pub mod cv {
    use b2b_calib::Iso3;
    use b2b_calib::handeye::{HandEyeMethod, RobotWorld, RobotWorldMethod};
    use nalgebra::{Matrix3, Translation3, UnitQuaternion, Vector3};
    use opencv::calib3d::{HandEyeCalibrationMethod, RobotWorldHandEyeCalibrationMethod};
    use opencv::core::{Mat, MatTraitConst, Vector};

    /// Errors from OpenCV, or from reading its output.
    pub type Result<T> = opencv::Result<T>;

    fn err(msg: String) -> opencv::Error {
        opencv::Error::new(opencv::core::StsError, msg)
    }

    /// A 3x3 `CV_64F` rotation matrix.
    pub fn rotation_to_mat(r: &UnitQuaternion<f64>) -> Result<Mat> {
        let m = r.to_rotation_matrix();
        let rows: Vec<[f64; 3]> = (0..3).map(|i| [m[(i, 0)], m[(i, 1)], m[(i, 2)]]).collect();
        Mat::from_slice_2d(&rows)
    }

    /// A 3x1 `CV_64F` column (translation or Rodrigues vector).
    pub fn vector_to_mat(v: &Vector3<f64>) -> Result<Mat> {
        Mat::from_slice_2d(&[[v.x], [v.y], [v.z]])
    }

    /// A pose as OpenCV's `(R 3x3, t 3x1)`.
    pub fn iso_to_rt(pose: &Iso3) -> Result<(Mat, Mat)> {
        Ok((
            rotation_to_mat(&pose.rotation)?,
            vector_to_mat(&pose.translation.vector)?,
        ))
    }

    /// A pose as OpenCV's `(rvec 3x1, tvec 3x1)`, the Rodrigues form of
    /// `solvePnP` and friends.
    pub fn iso_to_rvec_tvec(pose: &Iso3) -> Result<(Mat, Mat)> {
        Ok((
            vector_to_mat(&pose.rotation.scaled_axis())?,
            vector_to_mat(&pose.translation.vector)?,
        ))
    }

    /// Reads a 3-vector from a 3x1 or 1x3 `CV_64F` matrix.
    pub fn mat_to_vector(m: &Mat) -> Result<Vector3<f64>> {
        let (rows, cols) = (m.rows(), m.cols());
        if rows * cols != 3 {
            return Err(err(format!(
                "expected a 3-vector, got a {rows}x{cols} matrix"
            )));
        }
        let at = |k: i32| -> Result<f64> {
            if rows == 3 {
                m.at_2d::<f64>(k, 0).copied()
            } else {
                m.at_2d::<f64>(0, k).copied()
            }
        };
        Ok(Vector3::new(at(0)?, at(1)?, at(2)?))
    }

    /// Reads a rotation from a 3x3 matrix or a 3-element Rodrigues vector. A 3x3
    /// matrix must be orthonormal to 1e-6 and is then projected onto SO(3).
    pub fn mat_to_rotation(m: &Mat) -> Result<UnitQuaternion<f64>> {
        if m.rows() == 3 && m.cols() == 3 {
            let r = Matrix3::from_fn(|i, j| {
                m.at_2d::<f64>(i as i32, j as i32)
                    .copied()
                    .unwrap_or(f64::NAN)
            });
            b2b_calib::pose::rotation_from_matrix(&r, 1e-6).map_err(|e| err(e.to_string()))
        } else {
            Ok(UnitQuaternion::from_scaled_axis(mat_to_vector(m)?))
        }
    }

    /// A pose from OpenCV's `(R or rvec, t)`.
    pub fn iso_from_rt(r: &Mat, t: &Mat) -> Result<Iso3> {
        Ok(Iso3::from_parts(
            Translation3::from(mat_to_vector(t)?),
            mat_to_rotation(r)?,
        ))
    }

    /// Poses as the two `Vector<Mat>` (3x3 rotations, 3x1 translations) OpenCV's
    /// solvers take.
    pub fn poses_to_vectors(poses: &[Iso3]) -> Result<(Vector<Mat>, Vector<Mat>)> {
        let mut rs = Vector::<Mat>::with_capacity(poses.len());
        let mut ts = Vector::<Mat>::with_capacity(poses.len());
        for p in poses {
            let (r, t) = iso_to_rt(p)?;
            rs.push(r);
            ts.push(t);
        }
        Ok((rs, ts))
    }

    /// OpenCV's enum for one of our hand-eye methods.
    pub fn hand_eye_method(m: HandEyeMethod) -> HandEyeCalibrationMethod {
        match m {
            HandEyeMethod::Tsai => HandEyeCalibrationMethod::CALIB_HAND_EYE_TSAI,
            HandEyeMethod::Park => HandEyeCalibrationMethod::CALIB_HAND_EYE_PARK,
            HandEyeMethod::Horaud => HandEyeCalibrationMethod::CALIB_HAND_EYE_HORAUD,
            HandEyeMethod::Andreff => HandEyeCalibrationMethod::CALIB_HAND_EYE_ANDREFF,
            HandEyeMethod::Daniilidis => HandEyeCalibrationMethod::CALIB_HAND_EYE_DANIILIDIS,
        }
    }

    /// OpenCV's enum for one of our robot-world methods.
    pub fn robot_world_method(m: RobotWorldMethod) -> RobotWorldHandEyeCalibrationMethod {
        match m {
            RobotWorldMethod::Shah => {
                RobotWorldHandEyeCalibrationMethod::CALIB_ROBOT_WORLD_HAND_EYE_SHAH
            }
            RobotWorldMethod::Li => {
                RobotWorldHandEyeCalibrationMethod::CALIB_ROBOT_WORLD_HAND_EYE_LI
            }
        }
    }

    /// The inputs of `calibrateHandEye`, converted once (so benchmarks can time the
    /// solver alone).
    #[derive(Debug)]
    pub struct HandEyeInputs {
        pub r_gripper2base: Vector<Mat>,
        pub t_gripper2base: Vector<Mat>,
        pub r_target2cam: Vector<Mat>,
        pub t_target2cam: Vector<Mat>,
    }

    impl HandEyeInputs {
        pub fn new(base_from_flange: &[Iso3], camera_from_target: &[Iso3]) -> Result<Self> {
            let (r_gripper2base, t_gripper2base) = poses_to_vectors(base_from_flange)?;
            let (r_target2cam, t_target2cam) = poses_to_vectors(camera_from_target)?;
            Ok(HandEyeInputs {
                r_gripper2base,
                t_gripper2base,
                r_target2cam,
                t_target2cam,
            })
        }

        /// `cv::calibrateHandEye`; returns `cam2gripper` = `flange_from_camera`.
        pub fn calibrate(&self, method: HandEyeMethod) -> Result<Iso3> {
            let mut r = Mat::default();
            let mut t = Mat::default();
            opencv::calib3d::calibrate_hand_eye(
                &self.r_gripper2base,
                &self.t_gripper2base,
                &self.r_target2cam,
                &self.t_target2cam,
                &mut r,
                &mut t,
                hand_eye_method(method),
            )?;
            iso_from_rt(&r, &t)
        }
    }

    /// The inputs of `calibrateRobotWorldHandEye`, converted once. Note
    /// `base2gripper` is the **inverse** of the forward-kinematics pose.
    #[derive(Debug)]
    pub struct RobotWorldInputs {
        pub r_world2cam: Vector<Mat>,
        pub t_world2cam: Vector<Mat>,
        pub r_base2gripper: Vector<Mat>,
        pub t_base2gripper: Vector<Mat>,
    }

    impl RobotWorldInputs {
        pub fn new(base_from_flange: &[Iso3], camera_from_target: &[Iso3]) -> Result<Self> {
            let flange_from_base: Vec<Iso3> =
                base_from_flange.iter().map(|p| p.inverse()).collect();
            let (r_world2cam, t_world2cam) = poses_to_vectors(camera_from_target)?;
            let (r_base2gripper, t_base2gripper) = poses_to_vectors(&flange_from_base)?;
            Ok(RobotWorldInputs {
                r_world2cam,
                t_world2cam,
                r_base2gripper,
                t_base2gripper,
            })
        }

        /// `cv::calibrateRobotWorldHandEye`, returned in this project's naming
        /// (`base2world` and `gripper2cam` inverted).
        pub fn calibrate(&self, method: RobotWorldMethod) -> Result<RobotWorld> {
            let (mut r_bw, mut t_bw, mut r_gc, mut t_gc) = (
                Mat::default(),
                Mat::default(),
                Mat::default(),
                Mat::default(),
            );
            opencv::calib3d::calibrate_robot_world_hand_eye(
                &self.r_world2cam,
                &self.t_world2cam,
                &self.r_base2gripper,
                &self.t_base2gripper,
                &mut r_bw,
                &mut t_bw,
                &mut r_gc,
                &mut t_gc,
                robot_world_method(method),
            )?;
            let target_from_base = iso_from_rt(&r_bw, &t_bw)?;
            let camera_from_flange = iso_from_rt(&r_gc, &t_gc)?;
            Ok(RobotWorld {
                flange_from_camera: camera_from_flange.inverse(),
                base_from_target: target_from_base.inverse(),
            })
        }
    }

    /// One-shot `cv::calibrateHandEye` in this project's naming.
    pub fn calibrate_hand_eye(
        base_from_flange: &[Iso3],
        camera_from_target: &[Iso3],
        method: HandEyeMethod,
    ) -> Result<Iso3> {
        HandEyeInputs::new(base_from_flange, camera_from_target)?.calibrate(method)
    }

    /// One-shot `cv::calibrateRobotWorldHandEye` in this project's naming.
    pub fn calibrate_robot_world(
        base_from_flange: &[Iso3],
        camera_from_target: &[Iso3],
        method: RobotWorldMethod,
    ) -> Result<RobotWorld> {
        RobotWorldInputs::new(base_from_flange, camera_from_target)?.calibrate(method)
    }
}

/// Synthetic inputs shared by the agreement tests and the benchmarks.
pub mod data {
    use b2b_calib::Iso3;
    use b2b_calib::synth::{SynthConfig, SynthRobot, random_robot};

    /// A noisy 30-capture problem from `b2b_calib::synth` (default noise: 0.2 px,
    /// 0.05 mm, 0.01°). Its viewpoints roll freely about the viewing axis, so
    /// relative rotations reach 180°.
    pub fn noisy_robot(seed: u64) -> SynthRobot {
        random_robot(seed, &SynthConfig::default()).expect("synthetic problem")
    }

    /// A noisy problem whose relative rotations all stay below `max_pair_deg`: `n`
    /// captures greedily picked from a larger synthetic set (same noise model),
    /// each within `max_pair_deg` of all captures picked before. OpenCV's Tsai,
    /// Horaud and Daniilidis pick quaternion signs consistently only below 120°
    /// (see `b2b_calib::handeye`), so exact agreement is tested on such data.
    pub fn bounded_rotation_robot(seed: u64, n: usize, max_pair_deg: f64) -> SynthRobot {
        let cfg = SynthConfig {
            captures: 20 * n,
            ..SynthConfig::default()
        };
        let all = random_robot(seed, &cfg).expect("synthetic problem");
        let limit = max_pair_deg.to_radians();
        let mut picked: Vec<usize> = Vec::with_capacity(n);
        for i in 0..all.base_from_flange.len() {
            let ok = picked.iter().all(|&j| {
                all.base_from_flange[i]
                    .rotation
                    .angle_to(&all.base_from_flange[j].rotation)
                    < limit
            });
            if ok {
                picked.push(i);
                if picked.len() == n {
                    break;
                }
            }
        }
        assert_eq!(
            picked.len(),
            n,
            "could not pick {n} captures within {max_pair_deg} deg"
        );
        let take = |v: &[Iso3]| picked.iter().map(|&i| v[i]).collect::<Vec<Iso3>>();
        SynthRobot {
            flange_from_camera: all.flange_from_camera,
            base_from_target: all.base_from_target,
            true_base_from_flange: take(&all.true_base_from_flange),
            base_from_flange: take(&all.base_from_flange),
            observations: picked
                .iter()
                .map(|&i| all.observations[i].clone())
                .collect(),
            camera_from_target: take(&all.camera_from_target),
            board: all.board,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::cv;
    use b2b_calib::Iso3;
    use nalgebra::Vector3;

    #[test]
    fn rotation_matrix_and_rodrigues_round_trip() {
        let pose = Iso3::new(Vector3::new(0.1, -0.2, 0.3), Vector3::new(0.4, -1.1, 2.5));
        let (r, t) = cv::iso_to_rt(&pose).unwrap();
        let back = cv::iso_from_rt(&r, &t).unwrap();
        let (dt, dr) = b2b_calib::pose::pose_distance(&pose, &back);
        assert!(dt < 1e-15 && dr < 1e-12, "{dt} {dr}");
        let (rv, tv) = cv::iso_to_rvec_tvec(&pose).unwrap();
        let back = cv::iso_from_rt(&rv, &tv).unwrap();
        let (dt, dr) = b2b_calib::pose::pose_distance(&pose, &back);
        assert!(dt < 1e-15 && dr < 1e-12, "{dt} {dr}");
    }

    #[test]
    fn rotation_matrix_layout_matches_opencv_rodrigues() {
        // OpenCV's own Rodrigues of our rvec must give our 3x3 matrix (row-major).
        let pose = Iso3::new(Vector3::zeros(), Vector3::new(0.3, 0.2, -0.7));
        let (rv, _) = cv::iso_to_rvec_tvec(&pose).unwrap();
        let mut m = opencv::core::Mat::default();
        opencv::calib3d::rodrigues_def(&rv, &mut m).unwrap();
        let (r, _) = cv::iso_to_rt(&pose).unwrap();
        let diff = opencv::core::norm2_def(&m, &r).unwrap();
        assert!(diff < 1e-12, "{diff}");
    }
}
