//! The simulated cart (`b2b-sim-cart run`, started by `agent run --sim` / `agent auto --sim`
//! as a separate process): an LBR iiwa behind a real FRI server on UDP, and its flange
//! camera rendering the scene into the same iceoryx2 services a RealSense process
//! would fill. The agent talks to it exactly as to hardware: FRI datagrams in and out,
//! frames from shared memory.
//!
//! Truth stays here. The arm's true kinematics are the nominal ones with the scene's
//! kinematic errors drawn for the seed; the FRI controller reports the joints with
//! encoder noise; each time the arm comes to rest it settles with the repeatability
//! wobble; the camera renders from the true flange pose through the true mount.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::Context;
use b2b_calib::camera::CameraModel;
use b2b_robot::{Arm, Joints};
use b2b_sim::Iso3;
use b2b_sim::render::Renderer;
use b2b_sim::scene::Scene;
use b2b_sim::sensor::{DepthImage, GreyImage, expose};
use kuka_fri::{SimConfig, SimServer, SimServerConfig};
use rand::SeedableRng;

/// One rendered frame, as the camera process publishes it.
#[derive(Debug, Clone)]
pub struct RenderedFrame {
    pub number: u64,
    /// Start of the exposure, ns since the Unix epoch (host clock).
    pub timestamp_ns: u64,
    pub camera: CameraModel,
    /// The camera publishes `camera` as its intrinsics; `false`: it publishes
    /// none (zeros), as a camera without a factory calibration.
    pub intrinsics_given: bool,
    pub grey: GreyImage,
    pub depth: Option<DepthImage>,
}

/// Where the cart's camera puts its frames (iceoryx2 in the cart process).
pub trait FrameSink {
    fn publish(&mut self, frame: &RenderedFrame) -> anyhow::Result<()>;
}

/// Settings of the simulated cart.
#[derive(Debug, Clone)]
pub struct CartOptions {
    pub scene: PathBuf,
    pub robot: String,
    /// The FRI client (the agent) to send monitoring messages to.
    pub client: SocketAddr,
    /// The controller's own address.
    pub bind: SocketAddr,
    pub seed: u64,
    pub send_period_ms: u32,
    /// Longest the cart runs without hearing from its client.
    pub idle_timeout: Duration,
    /// A folder the cart watches for commands ([`bump_file`]).
    pub control: Option<PathBuf>,
    /// The shortest time between two frames: a camera exposes at its frame
    /// rate, and a renderer left to run as fast as it can would take the
    /// machine from the processes it simulates for (see [`FRAME_PERIOD`]).
    pub frame_period: Duration,
}

/// The simulated camera's frame period: 6 frames per second, a RealSense colour
/// stream's lowest setting. Rendering a frame takes one core tens of milliseconds,
/// so two carts at 15 frames per second would take a two-core machine from the
/// agents they simulate for (and deliver fewer than 15 anyway); at 6 both keep
/// their rate with room for the agents, and the watch's 5 Hz still gets a new
/// frame every tick.
pub const FRAME_PERIOD: Duration = Duration::from_nanos(1_000_000_000 / 6);

/// The command file that bumps `robot`'s cart: a pose `{"t": [x, y, z],
/// "rpy_deg": [r, p, y]}` (metres, degrees) by which the cart's base moves, in
/// its own base frame. The cart applies it at its next frame and renames it
/// `*.applied`.
pub fn bump_file(control: &Path, robot: &str) -> PathBuf {
    control.join(format!("bump-{robot}.json"))
}

/// The command file that takes the target away: while it exists, every cart
/// watching `control` renders the scene without its target (an operator has
/// carried the board off). Its content is not read.
pub fn target_taken_file(control: &Path) -> PathBuf {
    control.join("target-taken")
}

/// Takes a pending bump of `robot`, if any.
fn take_bump(control: &Path, robot: &str) -> anyhow::Result<Option<Iso3>> {
    let file = bump_file(control, robot);
    let text = match std::fs::read_to_string(&file) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", file.display())),
    };
    let spec: b2b_sim::scene::PoseSpec = serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not a pose {{\"t\": [..], \"rpy_deg\": [..]}}",
            file.display()
        )
    })?;
    let delta = spec.to_iso(&file, "bump")?;
    let done = file.with_extension("applied");
    std::fs::rename(&file, &done)
        .with_context(|| format!("cannot rename {} to {}", file.display(), done.display()))?;
    Ok(Some(delta))
}

/// How long an exposure lasts: a frame is exposed while the arm moves when its
/// joints change within this time after the state the frame shows is read.
pub const EXPOSURE: Duration = Duration::from_millis(10);

/// Samples per edge pixel in a frame exposed while the arm moves: the motion
/// smears every edge over many pixels in a real exposure, so anti-aliasing finer
/// than that shows nothing a real frame would; the agent passes over such frames
/// (it measures only frames exposed after the arm came to rest).
pub const MOVING_EDGE_SAMPLES: usize = 8;

