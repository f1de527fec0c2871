//! `sim generate`: a scene file and a seed in, a `b2b-dataset/1` folder out.
//!
//! For each robot: draw its true kinematics from its error model; plan viewpoints by
//! looking at the target from random points of a spherical cap around its viewing axis
//! (the printed side of a board, the open side of the three-face corner; distance,
//! tilt, azimuth, roll and aim jitter drawn per viewpoint); solve the IK of the
//! *nominal* model for the flange pose that puts the camera there (as the controller
//! would), inside the joint limits; let the robot settle (encoder noise,
//! repeatability); keep the viewpoint only if every key point of the target (inner
//! corners, marker corners) is inside the image as the *true* camera sees it and seen
//! less than 80° off its face's normal; render from the true camera pose (once per
//! lighting level with `lux_per_viewpoint`); write the *reported* flange pose. A
//! multimarker target's ARToolKit file is written next to `dataset.json`. Touch pairs: for each point of the shared workspace, both
//! robots bring a pointer's tip onto it (IK of the true model: the tip physically
//! touches the point) and the reported tips carry the robots' errors plus tip noise.
//! With N >= 3 robots every pair `a < b` gets its own touches: the first two robots'
//! in `touch_points.csv`, the others' in `touch_points_<a>_<b>.csv`; each robot's base
//! is `T_base1_base<n>` in `ground_truth.json`.
//!
//! Determinism: one ChaCha8 generator per purpose (robot realisation, planning,
//! rendering noise, touches), all seeded from `--seed` by stream number, so the output
//! is a pure function of the scene file and the seed. Streams are numbered by robot
//! (touches: by pair, `(0, 1)` first), so adding a robot leaves the first two robots'
//! files unchanged.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use b2b_dataset::{
    Capture, Dataset, GroundTruth, Intrinsics, Manifest, RobotData, RobotManifest, TouchPair,
};
use b2b_robot::{Arm, IkOptions};
use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng as _, SeedableRng};

use crate::render::{RenderSettings, Renderer, SceneGeometry};
use crate::robot_error::RobotInstance;
use crate::scene::Scene;
use crate::sensor::{expose, expose_rgb};
use crate::target::TargetModel;
use crate::texture::{NoiseTexture, Texture, Uniform};
use crate::{Iso3, Rng, SimError, image_io};

/// A generator stream: `purpose`, `robot` and `index` select independent sequences.
fn stream(seed: u64, purpose: u64, robot: usize, index: usize) -> Rng {
    let mut rng = Rng::seed_from_u64(seed);
    rng.set_stream((purpose << 48) | ((robot as u64) << 32) | index as u64);
    rng
}

/// What to produce.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct GenerateOptions {
    /// Render only these capture indices (0-based, per robot); `None` renders all.
    /// Everything else (poses, CSV, JSON, the other captures' randomness) is unchanged,
    /// because every capture draws its noise from its own stream: this is how the
    /// regeneration test checks a committed dataset without rendering all of it.
    pub render_only: Option<Vec<usize>>,
}

pub use b2b_calib::pose::look_at;

/// What `generate` made, besides the files.
#[derive(Debug, Clone)]
pub struct Summary {
    /// Robot ids, in the scene's order (that of the other per-robot fields).
    pub robots: Vec<String>,
    pub captures: Vec<usize>,
    /// Touch pairs of the first two robots (`touch_points.csv`).
    pub touches: usize,
    /// Touch pairs of every further pair of robots `(a, b)`, `a` before `b` in the
    /// scene (`touch_points_<a>_<b>.csv`), in the order they were drawn.
    pub pair_touches: Vec<((String, String), usize)>,
    /// Planning attempts per robot.
    pub attempts: Vec<usize>,
}

/// Builds the static scene geometry (target, table, boxes) in `base1`; also returns the
/// target model and `T_base1_target`.
pub fn scene_geometry(
    scene: &Scene,
    file: &Path,
) -> Result<(SceneGeometry, TargetModel, Iso3), SimError> {
    build_geometry(scene, file, true)
}

/// The scene's geometry once the target is taken away (table and boxes).
pub fn scene_geometry_without_target(
    scene: &Scene,
    file: &Path,
) -> Result<SceneGeometry, SimError> {
    build_geometry(scene, file, false).map(|(geo, _, _)| geo)
}

