//! The estimator on real arms: one arm's real captures split into two pseudo
//! robots (even and odd rows, or the recording's first half and its second),
//! the second base moved by a chosen transform, so `base1_from_base2` is exact
//! while the images and the arm's errors stay real (`common::split`). Each
//! figure is the error at 25 touch locations over the working volume (mean),
//! against Park on our detections, the best of the closed forms chosen by the
//! truth, OpenCV alone (`common::opencv_peer`: Park on its classic detector,
//! what a user picks, and the best of every detector, intrinsics and solver
//! pair chosen by the truth), and the result's predicted p95 at those
//! locations over the true p95. `docs/accuracy.md` tracks them.

use b2b_calib::Iso3;
use b2b_calib::metrics::predicted_error;
use b2b_calib::refine::RefineOptions;
use b2b_pipeline::{B2bMethod, CalibrationRun, base_to_base_run};
use nalgebra::Point3;

mod common;
use common::split::*;

/// What one real split measures.
#[derive(Debug)]
struct Figures {
    ours_mm: f64,
    park_mm: f64,
    /// Park on poses from the jointly refined cameras (the pipeline's initial
    /// intrinsics come from 8 views; a user of OpenCV would calibrate on all).
    park_refined_camera_mm: f64,
    best_mm: f64,
    best: &'static str,
    predicted_p95_mm: f64,
    true_p95_mm: f64,
    /// OpenCV alone (`common::opencv_peer`): Park on the classic detector
    /// (what a user picks), and the best of every detector and solver pair
    /// chosen by the truth (no user can pick that way).
    opencv_park_mm: f64,
    opencv_best_mm: f64,
    opencv_best: String,
    /// The model selection's choice and the held-out RMS (px) of it and Park.
    chosen: String,
    held_out_chosen_px: f64,
    held_out_park_px: f64,
}

impl Figures {
    fn ratio(&self) -> f64 {
        self.predicted_p95_mm / self.true_p95_mm
    }
}

/// `value` within 1.5x of `expected`, either way.
fn within(what: &str, value: f64, expected: f64) {
    assert!(
        value < 1.5 * expected && value > expected / 1.5,
        "{what}: {value} against {expected} (docs/accuracy.md): update both"
    );
}