/// The render settings of a frame exposed while the arm moves.
fn moving(still: &b2b_sim::render::RenderSettings) -> b2b_sim::render::RenderSettings {
    b2b_sim::render::RenderSettings {
        edge_samples: MOVING_EDGE_SAMPLES.min(still.edge_samples),
        varying_samples: 1,
        ..still.clone()
    }
}

/// The stream of the wobble at the `visit`-th arrival at a configuration (`key`:
/// the joints' bits).
fn rest_rng(seed: u64, robot: usize, key: &[u64; 7], visit: u64) -> b2b_sim::Rng {
    use std::hash::{Hash, Hasher};
    // A fixed hasher (not `RandomState`): the same rest draws the same wobble in
    // every run.
    let mut h = std::collections::hash_map::DefaultHasher::new();
    (seed, robot, key, visit).hash(&mut h);
    b2b_sim::Rng::seed_from_u64(h.finish())
}

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// Runs the cart until `stop` is set or the client is silent for the idle timeout.
/// `on_ready` is called with the controller's address once the socket is bound.
pub fn run_cart(
    opts: &CartOptions,
    sink: &mut dyn FrameSink,
    stop: &AtomicBool,
) -> anyhow::Result<u64> {
    let scene = Scene::load(&opts.scene)?;
    let r = scene
        .robots
        .iter()
        .position(|s| s.id == opts.robot)
        .with_context(|| format!("robot '{}' is not in {}", opts.robot, opts.scene.display()))?;
    let spec = &scene.robots[r];
    // Rendered through the true camera; published with the intrinsics the camera
    // reports about itself (its factory calibration), which need not be the truth.
    let renderer = Renderer::new(&scene.camera(r)?)?;
    let camera = scene.reported_camera(r)?;
    let (geometry, _, _) = b2b_sim::generate::scene_geometry(&scene, &opts.scene)?;
    let without_target = b2b_sim::generate::scene_geometry_without_target(&scene, &opts.scene)?;
    let mut target_taken = false;
    let mut world_from_base = scene.base1_from_base(r, &opts.scene)?;
    let flange_from_camera = spec
        .flange_from_camera
        .to_iso(&opts.scene, &format!("robots[{r}].flange_from_camera"))?;
    let nominal = Arm::new(spec.model);
    // The same robot realisation `sim generate` draws for this scene and seed
    // (stream 1 of robot r), so the dataset's touch points were made by these very
    // arms and `coordinator verify` can check a live result against them.
    let mut realisation = b2b_sim::Rng::seed_from_u64(opts.seed);
    realisation.set_stream((1u64 << 48) | ((r as u64) << 32));
    let robot = spec.error.realise(&nominal, &mut realisation)?;
    // Sensor noise: fresh every frame, from the cart's own stream.
    let mut rng = b2b_sim::Rng::seed_from_u64(opts.seed);
    rng.set_stream(0x0ca7_0000 + r as u64);
    // Arrivals at each configuration, for the wobble's stream (`rest_rng`).
    let mut arrivals: std::collections::HashMap<[u64; 7], u64> = Default::default();

    let cfg = SimConfig {
        send_period_ms: opts.send_period_ms,
        limits: spec.model.limits(),
        initial_q: Arm::comfortable(),
        encoder_noise: spec.error.encoder_sigma_rad,
        seed: opts.seed.wrapping_add(r as u64 * 7919),
        ..SimConfig::default()
    };
    // The FRI server runs on its own cycle thread (SCHED_FIFO where permitted) and never
    // waits for this one, which renders: the robot application starts the FRI overlay
    // once the connection is good, as a Sunrise program would.
    let started = Instant::now();
    let fri = SimServer::start(SimServerConfig {
        bind: opts.bind,
        ..SimServerConfig::new(opts.client, cfg)
    })
    .with_context(|| format!("cannot start the FRI server on {}", opts.bind))?;

    let settings = scene.render_settings();
    let moving_settings = moving(&settings);
    let mut rest: Option<(Joints, Iso3)> = None;
    let mut rendered: Option<((Iso3, bool, bool), b2b_sim::render::Irradiance)> = None;
    let mut number = 0u64;
    let outcome = (|| -> anyhow::Result<()> {
        let mut next_frame = Instant::now();
        while !stop.load(Ordering::SeqCst) {
            if let Some(wait) = next_frame.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
            next_frame = Instant::now() + opts.frame_period;
            // The exposure starts no later than the arm's state it shows is read: a
            // frame stamped after the agent found the arm still shows it still, however
            // late a busy machine runs this loop.
            let timestamp_ns = now_ns();
            let s = fri.snapshot();
            if s.heard.unwrap_or(started).elapsed() > opts.idle_timeout {
                tracing::info!("cart: client silent for {:?}; stopping", opts.idle_timeout);
                break;
            }
            if !fri.is_running() {
                break;
            }
            // The target first: a bump commanded after the target was taken
            // never shows in a frame with the target.
            if let Some(control) = &opts.control
                && !target_taken
                && target_taken_file(control).exists()
            {
                target_taken = true;
                tracing::info!("cart {}: the target is taken away", opts.robot);
            }
            if let Some(control) = &opts.control
                && let Some(delta) = take_bump(control, &opts.robot)?
            {
                world_from_base *= delta;
                tracing::info!(
                    "cart {}: bumped by {:.2} mm, {:.3} deg",
                    opts.robot,
                    delta.translation.vector.norm() * 1e3,
                    delta.rotation.angle().to_degrees()
                );
            }
            // Settle: a fresh repeatability wobble every time the arm comes to rest
            // somewhere new, drawn from that rest's own stream (the configuration
            // and how often the arm has arrived there), so that which wobble a rest
            // gets does not depend on how many frames the machine rendered on the
            // way (a busy machine renders fewer).
            let base_from_flange = match rest {
                Some((q, pose)) if q == s.q => pose,
                _ => {
                    let key = s.q.map(f64::to_bits);
                    let visit = arrivals.entry(key).or_default();
                    *visit += 1;
                    let mut rest_rng = rest_rng(opts.seed, r, &key, *visit);
                    let pose = robot.settle(&s.q, &mut rest_rng).true_base_from_flange;
                    rest = Some((s.q, pose));
                    pose
                }
            };
            let camera_from_world =
                (world_from_base * base_from_flange * flange_from_camera).inverse();
            // Moving during the exposure: the joints change within it. An arm at
            // rest holds its joints exactly (the wobble above is drawn once per
            // rest), so every frame exposed after it stopped is rendered in full.
            std::thread::sleep(EXPOSURE);
            let fast = fri.snapshot().q != s.q;
            let world = if target_taken {
                &without_target
            } else {
                &geometry
            };
            // A still camera in an unchanged scene sees the same irradiance: it is
            // rendered once and exposed afresh (new sensor noise) every frame.
            let view = (camera_from_world, target_taken, fast);
            let irradiance = match &rendered {
                Some((v, irradiance)) if *v == view => irradiance,
                _ => {
                    let settings = if fast { &moving_settings } else { &settings };
                    let irradiance = renderer.render(&camera_from_world, world, settings);
                    &rendered.insert((view, irradiance)).1
                }
            };
            let grey = expose(irradiance, &scene.noise, &mut rng);
            let depth = scene.depth.map(|m| m.measure(irradiance, &mut rng));
            number += 1;
            sink.publish(&RenderedFrame {
                number,
                timestamp_ns,
                camera: camera.clone(),
                intrinsics_given: spec.reports_intrinsics,
                grey,
                depth,
            })?;
        }
        Ok(())
    })();
    let fri_result = fri.shutdown();
    outcome?;
    let last = fri_result.context("the FRI server stopped")?;
    tracing::info!("cart: FRI server stopped: {:?}", last.stats);
    Ok(number)
}

