//! Render time per frame: a 1280x720 view of a 9x6 checkerboard on a table, with
//! defocus, vignetting and sensor noise (the full path of one simulated capture).
//! `cargo bench -p b2b-sim --bench render` for numbers; `cargo test --benches` runs
//! each once as a smoke test.

use std::hint::black_box;

use b2b_calib::camera::CameraModel;
use b2b_sim::Iso3;
use b2b_sim::render::{Lighting, Optics, RenderSettings, Renderer, SceneGeometry};
use b2b_sim::sensor::{SensorNoise, expose};
use b2b_sim::texture::{Checkerboard, Uniform};
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;

fn bench(c: &mut Criterion) {
    let camera = CameraModel::new(
        1280,
        720,
        [910.0, 910.0, 640.0, 360.0],
        &[0.08, -0.15, 0.001, -0.002, 0.05],
    )
    .expect("camera");
    let mut scene = SceneGeometry::default();
    scene.add_checkerboard(
        Iso3::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        ),
        Checkerboard::new([9, 6], 0.025, 0.015),
    );
    scene.add_quad(
        Iso3::translation(0.0, 0.0, -0.001),
        [-1.0, -1.0],
        [1.0, 1.0],
        std::sync::Arc::new(Uniform(0.3)),
    );
    // Looking down at the board from 0.45 m, slightly tilted.
    let world_from_camera = Iso3::from_parts(
        Translation3::new(0.1, 0.06, 0.45),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI - 0.2),
    );
    let camera_from_world = world_from_camera.inverse();
    let renderer = Renderer::new(&camera).expect("renderer");
    let settings = RenderSettings {
        lighting: Lighting::uniform(243.0),
        optics: Optics::realsense(),
        ..RenderSettings::ideal()
    };
    c.bench_function("render_1280x720_board", |b| {
        let mut rng = b2b_sim::Rng::seed_from_u64(1);
        b.iter(|| {
            let irr = renderer.render(black_box(&camera_from_world), &scene, &settings);
            expose(&irr, &SensorNoise::default(), &mut rng)
        })
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench
}
criterion_main!(benches);