fn measure(name: &str, s: &Split) -> (Figures, CalibrationRun) {
    let run = base_to_base_run(&s.dataset, B2bMethod::Board, &RefineOptions::default()).unwrap();
    let r = &run.result;
    let selection = r.model_selection.clone().expect("cross-validated");
    let truth = s.base1_from_base2;
    let flanges: Vec<Point3<f64>> = run.observations[0]
        .observations
        .iter()
        .map(|o| Point3::from(o.board.base_from_flange.translation.vector))
        .collect();
    let points = touch_locations(&flanges);
    let est: Iso3 = r.base1_from_base2.to_isometry("T").unwrap();
    let ours = touch_errors(&est, &truth, &points);
    let cov = nalgebra::Matrix6::from_fn(|i, j| r.covariance[i][j]);
    let (_, predicted_p95) = predicted_error(&cov, &points, 0.0);
    let mut closed = vec![];
    for (k, m) in CLOSED_FORMS.iter().enumerate() {
        let e = closed_form_base1_from_base2(&run.observations, k)
            .map_or(f64::INFINITY, |z| mean(&touch_errors(&z, &truth, &points)));
        closed.push((*m, e));
    }
    for rej in &r.captures.rejected {
        eprintln!(
            "  rejected: {} row {:?}: {}",
            rej.robot, rej.row, rej.reason
        );
    }
    // Park on the captures the fit kept (the screen's and fit's rejections out).
    let mut kept_obs = run.observations.clone();
    for o in &mut kept_obs {
        let robot = o.robot.clone();
        o.observations.retain(|x| {
            !r.captures
                .rejected
                .iter()
                .any(|j| j.robot == robot && j.row == Some(x.row))
        });
    }
    let park_kept = closed_form_base1_from_base2(&kept_obs, 1)
        .map_or(f64::INFINITY, |z| mean(&touch_errors(&z, &truth, &points)));
    eprintln!(
        "  park on the captures the fit kept: {:.3} mm",
        park_kept * 1e3
    );
    let refit: Vec<_> = run
        .observations
        .iter()
        .zip(&run.cameras)
        .map(|(o, c)| b2b_pipeline::refit_poses(o.clone(), c.camera.clone(), "the refined camera"))
        .collect();
    let park_refit = closed_form_base1_from_base2(&refit, 1)
        .map_or(f64::INFINITY, |z| mean(&touch_errors(&z, &truth, &points)));
    eprintln!(
        "  park with the jointly refined cameras: {:.3} mm",
        park_refit * 1e3
    );
    let pairs = common::opencv_peer::opencv_pairs(s, &run, &points);
    for p in &pairs {
        eprintln!(
            "  opencv {} ({}) + {}: {:.3} mm",
            p.detector,
            p.intrinsics,
            p.solver,
            p.error_m * 1e3
        );
    }
    let opencv_park = pairs
        .iter()
        .find(|p| p.solver == "park")
        .map_or(f64::INFINITY, |p| p.error_m);
    let opencv_best = pairs
        .iter()
        .min_by(|a, b| a.error_m.total_cmp(&b.error_m))
        .unwrap();
    let park = closed[1].1;
    let (best, best_e) = closed
        .iter()
        .copied()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap();
    let f = Figures {
        ours_mm: mean(&ours) * 1e3,
        park_mm: park * 1e3,
        park_refined_camera_mm: park_refit * 1e3,
        opencv_park_mm: opencv_park * 1e3,
        opencv_best_mm: opencv_best.error_m * 1e3,
        opencv_best: format!(
            "{} ({}) + {}",
            opencv_best.detector, opencv_best.intrinsics, opencv_best.solver
        ),
        best_mm: best_e * 1e3,
        best,
        predicted_p95_mm: predicted_p95 * 1e3,
        true_p95_mm: p95(&ours) * 1e3,
        chosen: selection.chosen.clone(),
        held_out_chosen_px: selection.held_out_px[&selection.chosen],
        held_out_park_px: selection.held_out_px["park"],
    };
    // Never worse than Park on the evidence it computes.
    assert!(f.held_out_chosen_px <= f.held_out_park_px, "{selection:?}");
    eprintln!(
        "{name}: used {:?}; ours {:.3} mm, park {:.3} mm, best closed form {:.3} mm ({}); \
         predicted p95 {:.3} mm / true p95 {:.3} mm = {:.2}x",
        r.captures.used,
        f.ours_mm,
        f.park_mm,
        f.best_mm,
        f.best,
        f.predicted_p95_mm,
        f.true_p95_mm,
        f.ratio()
    );
    eprintln!(
        "  OpenCV alone: park {:.3} mm, best of {} pairs {:.3} mm ({}); ours / best {:.2}",
        f.opencv_park_mm,
        pairs.len(),
        f.opencv_best_mm,
        f.opencv_best,
        f.ours_mm / f.opencv_best_mm
    );
    eprintln!(
        "  closed forms (mm): {}",
        closed
            .iter()
            .map(|(m, e)| format!("{m} {:.3}", e * 1e3))
            .collect::<Vec<_>>()
            .join(", ")
    );
    eprintln!("  model selection: {selection:?}");
    for c in &run.cameras {
        eprintln!("  {}", c.describe());
        if let Some(n) = &c.pose_error {
            eprintln!("  {} pose error: {}", c.robot, n.describe());
        }
    }
    // Never behind what a user of OpenCV picks, on the truth.
    assert!(
        f.ours_mm <= f.opencv_park_mm,
        "{name}: ours {} mm, OpenCV's Park {} mm",
        f.ours_mm,
        f.opencv_park_mm
    );
    (f, run)
}