fn build_geometry(
    scene: &Scene,
    file: &Path,
    with_target: bool,
) -> Result<(SceneGeometry, TargetModel, Iso3), SimError> {
    let (target, base1_from_target) = scene.target_model(file)?;
    let mut geo = SceneGeometry::default();
    for q in target.quads.iter().filter(|_| with_target) {
        geo.add_quad(
            base1_from_target * q.target_from_quad,
            q.min,
            q.max,
            q.texture.clone(),
        );
    }
    if let Some(z) = scene.table_z_m {
        let texture: Arc<dyn Texture> = match scene.table_texture_seed {
            Some(seed) => Arc::new(NoiseTexture {
                seed,
                scale_m: 0.06,
                octaves: 4,
                mean: 0.45,
                contrast: 0.3,
            }),
            None => Arc::new(Uniform(0.3)),
        };
        geo.add_quad(
            Iso3::translation(0.5, 0.0, z),
            [-1.5, -1.5],
            [1.5, 1.5],
            texture,
        );
    }
    for (i, bx) in scene.boxes.iter().enumerate() {
        let pose = bx.pose.to_iso(file, &format!("boxes[{i}].pose"))?;
        let textures: [Arc<dyn Texture>; 6] = std::array::from_fn(|k| {
            Arc::new(NoiseTexture {
                seed: bx.texture_seed.wrapping_mul(7).wrapping_add(k as u64),
                scale_m: 0.04,
                octaves: 4,
                mean: 0.5,
                contrast: 0.35,
            }) as Arc<dyn Texture>
        });
        geo.add_box(pose, bx.size_m, textures);
    }
    Ok((geo, target, base1_from_target))
}

/// The largest angle between a target point's face normal and the direction to the
/// camera for the point to count as visible (beyond it the print is too foreshortened).
const MAX_INCIDENCE_DEG: f64 = 80.0;

/// Generates the dataset described by `scene_file` into `out`.
pub fn generate(scene_file: &Path, seed: u64, out: &Path) -> Result<Summary, SimError> {
    let scene = Scene::load(scene_file)?;
    generate_scene(&scene, scene_file, seed, out, &GenerateOptions::default())
}

/// One image to render and write: everything drawn for it while planning (its
/// noise stream positioned after the occluder's draws), so that images can be
/// rendered in any order, on any thread, and come out the same.
struct RenderJob {
    camera_from_world: Iso3,
    /// The scene with this capture's occluder, when it has one.
    occluded: Option<SceneGeometry>,
    settings: RenderSettings,
    noise: Rng,
    image: PathBuf,
    depth: Option<PathBuf>,
}

/// Renders and writes `jobs` on every core (each image is independent: its own
/// noise stream, its own files); the first error, if any.
fn render_jobs(
    renderer: &Renderer,
    geometry: &SceneGeometry,
    scene: &Scene,
    jobs: Vec<RenderJob>,
) -> Result<(), SimError> {
    let one = |mut job: RenderJob| -> Result<(), SimError> {
        let geo = job.occluded.as_ref().unwrap_or(geometry);
        let irradiance = renderer.render(&job.camera_from_world, geo, &job.settings);
        if scene.colour {
            let image = expose_rgb(&irradiance, &scene.noise, &mut job.noise);
            image_io::write_rgb(&job.image, &image)?;
        } else {
            let image = expose(&irradiance, &scene.noise, &mut job.noise);
            image_io::write_grey(&job.image, &image)?;
        }
        if let (Some(model), Some(file)) = (&scene.depth, &job.depth) {
            let d = model.measure(&irradiance, &mut job.noise);
            image_io::write_depth(file, &d)?;
        }
        Ok(())
    };
    let workers = std::thread::available_parallelism()
        .map_or(1, std::num::NonZeroUsize::get)
        .min(jobs.len().max(1));
    let queue = std::sync::Mutex::new(jobs.into_iter());
    std::thread::scope(|s| {
        let handles: Vec<_> = (0..workers)
            .map(|_| {
                s.spawn(|| -> Result<(), SimError> {
                    loop {
                        let next = queue.lock().unwrap_or_else(|e| e.into_inner()).next();
                        let Some(job) = next else { return Ok(()) };
                        one(job)?;
                    }
                })
            })
            .collect();
        handles.into_iter().try_for_each(|h| {
            h.join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
        })
    })
}

