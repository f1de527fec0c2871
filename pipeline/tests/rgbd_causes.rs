//! The RGB-D method's operator mistakes, built from the committed
//! `sim-rgbd-boxes-2x5`: a robot's depth folder holding the other robot's
//! depth images is refused by name; depth at another scale (a wrong
//! `depth_unit_m`) is refused with the scale measured against the robot's
//! motion, or, off by less than a refusal needs, named and held by the
//! result's covariance; a unit that puts the scene outside the working range
//! is refused with the depth it gives. The set as committed is accused of
//! none of them.

mod common;

use b2b_calib::Iso3;
use b2b_calib::pose::left_difference;
use b2b_calib::refine::{RefineOptions, mahalanobis2};
use b2b_dataset::{Dataset, load_ground_truth};
use b2b_pipeline::causes::{is_depth_scaled, kind};
use b2b_pipeline::rgbd::{RgbdOptions, RgbdRun, rgbd_base_to_base};
use common::{bundled, copy_dir};

const SET: &str = "sim-rgbd-boxes-2x5";

/// A copy of the committed set in a temporary folder.
fn copy() -> (tempfile::TempDir, std::path::PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    copy_dir(&bundled(SET), &dir);
    (tmp, dir)
}

fn truth() -> Iso3 {
    load_ground_truth(&bundled(SET))
        .unwrap()
        .unwrap()
        .base1_from_base2
        .unwrap()
}

/// The truth's Mahalanobis² in the result's own covariance.
fn m2(result: &b2b_protocol::CalibrationResult) -> f64 {
    let est = result.base1_from_base2.to_isometry("T").unwrap();
    let cov = nalgebra::Matrix6::from_fn(|i, j| result.covariance[i][j]);
    mahalanobis2(&left_difference(&est, &truth()), &cov).unwrap()
}

/// The method as `coordinator calibrate --method rgbd` runs it, or its error
/// as one line.
fn run(dir: &std::path::Path) -> Result<RgbdRun, String> {
    let ds = Dataset::load(dir).unwrap();
    rgbd_base_to_base(&ds, &RefineOptions::default(), &RgbdOptions::default())
        .map_err(|e| b2b_pipeline::error_chain(&e))
}

fn show(what: &str, run: &RgbdRun) {
    for c in &run.depth_checks {
        eprintln!(
            "{what}: {}: {} of {} evidence pairs agree, scale {:?}",
            c.robot,
            c.agreeing(),
            c.evidence(),
            c.scale
        );
        for p in &c.pairs {
            eprintln!(
                "  rows {:?}: {} lifted, {} inliers, rotation off {:?}°, |t| {:.3} m, {}",
                p.rows,
                p.lifted,
                p.inliers,
                p.rotation_error_rad.map(f64::to_degrees),
                p.predicted.translation.vector.norm(),
                p.reason.as_deref().unwrap_or("")
            );
        }
    }
    eprintln!(
        "{what}: findings {:#?}; m² {:.1}",
        run.result.findings,
        m2(&run.result)
    );
}

/// The committed set: every robot's depth registers to its motion, at its
/// scale; no finding.
#[test]
fn the_committed_rgbd_set_is_not_accused() {
    let r = run(&bundled(SET)).unwrap();
    show("committed", &r);
    // docs/verdict.md: 0.9996 ± 0.0019 and 0.9978 ± 0.0024 (the residuals'
    // 0.0012 and 0.0018 with the check's own systematic limit), every evidence
    // pair agreeing (9 and 10).
    for (c, sigma) in r.depth_checks.iter().zip([0.0019, 0.0024]) {
        assert!(!c.mismatch(), "{}", c.describe_mismatch());
        assert!(
            c.evidence() >= 8,
            "{}: {} evidence pairs",
            c.robot,
            c.evidence()
        );
        assert_eq!(c.agreeing(), c.evidence(), "{}", c.robot);
        let s = c.scale.expect("a scale");
        assert!((s.scale - 1.0).abs() < 0.005, "{}: {s:?}", c.robot);
        assert!(
            s.scale_sigma > sigma / 1.5 && s.scale_sigma < sigma * 1.5,
            "{}: {s:?}",
            c.robot
        );
        assert!(!is_depth_scaled(&s), "{}: {s:?}", c.robot);
        for row in 1..=c.views {
            assert_eq!(c.mismatched_view(row), None, "{} row {row}", c.robot);
        }
    }
    assert!(r.result.findings.is_empty(), "{:#?}", r.result.findings);
    // The truth within the result's covariance.
    assert!(m2(&r.result) <= 22.5, "m² {}", m2(&r.result));
}

