//! Robots that do not all see one target (#15): robot 1 sees the dataset's
//! `target`, robot 3 only a second board (`targets.side`), robot 2 both. The
//! datasets are written with pose-only rows (`T_camera_target` given, no
//! images: they exercise the solver, not the detector) by
//! `b2b_sim::pose_only::write_two_targets`, read back through the dataset
//! reader and calibrated as `coordinator calibrate` does.

use b2b_calib::refine::RefineOptions;
use b2b_dataset::{Dataset, DatasetError};
use b2b_pipeline::{B2bMethod, PipelineError, base_to_base, load_dataset};
use b2b_sim::pose_only::write_two_targets;

#[test]
fn a_robot_that_sees_only_another_target_is_placed_through_one_that_sees_both() {
    let dir = tempfile::tempdir().unwrap();
    let two = write_two_targets(dir.path(), 41, true).unwrap();
    let ds = load_dataset(dir.path()).unwrap();
    assert_eq!(ds.manifest.targets.len(), 1);
    assert_eq!(ds.robots[2].captures[0].target.as_deref(), Some("side"));
    let result = base_to_base(&ds, B2bMethod::Board, &RefineOptions::default()).unwrap();
    assert_eq!(result.reference.as_deref(), Some("robot1"));
    let mut errors = Vec::new();
    for (r, id) in ["robot2", "robot3"].iter().enumerate() {
        let base = &result.bases[*id];
        let est = base.ref_from_base.to_isometry("T_ref_base").unwrap();
        let truth = two.base1_from_base[r];
        // Where the robot works: the centre of the last target it sees.
        let centre = two.base1_from_target[r] * nalgebra::Point3::new(0.1, 0.0625, 0.0);
        let error = (est * (truth.inverse() * centre) - centre).norm();
        let d = b2b_calib::pose::left_difference(&est, &truth);
        let cov = nalgebra::Matrix6::from_fn(|i, j| base.covariance[i][j]);
        let m2 = b2b_calib::refine::mahalanobis2(&d, &cov).unwrap();
        // The point's own standard deviation at the target centre (left
        // perturbation: δp = δr × p + δt).
        let mut j = nalgebra::Matrix3x6::zeros();
        j.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(-centre.coords.cross_matrix()));
        j.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&nalgebra::Matrix3::identity());
        let sd = (j * cov * j.transpose()).trace().sqrt();
        eprintln!(
            "{id}: {:.3} mm at its target (σ there {:.3} mm), Mahalanobis² {m2:.1}, predicted p95 {:.3} mm",
            error * 1e3,
            sd * 1e3,
            base.predicted_touch_error_m.p95 * 1e3
        );
        errors.push((id, error, sd, m2));
    }
    // Pose-only rows hide the pixel noise inside each pose (their corners are
    // projected exactly from it), so the fit sees it as robot noise and the
    // bases come out looser than from images: 0.38 mm (σ 1.7 mm) and 1.3 mm
    // (σ 2.3 mm) when measured. What is asserted is that both are found and
    // inside their own uncertainty; `b2b-calib`'s
    // `robots_that_see_different_targets_...` test measures the accuracy over
    // ten problems with pixels.
    for (id, error, sd, m2) in errors {
        assert!(m2 < 22.46, "{id}: Mahalanobis² {m2}");
        assert!(error < 3.0 * sd, "{id}: {error} m, σ {sd} m");
    }
}

#[test]
fn robots_no_shared_target_links_are_named() {
    let dir = tempfile::tempdir().unwrap();
    write_two_targets(dir.path(), 41, false).unwrap();
    let ds = load_dataset(dir.path()).unwrap();
    let err = base_to_base(&ds, B2bMethod::Board, &RefineOptions::default()).unwrap_err();
    match &err {
        PipelineError::Disconnected { reference, cut_off } => {
            assert_eq!(reference, "robot1");
            assert_eq!(cut_off, &["robot3".to_owned()]);
        }
        other => panic!("expected Disconnected, got {other}"),
    }
    assert!(
        err.to_string()
            .starts_with("robot3 cannot be placed in robot1's base"),
        "{err}"
    );
}

#[test]
fn a_capture_naming_an_unlisted_target_is_refused_with_its_row() {
    let dir = tempfile::tempdir().unwrap();
    write_two_targets(dir.path(), 41, true).unwrap();
    let file = dir.path().join("robot3").join("captures.csv");
    let text = std::fs::read_to_string(&file).unwrap();
    std::fs::write(&file, text.replacen(",side", ",sdie", 1)).unwrap();
    let err = Dataset::load(dir.path()).unwrap_err();
    assert!(matches!(err, DatasetError::UnknownTarget { .. }), "{err}");
    let message = err.to_string();
    for part in ["robot3/captures.csv", "row 1", "target `sdie`", "(side)"] {
        assert!(message.contains(part), "`{part}` not in: {message}");
    }
}
