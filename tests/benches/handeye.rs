//! Our closed-form solvers against OpenCV's on the same 30 noisy captures.
//!
//! One criterion group per method (`handeye/<method>`, `robot_world/<method>`),
//! each with `ours` and `opencv` measured in the same run. Both sides start from
//! their native inputs, converted beforehand: `&[Iso3]` for ours, `Vector<Mat>`
//! for OpenCV. "ours" includes the degeneracy checks every solver runs first;
//! "opencv" includes OpenCV's own input conversion (R or Rodrigues → 4x4).
//!
//! `cargo bench -p b2b-tests --bench handeye` measures. `cargo test -p b2b-tests
//! --benches` runs each function once (criterion's test mode) as a smoke test.

use std::hint::black_box;
use std::time::Duration;

use b2b_calib::handeye::{HandEyeMethod, RobotWorldMethod, hand_eye, robot_world};
use b2b_tests::cv::{HandEyeInputs, RobotWorldInputs};
use b2b_tests::data::noisy_robot;
use criterion::{Criterion, criterion_group, criterion_main};

fn bench_hand_eye(c: &mut Criterion) {
    let r = noisy_robot(1);
    let (bf, ct) = (&r.base_from_flange, &r.camera_from_target);
    let cv_in = HandEyeInputs::new(bf, ct).expect("OpenCV inputs");
    for m in HandEyeMethod::ALL {
        let mut g = c.benchmark_group(format!("handeye/{m}"));
        g.bench_function("ours", |b| {
            b.iter(|| hand_eye(black_box(bf), black_box(ct), m).unwrap())
        });
        g.bench_function("opencv", |b| {
            b.iter(|| black_box(&cv_in).calibrate(m).unwrap())
        });
        g.finish();
    }
}

fn bench_robot_world(c: &mut Criterion) {
    let r = noisy_robot(1);
    let (bf, ct) = (&r.base_from_flange, &r.camera_from_target);
    let cv_in = RobotWorldInputs::new(bf, ct).expect("OpenCV inputs");
    for m in RobotWorldMethod::ALL {
        let mut g = c.benchmark_group(format!("robot_world/{m}"));
        g.bench_function("ours", |b| {
            b.iter(|| robot_world(black_box(bf), black_box(ct), m).unwrap())
        });
        g.bench_function("opencv", |b| {
            b.iter(|| black_box(&cv_in).calibrate(m).unwrap())
        });
        g.finish();
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2));
    targets = bench_hand_eye, bench_robot_world
}
criterion_main!(benches);
