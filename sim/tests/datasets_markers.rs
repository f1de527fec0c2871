//! The committed marker-target datasets (ChArUco, ArUco grid, single marker, planar and
//! three-face multimarker) regenerate byte for byte and load with the validator; see
//! `datasets.rs` for the others and the size budget.

mod common;

use b2b_dataset::Target;
use common::regenerate;

#[test]
fn charuco_set_regenerates() {
    let ds = regenerate("sim-charuco-occluded-2x10");
    assert!(matches!(ds.manifest.target, Target::Charuco { .. }));
    assert!(ds.robots.iter().all(|r| r.captures.len() >= 10));
}

#[test]
fn aruco_grid_set_regenerates() {
    let ds = regenerate("sim-aruco-grid-2x5");
    assert!(matches!(ds.manifest.target, Target::ArucoGrid { .. }));
}

/// The multimarker file the manifest names exists, parses as ARToolKit's format
/// (N, then 5 lines per marker) and holds `n` markers of `width_mm`.
fn check_multimarker(ds: &b2b_dataset::Dataset, n: usize, width_mm: f64) {
    let path = ds.multimarker_config_path().unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let lines: Vec<&str> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .collect();
    assert_eq!(lines[0].parse::<usize>().unwrap(), n);
    assert_eq!(lines.len(), 1 + 5 * n);
    for m in 0..n {
        let l = &lines[1 + 5 * m..6 + 5 * m];
        l[0].parse::<u64>().unwrap();
        assert_eq!(l[1].parse::<f64>().unwrap(), width_mm);
        for row in &l[2..] {
            assert_eq!(row.split_whitespace().count(), 4, "{row}");
        }
    }
}

#[test]
fn single_marker_set_regenerates() {
    let ds = regenerate("sim-single-marker-2x5");
    assert!(matches!(ds.manifest.target, Target::Multimarker { .. }));
    check_multimarker(&ds, 1, 100.0);
}

#[test]
fn planar_multimarker_set_regenerates() {
    let ds = regenerate("sim-multimarker-4x3-2x10");
    check_multimarker(&ds, 12, 40.0);
    assert!(ds.robots.iter().all(|r| r.captures.len() >= 10));
}

#[test]
fn corner_multimarker_set_regenerates() {
    let ds = regenerate("sim-multimarker-corner-2x10");
    check_multimarker(&ds, 12, 40.0);
    assert!(ds.robots.iter().all(|r| r.captures.len() >= 10));
}