/// robot1's depth folder holds robot2's depth images (the same names and size).
#[test]
fn the_other_robots_depth_is_refused_by_name() {
    let (_tmp, dir) = copy();
    let (from, to) = (dir.join("robot2/depth"), dir.join("robot1/depth"));
    for e in std::fs::read_dir(&from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
    match run(&dir) {
        Ok(r) => {
            show("swapped", &r);
            panic!(
                "a result from robot2's depth as robot1's: m² {:.0}",
                m2(&r.result)
            );
        }
        Err(text) => {
            eprintln!("{text}");
            assert!(
                text.contains("robot1's depth images do not match its colour images"),
                "{text}"
            );
            assert!(text.contains("robot1/depth"), "{text}");
            // docs/verdict.md: none of 8 pairs with evidence agrees.
            let evidence = number_after(&text, "colour images: of ");
            assert!(evidence >= 5.0, "{text}");
            assert!(
                text.contains(", 0 register to the robot's motion"),
                "{text}"
            );
        }
    }
}

/// Sets robot1's `depth_unit_m` in the copy's manifest.
fn set_unit(dir: &std::path::Path, unit: f64) {
    let manifest = dir.join("dataset.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&manifest).unwrap()).unwrap();
    v["robots"][0]["depth_unit_m"] = serde_json::json!(unit);
    std::fs::write(&manifest, serde_json::to_string_pretty(&v).unwrap()).unwrap();
}

/// The number after `prefix` in `text`.
fn number_after(text: &str, prefix: &str) -> f64 {
    let at = text
        .find(prefix)
        .unwrap_or_else(|| panic!("no '{prefix}' in: {text}"))
        + prefix.len();
    let digits: String = text[at..]
        .chars()
        .take_while(|c| c.is_ascii_digit() || *c == '.')
        .collect();
    digits
        .parse()
        .unwrap_or_else(|_| panic!("no number after '{prefix}' in: {text}"))
}

/// robot1's depth read at another scale (`depth_unit_m` off by 5% either way,
/// or ten times): refused, with the scale measured against the robot's motion
/// (within 1%) and the unit that fits it.
#[test]
fn depth_at_another_scale_is_refused_with_its_scale() {
    for scale in [1.05, 0.95, 10.0] {
        let (_tmp, dir) = copy();
        set_unit(&dir, 0.001 * scale);
        let text = match run(&dir) {
            Ok(r) => {
                show(&format!("scale {scale}"), &r);
                panic!("{scale}: a result, m² {:.0}", m2(&r.result));
            }
            Err(text) => text,
        };
        eprintln!("{scale}: {text}");
        let measured = number_after(&text, "robot1's depth measures ");
        assert!(
            (measured / scale - 1.0).abs() < 0.01,
            "{scale}: measured {measured}: {text}"
        );
        // docs/verdict.md: 1.050 ± 0.0021.
        let sigma = number_after(&text, " ± ") / scale;
        assert!(sigma > 0.0014 && sigma < 0.0031, "{scale}: {text}");
        let fits = number_after(&text, "the motion fits ");
        assert!((fits / 0.001 - 1.0).abs() < 0.01, "{scale}: {text}");
        assert!(text.contains("dataset.json gives depth_unit_m"), "{text}");
    }
}

/// A unit slip that puts the scene outside the working range (a tenth, a
/// thousand times): nothing lifts; refused with the depth the images give.
#[test]
fn depth_outside_the_working_range_is_refused_with_its_unit() {
    // docs/verdict.md: 0.049 m at a tenth.
    for (scale, median_m) in [(0.1, 0.049), (1000.0, 490.0)] {
        let (_tmp, dir) = copy();
        set_unit(&dir, 0.001 * scale);
        let text = run(&dir).map(|_| ()).unwrap_err();
        eprintln!("{scale}: {text}");
        assert!(
            text.contains("robot1's depth images give a median depth of"),
            "{text}"
        );
        let measured = number_after(&text, "a median depth of ");
        assert!(
            measured > median_m / 1.5 && measured < median_m * 1.5,
            "{scale}: {measured} m: {text}"
        );
        assert!(text.contains("Its depth unit is wrong?"), "{text}");
    }
}

/// robot1's depth at a scale off by less than a refusal needs (0.5%, 1%):
/// measured within 0.2%, named in a finding that informs, and held by the
/// result's covariance (the truth's m² at most 22.5; without the widening it
/// was 42 at 0.5%, and holding only the deviation's excess over 2σ left it there).
#[test]
fn a_small_depth_scale_widens_the_covariance() {
    for scale in [1.005, 1.01, 0.99] {
        let (_tmp, dir) = copy();
        set_unit(&dir, 0.001 * scale);
        let r = run(&dir).unwrap_or_else(|e| panic!("{scale}: {e}"));
        let m2 = m2(&r.result);
        eprintln!(
            "{scale}: m² {m2:.1}, predicted p95 {:.2} mm, {:#?}",
            r.result.predicted_touch_error_m.p95 * 1e3,
            r.result.findings
        );
        let s = r.depth_checks[0].scale.unwrap();
        assert!((s.scale - scale).abs() < 0.002, "{scale}: {s:?}");
        let named: Vec<_> = r
            .result
            .findings
            .iter()
            .filter(|f| f.kind == kind::DEPTH_SCALE)
            .collect();
        assert_eq!(named.len(), 1, "{scale}: {named:#?}");
        assert_eq!(named[0].robot.as_deref(), Some("robot1"));
        assert!(!named[0].fails);
        assert!(
            named[0]
                .message
                .contains("the result's covariance holds a depth scale error of"),
            "{}",
            named[0].message
        );
        assert!(m2 <= 22.5, "{scale}: m² {m2}");
    }
}

/// One of robot1's depth images is robot2's (row 3's, then row 5's): that
/// view is left out by name, the others calibrate, and the truth stays within
/// the result's covariance.
#[test]
fn one_view_with_another_cameras_depth_is_left_out_by_name() {
    for (name, row) in [("002.png", 3), ("004.png", 5)] {
        let (_tmp, dir) = copy();
        std::fs::copy(
            dir.join("robot2/depth").join(name),
            dir.join("robot1/depth").join(name),
        )
        .unwrap();
        let r = run(&dir).unwrap_or_else(|e| panic!("{name}: {e}"));
        let m2 = m2(&r.result);
        let named: Vec<_> = r
            .result
            .captures
            .rejected
            .iter()
            .filter(|c| {
                c.reason
                    .contains("its depth does not match its colour image")
            })
            .collect();
        eprintln!("{name}: m² {m2:.1}, {named:#?}");
        assert_eq!(named.len(), 1, "{name}: {:#?}", r.result.captures.rejected);
        assert_eq!(named[0].robot, "robot1");
        assert_eq!(named[0].row, Some(row));
        assert!(m2 <= 22.5, "{name}: m² {m2}");
    }
}