/// Generates from an already loaded scene; `scene_file` is used in messages and the
/// manifest's `source`.
pub fn generate_scene(
    scene: &Scene,
    scene_file: &Path,
    seed: u64,
    out: &Path,
    options: &GenerateOptions,
) -> Result<Summary, SimError> {
    scene.validate(scene_file)?;
    let (geometry, target, base1_from_target) = scene_geometry(scene, scene_file)?;
    let world_from_base = (0..scene.robots.len())
        .map(|r| scene.base1_from_base(r, scene_file))
        .collect::<Result<Vec<Iso3>, SimError>>()?;
    let mut truth = GroundTruth {
        base1_from_base2: Some(world_from_base[1]),
        // Robot n (1-based) is robots[n - 1].
        base1_from_base_n: (3..=world_from_base.len())
            .map(|n| (n, world_from_base[n - 1]))
            .collect(),
        ..GroundTruth::default()
    };
    let mut robots_manifest = vec![];
    let mut robots_data = vec![];
    let mut instances = vec![];
    let mut summary = Summary {
        robots: scene.robots.iter().map(|r| r.id.clone()).collect(),
        captures: vec![],
        touches: 0,
        pair_touches: vec![],
        attempts: vec![],
    };
    let centre_in_target = target.centre;
    // The viewing cone's axis and two directions across it (for a board seen from its
    // printed side, −z: x and y).
    let axis = target.view_axis;
    let helper = if axis.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let across1 = (helper - axis * axis.dot(&helper)).normalize();
    let across2 = across1.cross(&axis);
    let reps = if scene.lux_per_viewpoint {
        scene.lux_levels.len()
    } else {
        1
    };
    let max_incidence_cos = MAX_INCIDENCE_DEG.to_radians().cos();
    for (r, spec) in scene.robots.iter().enumerate() {
        let camera = scene.camera(r)?;
        let renderer = Renderer::new(&camera)?;
        let flange_from_camera = spec
            .flange_from_camera
            .to_iso(scene_file, &format!("robots[{r}].flange_from_camera"))?;
        let nominal = Arm::new(spec.model);
        let robot = spec.error.realise(&nominal, &mut stream(seed, 1, r, 0))?;
        let base_from_world = world_from_base[r].inverse();
        let base_from_target = base_from_world * base1_from_target;
        truth
            .flange_from_camera
            .insert(spec.id.clone(), flange_from_camera);
        truth
            .base_from_target
            .insert(spec.id.clone(), base_from_target);

        let mut plan = stream(seed, 2, r, 0);
        let v = &scene.viewpoints;
        let mut captures = vec![];
        let mut jobs = vec![];
        let mut attempts = 0;
        let max_attempts = v.count * 400;
        let up_in_target = base_from_target.inverse().rotation * Vector3::z();
        while captures.len() < v.count * reps {
            attempts += 1;
            if attempts > max_attempts {
                return Err(SimError::PlanningFailed {
                    what: format!("viewpoints of {} with the whole target in view", spec.id),
                    found: captures.len() / reps,
                    wanted: v.count,
                    attempts: max_attempts,
                });
            }
            let tilt = plan.random_range(0.0..=v.max_tilt_deg.to_radians());
            let azimuth = plan.random_range(0.0..std::f64::consts::TAU);
            let dist = plan.random_range(v.distance_m[0]..=v.distance_m[1]);
            let roll = plan.random_range(-1.0..=1.0) * v.max_roll_deg.to_radians();
            let jitter = Vector3::new(
                plan.random_range(-1.0..=1.0),
                plan.random_range(-1.0..=1.0),
                0.0,
            ) * v.look_jitter_m;
            let dir = across1 * (tilt.sin() * azimuth.cos())
                + across2 * (tilt.sin() * azimuth.sin())
                + axis * tilt.cos();
            let eye = centre_in_target + dir * dist;
            let target_from_camera =
                look_at(&eye, &(centre_in_target + jitter), &up_in_target, roll);
            let wanted_flange =
                base_from_target * target_from_camera * flange_from_camera.inverse();
            let Ok(q) =
                robot
                    .nominal
                    .ik(&wanted_flange, &Arm::comfortable(), &IkOptions::default())
            else {
                continue;
            };
            let state = robot.settle(&q, &mut plan);
            let base_from_camera = state.true_base_from_flange * flange_from_camera;
            let camera_from_target = base_from_camera.inverse() * base_from_target;
            let m = v.min_margin_px;
            let eye_in_target = camera_from_target.inverse() * Point3::origin();
            let all_in = target.key_points.iter().all(|(p, normal)| {
                let to_eye = eye_in_target - p;
                normal.dot(&to_eye) >= max_incidence_cos * to_eye.norm()
                    && camera.project(&(camera_from_target * p)).is_some_and(|uv| {
                        uv.x >= m
                            && uv.y >= m
                            && uv.x <= camera.width as f64 - 1.0 - m
                            && uv.y <= camera.height as f64 - 1.0 - m
                    })
            });
            if !all_in {
                continue;
            }
            for rep in 0..reps {
                let k = captures.len();
                let mut noise = stream(seed, 3, r, k);
                let rel_image = PathBuf::from(format!("images/{k:03}.png"));
                let rel_depth = scene
                    .depth
                    .map(|_| PathBuf::from(format!("depth/{k:03}.png")));
                let render = options
                    .render_only
                    .as_ref()
                    .is_none_or(|only| only.contains(&k));
                let camera_from_world = (world_from_base[r] * base_from_camera).inverse();
                let mut settings = scene.render_settings();
                if scene.lux_per_viewpoint {
                    settings.lighting.lux = scene.lux_levels[rep];
                } else if !scene.lux_levels.is_empty() {
                    settings.lighting.lux = scene.lux_levels[k % scene.lux_levels.len()];
                }
                settings.colour = scene.colour;
                let mut geo = SceneGeometry::default();
                if let Some(occ) = &scene.occluders
                    && noise.random_bool(occ.probability)
                {
                    // A rectangle 10-25 cm in front of the camera, somewhere in the view or
                    // on the line of sight to a point of the target.
                    let d = noise.random_range(0.1..0.25);
                    let size = noise.random_range(occ.size_m[0]..=occ.size_m[1]);
                    let length = noise.random_range(0.1..0.3);
                    let (x, y) = if occ.over_target {
                        let i = noise.random_range(0..target.key_points.len());
                        let p = camera_from_target * target.key_points[i].0;
                        (p.x / p.z * d, p.y / p.z * d)
                    } else {
                        (
                            noise.random_range(-0.3..0.3) * d,
                            noise.random_range(-0.2..0.2) * d,
                        )
                    };
                    let angle = noise.random_range(0.0..std::f64::consts::PI);
                    let camera_from_occluder = Iso3::from_parts(
                        Translation3::new(x, y, d),
                        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), angle),
                    );
                    geo = geometry.clone();
                    geo.add_quad(
                        camera_from_world.inverse() * camera_from_occluder,
                        [-length / 2.0, -size / 2.0],
                        [length / 2.0, size / 2.0],
                        Arc::new(Uniform(occ.reflectance)),
                    );
                }
                if render {
                    jobs.push(RenderJob {
                        camera_from_world,
                        occluded: (!geo.quads.is_empty()).then_some(geo),
                        settings,
                        noise,
                        image: out.join(&spec.id).join(&rel_image),
                        depth: rel_depth.as_ref().map(|rel| out.join(&spec.id).join(rel)),
                    });
                }
                captures.push(Capture {
                    row: k + 1,
                    image: Some(rel_image),
                    depth: rel_depth,
                    base_from_flange: state.reported_base_from_flange,
                    camera_from_target: None,
                    target: None,
                });
            }
        }
        render_jobs(&renderer, &geometry, scene, jobs)?;
        summary.captures.push(captures.len());
        summary.attempts.push(attempts);
        // What the camera says about itself, which is what a dataset records.
        let c = spec.reported_camera.as_ref().unwrap_or(&spec.camera);
        robots_manifest.push(RobotManifest {
            id: spec.id.clone(),
            camera: spec.reports_intrinsics.then(|| Intrinsics {
                dist: if c.dist.len() >= 4 {
                    c.dist.clone()
                } else {
                    vec![0.0; 5]
                },
                ..c.clone()
            }),
            depth_unit_m: scene.depth.map(|d| d.unit_m),
        });
        robots_data.push(RobotData {
            id: spec.id.clone(),
            captures,
        });
        instances.push(robot);
    }

    let mut touch_points = None;
    let mut pair_touch_points = BTreeMap::new();
    if let Some(spec) = &scene.touch_points {
        // Pair index p in the touch stream's robot field: (0, 1) is p = 0, the stream
        // of two-robot scenes; the others follow in order (0, 2), ..., (1, 2), ...
        let n = scene.robots.len();
        let pairs = (0..n).flat_map(|a| (a + 1..n).map(move |b| (a, b)));
        for (p, (a, b)) in pairs.enumerate() {
            let ids = [scene.robots[a].id.as_str(), scene.robots[b].id.as_str()];
            let made = touches(
                spec,
                [&instances[a], &instances[b]],
                [world_from_base[a], world_from_base[b]],
                ids,
                stream(seed, 4, p, 0),
            )?;
            if p == 0 {
                summary.touches = made.len();
                touch_points = Some(made);
            } else {
                let key = (ids[0].to_owned(), ids[1].to_owned());
                summary.pair_touches.push((key.clone(), made.len()));
                pair_touch_points.insert(key, made);
            }
        }
    }
    let mut manifest = Manifest::new(scene.name.clone(), target.manifest.clone(), robots_manifest);
    let scene_name = scene_file
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    manifest.source = format!(
        "b2b-sim: `sim generate --scene {scene_name} --seed {seed}`; rendered, with simulated robot error"
    );
    manifest.license = scene.license.clone();
    let dataset = Dataset {
        root: out.to_owned(),
        manifest,
        robots: robots_data,
        touch_points,
        pair_touch_points,
    };
    for (rel, text) in &target.files {
        let file = out.join(rel);
        if let Some(parent) = file.parent() {
            std::fs::create_dir_all(parent).map_err(|e| SimError::io(parent, e))?;
        }
        std::fs::write(&file, text).map_err(|e| SimError::io(&file, e))?;
    }
    dataset.write(out)?;
    b2b_dataset::write_ground_truth(out, &truth)?;
    Ok(summary)
}

