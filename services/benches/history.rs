//! The coordinator's history, measured on a database of 10,000 results of three
//! robots each (30,000 hand-eyes, each with its covariance):
//!
//! 1. `history --robot robot2`: open the file and list that robot's results and
//!    hand-eyes (all 10,000 of each). Goal: at most 50 ms.
//! 2. the same without `--robot` (every result, all 30,000 hand-eyes).
//! 3. the mount check every calibration runs before writing its result: open the
//!    file and compare three new hand-eyes with each robot's latest one.
//!
//! `cargo bench -p b2b-services --bench history`; under `cargo test --benches` a
//! smoke pass fills 300 results and runs each measurement once.

use std::hint::black_box;
use std::path::Path;
use std::time::Instant;

use b2b_protocol::{CalibrationResult, Pose};
use b2b_services::history::{self, History, Record};
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Isometry3, Vector3};

const ROBOTS: [&str; 3] = ["robot1", "robot2", "robot3"];

/// The report's fixture result with three robots' hand-eyes and covariances,
/// the hand-eyes varied by `i` (tenths of a millimetre).
fn result(i: usize) -> CalibrationResult {
    let text = include_str!("../../report/tests/fixtures/RESULT.json");
    let mut r: CalibrationResult = serde_json::from_str(text).unwrap();
    let mut c = [[0.0; 6]; 6];
    for (k, row) in c.iter_mut().enumerate() {
        // About 0.01 deg and 0.1 mm, 1 sigma.
        row[k] = if k < 3 { 3e-8 } else { 1e-8 };
    }
    for (k, robot) in ROBOTS.iter().enumerate() {
        let x = Isometry3::new(
            Vector3::new(0.05 + 1e-4 * (i % 7) as f64, -0.02, 0.1 + 0.01 * k as f64),
            Vector3::new(0.1, 0.2, -0.3),
        );
        r.hand_eye.insert((*robot).into(), Pose::from_isometry(&x));
        r.hand_eye_covariance.insert((*robot).into(), c);
        r.captures.used.insert((*robot).into(), 30);
    }
    r
}

fn fill(db: &Path, n: usize) {
    let robots: Vec<String> = ROBOTS.iter().map(|r| (*r).to_owned()).collect();
    let results: Vec<CalibrationResult> = (0..7).map(result).collect();
    let mut h = History::open(db).unwrap();
    let start = Instant::now();
    for i in 0..n {
        h.record(&Record {
            recorded_at_unix_ms: 1_700_000_000_000 + 3_600_000 * i as i64,
            command: "calibrate",
            result: &results[i % 7],
            result_file: Path::new("/var/lib/b2b/results/RESULT.json"),
            robots: &robots,
        })
        .unwrap();
    }
    println!(
        "filled {n} results ({} hand-eyes), one transaction each: {:.2} s",
        3 * n,
        start.elapsed().as_secs_f64()
    );
}

fn bench(c: &mut Criterion) {
    let full = std::env::args().any(|a| a == "--bench");
    let n = if full { 10_000 } else { 300 };
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join(history::DB_FILE);
    fill(&db, n);
    let list = |robot: Option<&str>| {
        let h = History::open_existing(&db).unwrap().unwrap();
        h.list(robot).unwrap()
    };
    let listing = list(Some("robot2"));
    assert_eq!(listing.results.len(), n);
    assert_eq!(listing.hand_eyes["robot2"].len(), n);
    let new = result(3);
    assert!(history::mount_warnings(&db, &new).unwrap().is_empty());

    let mut group = c.benchmark_group(format!("history_{n}_results_3_robots"));
    group.sample_size(20);
    group.bench_function("history --robot robot2 (open + list)", |b| {
        b.iter(|| list(black_box(Some("robot2"))))
    });
    group.bench_function("history (open + list everything)", |b| {
        b.iter(|| list(black_box(None)))
    });
    group.bench_function("mount check of 3 hand-eyes (open + 3 queries)", |b| {
        b.iter(|| history::mount_warnings(&db, black_box(&new)).unwrap())
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
