//! The drift watch's decision per observation (`coordinator watch`): goal
//! <= 1 ms. `drift_update_armed` is one innovation through an armed pair's
//! CUSUM; `drift_innovation_and_update` adds putting both observations in the
//! reference base, as the coordinator does for each. Run `cargo bench -p
//! b2b-calib --bench drift` (README); `cargo test --benches` runs each once.

use b2b_calib::Iso3;
use b2b_calib::drift::{DriftOptions, PairWatch, innovation};
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Matrix6, Point3, Vector3, Vector6};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let cov = Matrix6::identity() * 1e-8;
    let centre = Point3::new(0.5, 0.0, 0.0);
    let mut armed = PairWatch::new(DriftOptions::default(), &cov, &centre);
    for k in 0..DriftOptions::default().baseline {
        let e = (k as f64 * 0.37).sin() * 1e-5;
        armed.update(&Vector6::new(e, -e, e, 2.0 * e, e, -e));
    }
    assert!(armed.armed());
    let d = Vector6::new(1e-5, 0.0, -1e-5, 2e-5, 1e-5, 0.0);
    c.bench_function("drift_update_armed", |b| {
        let mut w = armed.clone();
        b.iter(|| w.update(black_box(&d)))
    });
    let ref_from_base = Iso3::new(Vector3::new(1.0, 0.05, 0.0), Vector3::new(0.0, 0.0, 3.1));
    let base_from_flange = Iso3::new(Vector3::new(0.5, 0.1, 0.4), Vector3::new(3.0, 0.1, 0.0));
    let flange_from_camera = Iso3::new(Vector3::new(0.0, 0.06, 0.04), Vector3::zeros());
    let camera_from_target = Iso3::new(Vector3::new(0.0, 0.0, 0.5), Vector3::new(0.1, 0.0, 0.0));
    let reference = base_from_flange * flange_from_camera * camera_from_target;
    let board = Point3::new(0.1, 0.06, 0.0);
    c.bench_function("drift_innovation_and_update", |b| {
        let mut w = armed.clone();
        b.iter(|| {
            let t = black_box(ref_from_base)
                * base_from_flange
                * flange_from_camera
                * camera_from_target;
            let d = innovation(&t, &reference, &board);
            w.update(&d)
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
