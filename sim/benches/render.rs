//! Render time per frame: a 1280x720 view of a 9x6 checkerboard on a table, with
//! defocus, vignetting and sensor noise (the full path of one simulated capture); the
//! same view of a ChArUco board; and a randomly textured scene with its depth image.
//! `cargo bench -p b2b-sim --bench render` for numbers; `cargo test --benches` runs
//! each once as a smoke test.

use std::hint::black_box;

use b2b_calib::camera::CameraModel;
use b2b_sim::Iso3;
use b2b_sim::render::{Lighting, Optics, RenderSettings, Renderer, SceneGeometry};
use b2b_sim::scene::SceneTarget;
use b2b_sim::sensor::{DepthModel, SensorNoise, expose};
use b2b_sim::target::TargetModel;
use b2b_sim::texture::{Checkerboard, NoiseTexture, Texture, Uniform};
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

    // The same view of a 7x5 ChArUco board (40 mm squares): many more edges.
    let charuco: SceneTarget = serde_json::from_str(
        r#"{"kind": "charuco", "squares": [7, 5], "square_m": 0.04, "marker_m": 0.028,
            "dictionary": "DICT_5X5_100", "base1_from_target": {"t": [0, 0, 0]}}"#,
    )
    .expect("spec");
    let target = TargetModel::build(&charuco).expect("target");
    let mut scene = SceneGeometry::default();
    let world_from_target = Iso3::from_parts(
        Translation3::new(-0.04, -0.04, 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
    );
    for q in &target.quads {
        scene.add_quad(
            world_from_target * q.target_from_quad,
            q.min,
            q.max,
            q.texture.clone(),
        );
    }
    scene.add_quad(
        Iso3::translation(0.0, 0.0, -0.001),
        [-1.0, -1.0],
        [1.0, 1.0],
        std::sync::Arc::new(Uniform(0.3)),
    );
    c.bench_function("render_1280x720_charuco", |b| {
        let mut rng = b2b_sim::Rng::seed_from_u64(1);
        b.iter(|| {
            let irr = renderer.render(black_box(&camera_from_world), &scene, &settings);
            expose(&irr, &SensorNoise::default(), &mut rng)
        })
    });

    // The RGB-D path: a randomly textured table (every pixel supersampled) with two
    // textured boxes, and the depth image.
    let mut scene = SceneGeometry::default();
    scene.add_quad(
        Iso3::translation(0.0, 0.0, -0.001),
        [-1.0, -1.0],
        [1.0, 1.0],
        std::sync::Arc::new(noise(11)),
    );
    for (k, (x, y)) in [(0.05, 0.1), (0.2, -0.05)].into_iter().enumerate() {
        scene.add_box(
            Iso3::translation(x, y, 0.05),
            [0.12, 0.09, 0.1],
            std::array::from_fn(|f| {
                std::sync::Arc::new(noise(7 * k as u64 + f as u64)) as std::sync::Arc<dyn Texture>
            }),
        );
    }
    let depth = DepthModel::default();
    c.bench_function("render_1280x720_textured_with_depth", |b| {
        let mut rng = b2b_sim::Rng::seed_from_u64(1);
        b.iter(|| {
            let irr = renderer.render(black_box(&camera_from_world), &scene, &settings);
            (
                expose(&irr, &SensorNoise::default(), &mut rng),
                depth.measure(&irr, &mut rng),
            )
        })
    });
}

fn noise(seed: u64) -> NoiseTexture {
    NoiseTexture {
        seed,
        scale_m: 0.04,
        octaves: 4,
        mean: 0.5,
        contrast: 0.35,
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench
}
criterion_main!(benches);