/// Tabb & Ahmad Yousef's Denso arm (88 captures, no intrinsics, a symmetric
/// board 2 m away), 44 captures per pseudo robot.
#[test]
fn tabb_denso_split() {
    let s = split("tabb-denso-ds1", &chosen_base1_from_base2());
    let (f, _) = measure("tabb-denso-ds1", &s);
    // docs/accuracy.md
    within("ours", f.ours_mm, 4.12);
    within("park, refined cameras", f.park_refined_camera_mm, 6.91);
    within("predicted / true p95", f.ratio(), 1.44);
    assert!(f.ratio() >= 1.0, "the bound below the truth: {}", f.ratio());
    within("OpenCV's park", f.opencv_park_mm, 19.3);
    within("OpenCV's best pair", f.opencv_best_mm, 5.17);
    within(
        "ours / OpenCV's best pair",
        f.ours_mm / f.opencv_best_mm,
        0.80,
    );
    // The held-out captures keep the default: the refined shapes predict them
    // at 2.04-2.08 px RMS, the closed forms (on the jointly refined cameras)
    // at 2.5 px and worse.
    assert_eq!(f.chosen, "refined");
    within("held-out, refined", f.held_out_chosen_px, 2.04);
    within("held-out, park", f.held_out_park_px, 3.33);
}

/// The Denso recording's first 44 captures against its last 44: the halves
/// see the working volume along different parts of the path.
#[test]
fn tabb_denso_halves() {
    let s = split_by("tabb-denso-ds1", &chosen_base1_from_base2(), Deal::Halves);
    let (f, run) = measure("tabb-denso-ds1 halves", &s);
    // docs/accuracy.md: ahead of what a user of OpenCV picks, behind its best
    // pair chosen by the truth, and a bound just above the truth (the halves'
    // own systematic errors differ, and nothing in one half's captures shows the
    // part common to all of them; the agreeing models' spread holds it).
    within("ours", f.ours_mm, 11.9);
    within("OpenCV's park", f.opencv_park_mm, 43.8);
    within("OpenCV's best pair", f.opencv_best_mm, 6.24);
    within(
        "ours / OpenCV's best pair",
        f.ours_mm / f.opencv_best_mm,
        1.91,
    );
    within("predicted / true p95", f.ratio(), 1.09);
    assert!(f.ratio() >= 1.0, "the bound below the truth: {}", f.ratio());
    // The held-out captures choose the refinement even so (1.66 px against
    // Park's 2.47 on the refined cameras): they test each robot's own fit, and
    // nothing in them checks the bases against each other.
    assert_eq!(f.chosen, "refined");
    within("held-out, refined", f.held_out_chosen_px, 1.66);
    within("held-out, park", f.held_out_park_px, 2.47);
    within("park, refined cameras", f.park_refined_camera_mm, 6.15);
    // The refined shapes predict the held-out corners within 1% of each other
    // (1.646 to 1.661 px) while their bases lie apart: the estimate is their
    // mean (14.6 mm with the chosen shape alone) and the bound holds their
    // spread about it (0.72x the truth without it).
    let selection = run.result.model_selection.as_ref().unwrap();
    for (shape, px) in [
        ("refined/base", 1.646),
        ("refined/flange", 1.654),
        ("refined/two-centres", 1.661),
    ] {
        within(shape, selection.held_out_px[shape], px);
        assert!(
            selection.agreeing.iter().any(|c| c == shape),
            "{shape}: {selection:?}"
        );
    }
    let px: Vec<f64> = ["refined/base", "refined/flange", "refined/two-centres"]
        .iter()
        .map(|shape| selection.held_out_px[*shape])
        .collect();
    let (lo, hi) = px.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &x| {
        (lo.min(x), hi.max(x))
    });
    // Within 1% of each other (asserted within 1.5x: 1.5%).
    assert!(hi / lo - 1.0 < 0.015, "the shapes' held-out px {px:?}");
}

/// ViSP's first four captures against its last four.
#[test]
fn visp_franka_halves() {
    let s = split_by(
        "visp-franka-eye-in-hand",
        &chosen_base1_from_base2(),
        Deal::Halves,
    );
    let (f, _) = measure("visp-franka-eye-in-hand halves", &s);
    // docs/accuracy.md
    within("ours", f.ours_mm, 6.82);
    within("OpenCV's park", f.opencv_park_mm, 7.57);
    within("OpenCV's best pair", f.opencv_best_mm, 4.42);
    within(
        "ours / OpenCV's best pair",
        f.ours_mm / f.opencv_best_mm,
        1.54,
    );
    within("predicted / true p95", f.ratio(), 2.2);
}

