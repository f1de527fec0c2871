//! Viewpoint planning, what the automatic routine spends before its arm moves: one
//! plan of 30 viewpoints (candidates on a cap about the target's view axis, nominal
//! IK for each, the safety guard, farthest-point thinning, every leg checked) for the
//! committed checkerboard scene's iiwa 7, from the setup an agent derives from it
//! (`b2b-sim-cart setup --scene datasets/sim-checkerboard-2x12/scene.json --robot
//! robot1`, kept in `benches/fixtures/` so the bench needs no other binary).
//! The routine plans twice (at the start, and around where the first good view put
//! the board), so the figure per capture is two plans over 30 captures. Goal: at most
//! 50 ms per capture, amortised.
//!
//! `cargo bench -p b2b-services --bench plan`; `cargo test --benches` runs it once.

use std::hint::black_box;
use std::path::Path;

use b2b_calib::camera::CameraModel;
use b2b_robot::Arm;
use b2b_routine::plan::{PlanConfig, PlanScene, plan_viewpoints};
use b2b_services::setup::CellSetup;
use criterion::{Criterion, criterion_group, criterion_main};

fn bench(c: &mut Criterion) {
    let setup = CellSetup::load(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/fixtures/setup-robot1.json"),
    )
    .unwrap();
    let target = setup.read_target().unwrap();
    let points = target.all_points();
    let arm = Arm::new(setup.model);
    let guard = setup.guard().unwrap();
    let camera = CameraModel::new(640, 480, [615.2, 614.8, 321.4, 238.7], &[]).unwrap();
    let scene = PlanScene {
        arm: &arm,
        envelope: guard.envelope(),
        camera: &camera,
        base_from_target: setup
            .base_from_target_approx
            .to_isometry("T_base_target_approx")
            .unwrap(),
        flange_from_camera: setup
            .flange_from_camera_approx
            .to_isometry("T_flange_camera_approx")
            .unwrap(),
        target_points: &points,
        view_axis: target.view_axis(),
    };
    let cfg = PlanConfig {
        count: 30,
        ..PlanConfig::default()
    };
    let start = Arm::comfortable();
    let plan = plan_viewpoints(&scene, &start, &cfg).unwrap();
    assert!(
        plan.viewpoints.len() >= 28,
        "{} viewpoints",
        plan.viewpoints.len()
    );
    let mut group = c.benchmark_group("plan_30_viewpoints_iiwa7");
    group.sample_size(10);
    group.bench_function(
        "plan_viewpoints (one plan; per capture: 2 plans / 30)",
        |b| b.iter(|| plan_viewpoints(black_box(&scene), &start, &cfg).unwrap()),
    );
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
