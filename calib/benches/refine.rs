//! The joint refinements on realistic problem sizes.
//!
//! Goal: the whole solve over 2 x 30 captures x 54 corners in <= 50 ms
//! (`default_estimator_2x30x54`: closed-form seeds with the gross-row screen,
//! the refinement with its noise model, and the split-half check), three
//! robots in one problem in <= 100 ms (`default_estimator_3x30x54`); with both
//! cameras' intrinsics refined too, at most 200 ms more. The pipeline's
//! initial `calibrateCamera` fits add ~40 ms per robot
//! (`pipeline/tests/intrinsics.rs`). Run `cargo bench -p b2b-calib --bench
//! refine` for numbers (README); `cargo test --benches` runs each once as a
//! smoke test.
//!
//! `robots/N`: the default estimator on N robots of 27 captures each about
//! one board (`synth::robots_around`): its time grows linearly with N (each
//! capture adds a block of the normal equations over its own unknowns; each
//! leave-one-out step is a low-rank update).

use b2b_calib::base_to_base::{BaseToBaseInitial, perturb_initial, refine_base_to_base};
use b2b_calib::estimate::{RobotCaptures, estimate_base_to_base, estimate_bases};
use b2b_calib::pose::perturb_left;
use b2b_calib::refine::{RefineOptions, refine_hand_eye};
use b2b_calib::synth::{SynthConfig, random_robot, robots_around, three_robots, two_robots};
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::Vector6;
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let cfg = SynthConfig::default();
    let robot = random_robot(1, &cfg).expect("synthetic problem");
    let caps = robot.board_captures();
    let d = Vector6::new(0.01, -0.01, 0.02, 0.005, 0.01, -0.005);
    let start = (
        perturb_left(&d, &robot.flange_from_camera),
        perturb_left(&d, &robot.base_from_target),
    );
    let opts = RefineOptions::default();
    c.bench_function("hand_eye_refine_30x54", |b| {
        b.iter(|| {
            refine_hand_eye(black_box(&cfg.camera), black_box(&caps), start, &opts)
                .expect("converges")
        })
    });

    let two = two_robots(2, &cfg).expect("synthetic problem");
    let c1 = two.robots[0].board_captures();
    let c2 = two.robots[1].board_captures();
    let initial = perturb_initial(
        &BaseToBaseInitial {
            flange_from_camera: [
                two.robots[0].flange_from_camera,
                two.robots[1].flange_from_camera,
            ],
            base1_from_target: two.robots[0].base_from_target,
            base1_from_base2: two.base1_from_base2,
        },
        &d,
    );
    c.bench_function("base_to_base_refine_2x30x54", |b| {
        b.iter(|| {
            refine_base_to_base(
                [&cfg.camera, &cfg.camera],
                [&c1, &c2],
                black_box(&initial),
                &opts,
            )
            .expect("converges")
        })
    });

    // The whole default estimator, as the pipeline runs it.
    let robots = [0, 1].map(|r| RobotCaptures {
        camera: &cfg.camera,
        captures: if r == 0 { &c1 } else { &c2 },
        camera_from_target: &two.robots[r].camera_from_target,
    });
    c.bench_function("default_estimator_2x30x54", |b| {
        b.iter(|| {
            estimate_base_to_base([black_box(&robots[0]), &robots[1]], &opts).expect("converges")
        })
    });

    // Three robots in one problem (issue: <= 100 ms for 3 x 30 captures),
    // the whole default estimator with its split-half checks.
    let three = three_robots(2, &cfg).expect("synthetic problem");
    let caps3: Vec<_> = three.robots.iter().map(|r| r.board_captures()).collect();
    let robots3: Vec<RobotCaptures<'_>> = three
        .robots
        .iter()
        .zip(&caps3)
        .map(|(r, caps)| RobotCaptures {
            camera: &cfg.camera,
            captures: caps,
            camera_from_target: &r.camera_from_target,
        })
        .collect();
    let refs3: Vec<&RobotCaptures<'_>> = robots3.iter().collect();
    c.bench_function("default_estimator_3x30x54", |b| {
        b.iter(|| estimate_bases(black_box(&refs3), &opts).expect("converges"))
    });

    // The default estimator as the robots grow, 27 captures each.
    let mut group = c.benchmark_group("robots");
    group.sample_size(10);
    for n in [2, 4, 8, 12] {
        let cfg27 = SynthConfig {
            captures: 27,
            ..SynthConfig::default()
        };
        let many = robots_around(n, 1, &cfg27).expect("synthetic problem");
        let caps: Vec<_> = many.robots.iter().map(|r| r.board_captures()).collect();
        let robots: Vec<RobotCaptures<'_>> = many
            .robots
            .iter()
            .zip(&caps)
            .map(|(r, c)| RobotCaptures {
                camera: &cfg27.camera,
                captures: c,
                camera_from_target: &r.camera_from_target,
            })
            .collect();
        let refs: Vec<&RobotCaptures<'_>> = robots.iter().collect();
        group.bench_function(format!("{n}x27x54"), |b| {
            b.iter(|| estimate_bases(black_box(&refs), &opts).expect("converges"))
        });
    }
    group.finish();

    // The same problem with both cameras' nine intrinsics refined jointly, from
    // cameras 1 % off in focal length and 2 px off in the principal point (what
    // the pipeline does when a dataset gives no intrinsics, after its initial
    // fit, or with --refine-intrinsics).
    let mut wrong = [cfg.camera.clone(), cfg.camera.clone()];
    for (k, c) in wrong.iter_mut().enumerate() {
        let s = if k == 0 { 1.0 } else { -1.0 };
        c.fx *= 1.0 + 0.01 * s;
        c.fy *= 1.0 + 0.01 * s;
        c.cx += 2.0 * s;
        c.cy -= 2.0 * s;
    }
    let with_intrinsics = RefineOptions {
        refine_intrinsics: true,
        ..RefineOptions::default()
    };
    c.bench_function("base_to_base_refine_2x30x54_intrinsics", |b| {
        b.iter(|| {
            refine_base_to_base(
                [&wrong[0], &wrong[1]],
                [&c1, &c2],
                black_box(&initial),
                &with_intrinsics,
            )
            .expect("converges")
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
