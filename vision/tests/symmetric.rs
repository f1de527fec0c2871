//! Symmetric checkerboards (odd x odd squares, square boards): the detector returns the
//! corners in one labelling plus the board's symmetry instead of refusing, on rendered
//! boards with exactly known corners.

use b2b_calib::camera::CameraModel;
use b2b_vision::synth::{BoardScene, render_checkerboard};
use b2b_vision::{
    CheckerboardSpec, VisionError, detect_checkerboard, detect_checkerboard_up_to_symmetry,
};
use nalgebra::{Isometry3, Point2, Translation3, UnitQuaternion, Vector3};

fn camera() -> CameraModel {
    CameraModel::new(640, 480, [560.0, 560.0, 319.7, 240.2], &[]).unwrap()
}

/// The board centred 0.55 m in front of the camera, turned by roll/pitch/yaw (degrees).
fn pose(spec: &CheckerboardSpec, [roll, pitch, yaw]: [f64; 3]) -> Isometry3<f64> {
    let r =
        UnitQuaternion::from_euler_angles(roll.to_radians(), pitch.to_radians(), yaw.to_radians());
    let centre = Vector3::new(
        (spec.cols - 1) as f64 * spec.square_m / 2.0,
        (spec.rows - 1) as f64 * spec.square_m / 2.0,
        0.0,
    );
    Isometry3::from_parts(
        Translation3::from(Vector3::new(0.01, -0.005, 0.55) - r * centre),
        r,
    )
}

/// The elements `k` of the symmetry under which the detection is the truth:
/// `pixels[permutation_k[m]]` is the true image of corner `m`.
fn matching_elements(
    pixels: &[Point2<f64>],
    truth: &[Point2<f64>],
    sym: &b2b_calib::symmetry::TargetSymmetry,
) -> (Vec<usize>, f64) {
    let mut worst_match = 0.0_f64;
    let ks = sym
        .elements()
        .iter()
        .enumerate()
        .filter_map(|(k, el)| {
            let worst = (0..truth.len())
                .map(|m| (pixels[el.permutation[m]] - truth[m]).norm())
                .fold(0.0, f64::max);
            (worst < 0.5).then(|| {
                worst_match = worst_match.max(worst);
                k
            })
        })
        .collect();
    (ks, worst_match)
}

#[test]
fn symmetric_boards_are_detected_with_their_symmetry() {
    // (cols, rows, group size, elements the colours allow)
    let cases: [(usize, usize, usize, &[usize]); 3] = [
        // 9x7 squares: identity and the half-turn, both look the same.
        (8, 6, 2, &[0, 1]),
        // 7x7 squares: all four quarter turns look the same.
        (6, 6, 4, &[0, 1, 2, 3]),
        // 6x6 squares: a quarter turn swaps the colours, so only the half-turn is left.
        (5, 5, 2, &[0, 1]),
    ];
    for (cols, rows, len, allowed) in cases {
        let spec = CheckerboardSpec {
            cols,
            rows,
            square_m: 0.03,
        };
        let mut seen = vec![];
        for yaw in [3.0, 93.0, 183.0, 273.0] {
            let scene = BoardScene::new(spec, camera(), pose(&spec, [12.0, -8.0, yaw]));
            let (img, truth) = render_checkerboard(&scene).unwrap();
            // The plain detector still refuses: its callers take the labelling as the truth.
            let err = detect_checkerboard(&img, &spec).unwrap_err();
            assert!(matches!(err, VisionError::AmbiguousOrientation(_)), "{err}");
            let (det, sym) = detect_checkerboard_up_to_symmetry(&img, &spec)
                .unwrap_or_else(|e| panic!("{cols}x{rows} yaw {yaw}: {e}"));
            assert_eq!(sym.len(), len, "{cols}x{rows}");
            assert_eq!(det.pixels.len(), cols * rows);
            let (ks, worst) = matching_elements(&det.pixels, &truth, &sym);
            eprintln!(
                "{cols}x{rows} yaw {yaw:5.1}: symmetry of {} ({}), detection = truth under {ks:?}, worst corner {worst:.3} px",
                sym.len(),
                sym.elements()
                    .iter()
                    .map(|e| e.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            );
            assert_eq!(ks.len(), 1, "{cols}x{rows} yaw {yaw}: {ks:?}");
            assert!(allowed.contains(&ks[0]), "{cols}x{rows} yaw {yaw}: {ks:?}");
            // The colour rule holds: inner square (0, 0) is dark. Target points follow the ids.
            assert_eq!(det.corner_ids, (0..cols * rows).collect::<Vec<_>>());
            seen.push(ks[0]);
        }
        // Turning the board by 90° steps really changes which labelling comes back.
        seen.sort();
        seen.dedup();
        assert!(seen.len() >= 2, "{cols}x{rows}: always {seen:?}");
    }
}

#[test]
fn asymmetric_boards_are_detected_as_before_with_no_symmetry() {
    let spec = CheckerboardSpec {
        cols: 9,
        rows: 6,
        square_m: 0.03,
    };
    for yaw in [3.0, 183.0] {
        let scene = BoardScene::new(spec, camera(), pose(&spec, [12.0, -8.0, yaw]));
        let (img, truth) = render_checkerboard(&scene).unwrap();
        let plain = detect_checkerboard(&img, &spec).unwrap();
        let (det, sym) = detect_checkerboard_up_to_symmetry(&img, &spec).unwrap();
        assert!(sym.is_trivial());
        assert_eq!(det, plain);
        let (ks, worst) = matching_elements(&det.pixels, &truth, &sym);
        eprintln!("9x6 yaw {yaw}: worst corner {worst:.3} px");
        assert_eq!(ks, vec![0]);
    }
}