/// The cart's camera publishing into iceoryx2, as the camera process does.
pub struct IceoryxSink {
    colour: b2b_frames::FramePublisher,
    depth: Option<b2b_frames::FramePublisher>,
}

impl std::fmt::Debug for IceoryxSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("IceoryxSink").finish_non_exhaustive()
    }
}

impl IceoryxSink {
    /// Publishers of `robot`'s streams under `prefix` (`b2b/camera` in deployment).
    pub fn new(
        prefix: &str,
        robot: &str,
        camera: &CameraModel,
        depth: bool,
    ) -> anyhow::Result<Self> {
        use b2b_frames::{Stream, service_name_in};
        let pixels = camera.width as usize * camera.height as usize;
        let colour = b2b_frames::FramePublisher::new(
            &service_name_in(prefix, robot, Stream::Colour),
            pixels,
        )?;
        let depth = if depth {
            Some(b2b_frames::FramePublisher::new(
                &service_name_in(prefix, robot, Stream::Depth),
                pixels * 2,
            )?)
        } else {
            None
        };
        Ok(IceoryxSink { colour, depth })
    }
}

fn header(kind: b2b_frames::StreamKind, frame: &RenderedFrame) -> b2b_frames::FrameHeader {
    let c = &frame.camera;
    let mut dist = [0.0; 5];
    for (d, v) in dist.iter_mut().zip(&c.dist) {
        *d = *v;
    }
    let h = b2b_frames::FrameHeader::new(kind, c.width, c.height);
    let h = if frame.intrinsics_given {
        h.with_intrinsics(c.fx, c.fy, c.cx, c.cy, dist)
    } else {
        h
    };
    h.at(frame.number, frame.timestamp_ns)
}

impl FrameSink for IceoryxSink {
    fn publish(&mut self, frame: &RenderedFrame) -> anyhow::Result<()> {
        let h = header(b2b_frames::StreamKind::Gray8, frame);
        self.colour.update_connections()?;
        self.colour
            .publish_with(&h, |buf| buf.copy_from_slice(&frame.grey.data))?;
        if let (Some(p), Some(d)) = (&mut self.depth, &frame.depth) {
            let mut h = header(b2b_frames::StreamKind::Z16, frame);
            h.depth_unit_m = d.unit_m;
            p.update_connections()?;
            p.publish_with(&h, |buf| {
                for (out, v) in buf.chunks_exact_mut(2).zip(&d.data) {
                    out.copy_from_slice(&v.to_le_bytes());
                }
            })?;
        }
        Ok(())
    }
}
