//! Our camera model against OpenCV's `projectPoints`: the refinement fits
//! corners through `CameraModel::project`, the detectors and the intrinsics
//! calibration use OpenCV's model, so the two must be the same function.
//!
//! Random cameras with the full rational distortion (k1, k2, p1, p2, k3, k4, k5,
//! k6), random poses and points across the image, including its corners where
//! distortion is strongest: they agree to 1e-9 px.

use b2b_calib::camera::CameraModel;
use b2b_tests::cv::iso_to_rvec_tvec;
use nalgebra::{Isometry3, Point3, Vector3};
use opencv::core::{Mat, Point2d, Point3d, Vector};
use rand::{Rng, SeedableRng};

#[test]
fn projection_equals_opencv_project_points() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let mut worst: f64 = 0.0;
    let mut compared = 0;
    for case in 0..50 {
        let mut dist = [0.0; 8];
        // Plain Brown-Conrady for half the cases, the rational model for the rest.
        let terms = if case % 2 == 0 { 5 } else { 8 };
        let scale = [0.2, 0.1, 0.002, 0.002, 0.05, 0.05, 0.02, 0.02];
        for k in 0..terms {
            dist[k] = rng.random_range(-scale[k]..scale[k]);
        }
        let camera = CameraModel {
            width: 1280,
            height: 720,
            fx: rng.random_range(500.0..1500.0),
            fy: rng.random_range(500.0..1500.0),
            cx: rng.random_range(600.0..680.0),
            cy: rng.random_range(330.0..390.0),
            dist,
        };
        let camera_from_target = Isometry3::new(
            Vector3::new(
                rng.random_range(-0.1..0.1),
                rng.random_range(-0.1..0.1),
                rng.random_range(0.3..2.0),
            ),
            Vector3::new(
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.5..0.5),
                rng.random_range(-3.0..3.0),
            ),
        );
        // Points whose rays span the field of view (normalised |x| <= 0.6).
        let points: Vec<Point3<f64>> = (0..40)
            .map(|_| {
                let z = rng.random_range(0.3..2.5);
                let ray = Point3::new(
                    rng.random_range(-0.6..0.6) * z,
                    rng.random_range(-0.4..0.4) * z,
                    z,
                );
                camera_from_target.inverse() * ray
            })
            .collect();
        let ours: Vec<_> = points
            .iter()
            .map(|p| camera.project(&(camera_from_target * p)).expect("in front"))
            .collect();
        let object: Vector<Point3d> = points.iter().map(|p| Point3d::new(p.x, p.y, p.z)).collect();
        let (rvec, tvec) = iso_to_rvec_tvec(&camera_from_target).unwrap();
        let k = Mat::from_slice_2d(&[
            [camera.fx, 0.0, camera.cx],
            [0.0, camera.fy, camera.cy],
            [0.0, 0.0, 1.0],
        ])
        .unwrap();
        let d = Mat::from_slice(&camera.dist[..terms]).unwrap();
        let mut theirs: Vector<Point2d> = Vector::new();
        opencv::calib3d::project_points_def(&object, &rvec, &tvec, &k, &d, &mut theirs).unwrap();
        for (a, b) in ours.iter().zip(theirs.iter()) {
            let e = ((a.x - b.x).powi(2) + (a.y - b.y).powi(2)).sqrt();
            worst = worst.max(e);
            compared += 1;
        }
    }
    eprintln!("{compared} projections, largest difference {worst:.2e} px");
    assert_eq!(compared, 2000);
    assert!(worst < 1e-9, "largest difference {worst} px");
}