/// ViSP's Franka recording (8 captures, intrinsics given), 4 per pseudo robot.
#[test]
fn visp_franka_split() {
    let s = split("visp-franka-eye-in-hand", &chosen_base1_from_base2());
    let (f, run) = measure("visp-franka-eye-in-hand", &s);
    // docs/accuracy.md
    within("ours", f.ours_mm, 3.04);
    within("park", f.park_mm, 3.09);
    within("predicted / true p95", f.ratio(), 4.9);
    within("OpenCV's park", f.opencv_park_mm, 3.15);
    within("OpenCV's best pair", f.opencv_best_mm, 3.13);
    within(
        "ours / OpenCV's best pair",
        f.ours_mm / f.opencv_best_mm,
        0.97,
    );
    // Three captures per robot in each fold's fit: the refinement's noise model
    // has too little to go on (29.5 px and worse), the closed forms predict the
    // held-out captures better and Daniilidis best. Those fits scatter 3.8x the
    // covariance; near-minimal folds are no evidence for the bound
    // (`calib/tests/spread_scale.rs`), so it is reported, not applied.
    assert_eq!(f.chosen, "daniilidis");
    let selection = run
        .result
        .model_selection
        .as_ref()
        .expect("cross-validated");
    assert_eq!(selection.spread_scale, None);
    let scatter = selection.fold_scatter.expect("the folds' scatter");
    within("folds' scatter", scatter, 3.81);
    within("held-out, chosen", f.held_out_chosen_px, 14.4);
    within("held-out, park", f.held_out_park_px, 14.9);
}

/// The bound's ratio on the rendered sets (their truth from
/// `ground_truth.json`): predicted p95 over the true p95 at 27 points of a
/// 0.3 m cube about robot 1's mean flange position.
#[test]
fn rendered_sets_bound_ratio() {
    use b2b_dataset::{Dataset, load_ground_truth};
    // docs/accuracy.md: (set, method, predicted / true p95)
    for (name, method, expected) in [
        ("sim-checkerboard-2x12", B2bMethod::Board, 1.99),
        ("sim-multimarker-4x3-2x10", B2bMethod::Multimarker, 0.98),
        ("sim-multimarker-corner-2x10", B2bMethod::Multimarker, 1.70),
    ] {
        let dir = common::bundled(name);
        let ds = Dataset::load(&dir).unwrap();
        let truth = load_ground_truth(&dir)
            .unwrap()
            .unwrap()
            .base1_from_base2
            .unwrap();
        let run = base_to_base_run(&ds, method, &RefineOptions::default()).unwrap();
        let r = &run.result;
        let est: Iso3 = r.base1_from_base2.to_isometry("T").unwrap();
        // A 0.3 m cube about robot 1's mean flange position.
        let flanges: Vec<Point3<f64>> = run.observations[0]
            .observations
            .iter()
            .map(|o| Point3::from(o.board.base_from_flange.translation.vector))
            .collect();
        let mean_flange = Point3::from(
            flanges
                .iter()
                .fold(nalgebra::Vector3::zeros(), |a, p| a + p.coords)
                / flanges.len() as f64,
        );
        let points: Vec<Point3<f64>> = (0..27)
            .map(|k| {
                let o =
                    nalgebra::Vector3::new((k % 3) as f64, ((k / 3) % 3) as f64, (k / 9) as f64)
                        * 0.15
                        - nalgebra::Vector3::repeat(0.15);
                mean_flange + o
            })
            .collect();
        let errors = touch_errors(&est, &truth, &points);
        let cov = nalgebra::Matrix6::from_fn(|i, j| r.covariance[i][j]);
        let (_, predicted) = predicted_error(&cov, &points, 0.0);
        let ratio = predicted / p95(&errors);
        eprintln!(
            "{name}: {:.3} mm mean, predicted p95 {:.3} mm / true p95 {:.3} mm = {ratio:.2}x; {:?}",
            mean(&errors) * 1e3,
            predicted * 1e3,
            p95(&errors) * 1e3,
            r.model_selection
                .as_ref()
                .map(|m| (&m.chosen, m.spread_scale))
        );
        within(name, ratio, expected);
    }
}