/// Touches of one pair of robots, drawn from `rng`: `tip1_in_base1` is the first
/// robot's reported tip in its base, `tip2_in_base2` the second's.
fn touches(
    spec: &crate::scene::TouchSpec,
    robots: [&RobotInstance; 2],
    world_from_base: [Iso3; 2],
    ids: [&str; 2],
    mut rng: Rng,
) -> Result<Vec<TouchPair>, SimError> {
    let tool = Iso3::translation(0.0, 0.0, spec.tool_length_m);
    let mut out = vec![];
    let mut attempts = 0;
    let max_attempts = spec.count * 200 + 10;
    while out.len() < spec.count {
        attempts += 1;
        if attempts > max_attempts {
            return Err(SimError::PlanningFailed {
                what: format!("touch points reachable by both {} and {}", ids[0], ids[1]),
                found: out.len(),
                wanted: spec.count,
                attempts: max_attempts,
            });
        }
        let p = Point3::new(
            rng.random_range(spec.region_min[0]..=spec.region_max[0]),
            rng.random_range(spec.region_min[1]..=spec.region_max[1]),
            rng.random_range(spec.region_min[2]..=spec.region_max[2]),
        );
        let mut tips = [Point3::origin(); 2];
        let mut ok = true;
        for (r, robot) in robots.iter().enumerate() {
            let p_in_base = world_from_base[r].inverse() * p;
            // Pointer straight down, turned about the vertical at random.
            let yaw = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
            let rot = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)
                * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
            let base_from_tip = Iso3::from_parts(Translation3::from(p_in_base.coords), rot);
            let wanted = base_from_tip * tool.inverse();
            // The tip physically touches the point: solve with the true kinematics.
            let Ok(q) = robot
                .true_arm
                .ik(&wanted, &Arm::comfortable(), &IkOptions::default())
            else {
                ok = false;
                break;
            };
            let state = robot.settle(&q, &mut rng);
            let tip_noise: Vector3<f64> = Vector3::from_fn(|_, _| {
                rand_distr::Distribution::<f64>::sample(&rand_distr::StandardNormal, &mut rng)
            }) * spec.tip_sigma_m;
            tips[r] = state.reported_base_from_flange * tool * Point3::origin() + tip_noise;
        }
        if ok {
            out.push(TouchPair {
                location: None,
                row: out.len() + 1,
                tip1_in_base1: tips[0],
                tip2_in_base2: tips[1],
            });
        }
    }
    Ok(out)
}
