//! `agent`: one per cart. `handeye` works offline on a dataset; `run` publishes a
//! cart's captures over zenoh from a dataset replay, the simulated cart or a real arm
//! (FRI + the camera process over iceoryx2); `auto` runs the automatic pre-operative
//! routine. `--sim` starts the simulated cart, its own binary (`b2b-sim-cart`), as a
//! process.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use b2b_calib::refine::RefineOptions;
use b2b_pipeline::{HandEyeChoice, hand_eye, load_dataset, observe_robot};
use std::sync::Arc;

use b2b_services::{
    RerunArgs, RobotNoiseArgs, finish_recording, init_logging, run_main, write_json,
};
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(name = "agent", version, about = "Calibration agent of one robot cart")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Publish this cart's captures (flange pose, board observation,
    /// base_from_target, hand-eye, status) over zenoh until the coordinator answers.
    Run {
        /// Robot id (as in the dataset; used in key expressions).
        #[arg(long)]
        robot: String,
        /// Replay a b2b-dataset/1 folder's captures for this robot.
        #[arg(long, conflicts_with_all = ["sim", "fri"])]
        replay: Option<PathBuf>,
        /// Simulated cart from a scene file (started as a child process: FRI server
        /// on loopback UDP, camera into iceoryx2).
        #[arg(long, conflicts_with = "fri")]
        sim: Option<PathBuf>,
        /// A real controller over KUKA FRI at HOST:PORT (frames from the camera
        /// process over iceoryx2; needs --setup).
        #[arg(long)]
        fri: Option<String>,
        #[command(flatten)]
        live: LiveArgs,
        /// zenoh configuration file (JSON5); default: loopback peer connecting to
        /// the coordinator on tcp/127.0.0.1:7447.
        #[arg(long)]
        zenoh: Option<PathBuf>,
        /// Where the agent keeps its sequence number.
        #[arg(long, default_value = "agent-state")]
        state_dir: PathBuf,
        /// Milliseconds between replayed captures.
        #[arg(long, default_value_t = 0)]
        pace_ms: u64,
        /// Local features for the coordinator's RGB-D method, lifted with each
        /// capture's depth image and published with it: sift, akaze, orb or none
        /// (captures without depth never carry features).
        #[arg(long, default_value = "sift")]
        features: String,
        /// Seconds to wait for the coordinator's result after the last capture.
        #[arg(long, default_value_t = 600)]
        wait_result_s: u64,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
        #[command(flatten)]
        rerun: RerunArgs,
    },
    /// The automatic pre-operative routine: plan ~30 viewpoints around the board,
    /// move, settle, capture, re-centre the board in a closed loop, stop when the
    /// hand-eye is good enough; every capture is published as it is taken.
    Auto {
        /// This cart's robot id (robot1, robot2, ...): the key its messages go under.
        #[arg(long)]
        robot: String,
        /// Simulated cart from a scene file.
        #[arg(long, conflicts_with = "fri")]
        sim: Option<PathBuf>,
        /// A real controller over KUKA FRI at HOST:PORT (needs --setup).
        #[arg(long)]
        fri: Option<String>,
        /// Plan and print the path without moving.
        #[arg(long)]
        dry_run: bool,
        /// Stop when the hand-eye's 1-sigma translation is below this (mm) ...
        #[arg(long, default_value_t = 0.1)]
        stop_sigma_mm: f64,
        /// ... and its 1-sigma rotation below this (deg) ...
        #[arg(long, default_value_t = 0.01)]
        stop_sigma_deg: f64,
        /// ... with at least this many good captures.
        #[arg(long, default_value_t = 20)]
        min_good: usize,
        /// zenoh configuration file (JSON5); default: loopback peer connecting to
        /// the coordinator on tcp/127.0.0.1:7447.
        #[arg(long)]
        zenoh: Option<PathBuf>,
        /// Where the agent keeps its sequence number.
        #[arg(long, default_value = "agent-state")]
        state_dir: PathBuf,
        /// Seconds to wait for the coordinator's result after the last capture.
        #[arg(long, default_value_t = 600)]
        wait_result_s: u64,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
        #[command(flatten)]
        live: LiveArgs,
        #[command(flatten)]
        rerun: RerunArgs,
    },
    /// Hand-eye (T_flange_camera) of one robot from a b2b-dataset/1 folder.
    Handeye {
        /// The dataset folder.
        #[arg(long)]
        dataset: PathBuf,
        /// Robot id as listed in dataset.json.
        #[arg(long)]
        robot: String,
        /// tsai, park, horaud, andreff, daniilidis, shah, li or refined (joint
        /// reprojection-error refinement seeded by Park).
        #[arg(
            long,
            default_value = "refined",
            value_parser = ["tsai", "park", "horaud", "andreff", "daniilidis", "shah", "li", "refined"]
        )]
        method: String,
        /// Also refine the camera intrinsics (fx, fy, cx, cy, k1, k2, p1, p2, k3).
        /// A robot without intrinsics in dataset.json always gets them estimated
        /// from its images and refined so.
        #[arg(long)]
        refine_intrinsics: bool,
        /// Where to write HANDEYE.json.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        noise: RobotNoiseArgs,
        #[command(flatten)]
        rerun: RerunArgs,
    },
}

/// Options of the live sources (`--sim`, `--fri`).
#[derive(clap::Args, Debug, Clone)]
struct LiveArgs {
    /// Cell setup (JSON: arm model, target, approximate board and mount, workspace
    /// box); required with --fri, derived from the scene with --sim.
    #[arg(long)]
    setup: Option<PathBuf>,
    /// Where the FRI client binds (the cell's client port).
    #[arg(long, default_value = "0.0.0.0:30200")]
    fri_bind: std::net::SocketAddr,
    /// The camera's iceoryx2 service root.
    #[arg(long, default_value = "b2b/camera")]
    camera_prefix: String,
    /// Viewpoints to plan.
    #[arg(long, default_value_t = 30)]
    count: usize,
    /// Seed of the simulated cart (its robot errors and sensor noise).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    #[command(flatten)]
    noise: RobotNoiseArgs,
}

/// Kills the simulated cart when the agent ends.
struct Child(std::process::Child);

impl Drop for Child {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The simulated cart's binary: `B2B_SIM_CART`, or `b2b-sim-cart` beside the
/// agent's own executable (cargo builds both into one folder).
fn sim_cart_exe() -> anyhow::Result<PathBuf> {
    if let Some(p) = std::env::var_os("B2B_SIM_CART") {
        return Ok(PathBuf::from(p));
    }
    let exe = std::env::current_exe().context("cannot find the agent's own executable")?;
    let cart = exe.with_file_name(format!("b2b-sim-cart{}", std::env::consts::EXE_SUFFIX));
    anyhow::ensure!(
        cart.is_file(),
        "the simulated cart's binary is not at {} (build it with `cargo build -p b2b-sim-cart`, or set B2B_SIM_CART)",
        cart.display()
    );
    Ok(cart)
}

/// What `b2b-sim-cart setup` reports.
#[derive(Debug, serde::Deserialize)]
struct DerivedSetup {
    setup: PathBuf,
    depth: bool,
}

/// Runs `b2b-sim-cart setup` for `robot` of `scene` into `dir`.
fn sim_cart_setup(
    scene: &std::path::Path,
    robot: &str,
    dir: &std::path::Path,
) -> anyhow::Result<DerivedSetup> {
    let out = std::process::Command::new(sim_cart_exe()?)
        .args(["setup", "--robot", robot, "--scene"])
        .arg(scene)
        .arg("--dir")
        .arg(dir)
        .stdin(std::process::Stdio::null())
        .output()
        .context("cannot start the simulated cart")?;
    anyhow::ensure!(
        out.status.success(),
        "the simulated cart refused {}: {}",
        scene.display(),
        String::from_utf8_lossy(&out.stderr).trim()
    );
    serde_json::from_slice(&out.stdout).with_context(|| {
        format!(
            "the simulated cart's setup answer is not JSON: {}",
            String::from_utf8_lossy(&out.stdout).trim()
        )
    })
}

/// Connects to the arm and camera of `--sim` or `--fri`; returns the source and,
/// for `--sim`, the cart process.
fn connect(
    robot: &str,
    sim: Option<&std::path::Path>,
    fri: Option<&str>,
    live: &LiveArgs,
    mode: b2b_services::live::LiveMode,
    features: Option<b2b_vision::features::FeatureKind>,
) -> anyhow::Result<(b2b_services::live::LiveSource, Option<Child>)> {
    use b2b_services::setup::{CellSetup, Connection, fri_client, live_source};
    b2b_protocol::messages::validate_robot_id(robot)?;
    b2b_frames::quiet_iceoryx2_logs();
    let plan = b2b_services::plan::PlanConfig {
        count: live.count,
        ..Default::default()
    };
    let mut has_depth = true;
    let (setup, conn, cart_scene) = match (sim, fri) {
        (Some(scene), None) => {
            // The simulated cart's own binary derives the setup from the scene
            // (board and mount off by a setup sheet's error); the target's files
            // go into a folder of this agent process.
            let derived = sim_cart_setup(
                scene,
                robot,
                &std::env::temp_dir().join(format!("b2b-agent-{}-{robot}", std::process::id())),
            )?;
            has_depth = derived.depth;
            let setup = match &live.setup {
                Some(f) => CellSetup::load(f)?,
                None => CellSetup::load(&derived.setup)?,
            };
            // A unique service root per run, so two simulated cells never mix.
            let prefix = format!("{}/sim{}", live.camera_prefix, std::process::id());
            let conn = Connection {
                bind: "127.0.0.1:0".parse()?,
                controller: None,
                camera_prefix: prefix,
            };
            (setup, conn, Some(scene.to_owned()))
        }
        (None, Some(addr)) => {
            let file = live
                .setup
                .as_ref()
                .context("--fri needs --setup FILE (arm model, target, approximate board and mount, workspace)")?;
            let controller: std::net::SocketAddr = addr
                .parse()
                .with_context(|| format!("--fri {addr}: not HOST:PORT"))?;
            let conn = Connection {
                bind: live.fri_bind,
                controller: Some(controller),
                camera_prefix: live.camera_prefix.clone(),
            };
            (CellSetup::load(file)?, conn, None)
        }
        _ => anyhow::bail!("give a source: --sim SCENE or --fri HOST:PORT"),
    };
    let fri = fri_client(&setup, &conn)?;
    let mut frames = b2b_services::live::IceoryxFrames::new(&conn.camera_prefix, robot)?;
    let features = features.map(b2b_pipeline::rgbd::RgbdOptions::with_kind);
    // A simulated camera has depth only when its scene says so.
    if features.is_some() && has_depth {
        frames = frames.with_depth(&conn.camera_prefix, robot)?;
    }
    let child = match cart_scene {
        Some(scene) => {
            let child = std::process::Command::new(sim_cart_exe()?)
                .args(["run", "--robot", robot, "--client"])
                .arg(fri.local_addr().to_string())
                .arg("--scene")
                .arg(&scene)
                .args(["--seed", &live.seed.to_string()])
                .args(["--camera-prefix", &conn.camera_prefix])
                .stdin(std::process::Stdio::null())
                .spawn()
                .context("cannot start the simulated cart")?;
            Some(Child(child))
        }
        None => None,
    };
    let source = live_source(&setup, robot, mode, plan, fri, Box::new(frames), features)?;
    Ok((source, child))
}

fn print_result(
    robot: &str,
    result: Option<b2b_protocol::CalibrationResult>,
    wait_result_s: u64,
) -> anyhow::Result<()> {
    match result {
        Some(r) => {
            let t = r.base1_from_base2.t;
            println!(
                "{robot}: coordinator result T_base1_base2 t = [{:.6}, {:.6}, {:.6}] m",
                t[0], t[1], t[2]
            );
            Ok(())
        }
        None => anyhow::bail!("no result from the coordinator within {wait_result_s} s"),
    }
}

fn main() -> std::process::ExitCode {
    init_logging();
    let cli = Cli::parse();
    run_main(|| match cli.command {
        Command::Run {
            robot,
            replay,
            sim,
            fri,
            zenoh,
            state_dir,
            pace_ms,
            features,
            wait_result_s,
            quiet,
            live,
            rerun,
        } => {
            let features = match features.as_str() {
                "none" => None,
                kind => Some(b2b_vision::features::FeatureKind::parse(kind)?),
            };
            let recorder = Arc::new(rerun.recorder(&format!("b2b-agent-{robot}"))?);
            let outcome = (|| {
                if sim.is_some() || fri.is_some() {
                    let stop = b2b_services::stop_flag();
                    let (mut source, _cart) = connect(
                        &robot,
                        sim.as_deref(),
                        fri.as_deref(),
                        &live,
                        b2b_services::live::LiveMode::Program,
                        features,
                    )?;
                    let opts = b2b_services::agent::AgentOptions {
                        robot: robot.clone(),
                        zenoh,
                        state_dir,
                        pace: Duration::from_millis(pace_ms),
                        wait_result: Duration::from_secs(wait_result_s),
                        progress: !quiet,
                        refine: live.noise.options()?,
                        rerun: Arc::clone(&recorder),
                    };
                    let result = b2b_services::agent::run_agent(&opts, &mut source, &stop)?;
                    return print_result(&robot, result, wait_result_s);
                }
                let Some(dataset) = replay else {
                    anyhow::bail!("give a source: --replay DIR, --sim SCENE or --fri HOST:PORT");
                };
                let stop = b2b_services::stop_flag();
                let opts = b2b_services::agent::ReplayOptions {
                    robot: robot.clone(),
                    dataset,
                    zenoh,
                    state_dir,
                    pace: Duration::from_millis(pace_ms),
                    wait_result: Duration::from_secs(wait_result_s),
                    progress: !quiet,
                    rerun: Arc::clone(&recorder),
                    features,
                };
                let result = b2b_services::agent::run_replay(&opts, &stop)?;
                print_result(&robot, result, wait_result_s)
            })();
            if let Ok(rec) = Arc::try_unwrap(recorder) {
                finish_recording(rec);
            }
            outcome
        }
        Command::Auto {
            robot,
            sim,
            fri,
            dry_run,
            stop_sigma_mm,
            stop_sigma_deg,
            min_good,
            zenoh,
            state_dir,
            wait_result_s,
            quiet,
            live,
            rerun,
        } => {
            let auto = b2b_services::live::AutoConfig {
                stop_sigma_t_m: stop_sigma_mm * 1e-3,
                stop_sigma_r_rad: stop_sigma_deg.to_radians(),
                min_good,
                ..Default::default()
            };
            auto.validate()
                .context("--stop-sigma-mm and --stop-sigma-deg must be > 0")?;
            let stop = b2b_services::stop_flag();
            let (mut source, _cart) = connect(
                &robot,
                sim.as_deref(),
                fri.as_deref(),
                &live,
                b2b_services::live::LiveMode::Auto(auto),
                None,
            )?;
            if dry_run {
                let plan = source.plan_only()?.clone();
                println!(
                    "{robot}: {} viewpoints planned from {} candidates; joint travel {:.2} rad",
                    plan.viewpoints.len(),
                    plan.candidates,
                    plan.travel_rad
                );
                for (reason, n) in &plan.dropped {
                    println!("  dropped {n}: {reason}");
                }
                for (i, v) in plan.viewpoints.iter().enumerate() {
                    let t = v.base_from_flange.translation.vector;
                    println!(
                        "  {:2}: q = [{}] rad; flange at [{:.3}, {:.3}, {:.3}] m; distance {:.2} m, tilt {:.0} deg, roll {:.0} deg",
                        i + 1,
                        v.q.iter()
                            .map(|x| format!("{x:.3}"))
                            .collect::<Vec<_>>()
                            .join(", "),
                        t.x,
                        t.y,
                        t.z,
                        v.distance_m,
                        v.tilt_rad.to_degrees(),
                        v.roll_rad.to_degrees()
                    );
                }
                return Ok(());
            }
            let opts = b2b_services::agent::AgentOptions {
                robot: robot.clone(),
                zenoh,
                state_dir,
                pace: Duration::ZERO,
                wait_result: Duration::from_secs(wait_result_s),
                progress: !quiet,
                refine: live.noise.options()?,
                rerun: Arc::new(rerun.recorder(&format!("b2b-agent-{robot}"))?),
            };
            let result = b2b_services::agent::run_agent(&opts, &mut source, &stop);
            drop(source);
            if let Ok(rec) = Arc::try_unwrap(opts.rerun) {
                finish_recording(rec);
            }
            print_result(&robot, result?, wait_result_s)
        }
        Command::Handeye {
            dataset,
            robot,
            method,
            refine_intrinsics,
            out,
            noise,
            rerun,
        } => {
            let recorder = rerun.recorder(&format!("b2b-handeye-{robot}"))?;
            let choice: HandEyeChoice = method.parse().map_err(anyhow::Error::msg)?;
            let ds = load_dataset(&dataset)?;
            let obs = observe_robot(&ds, &robot)?;
            let options = RefineOptions {
                refine_intrinsics,
                ..noise.options()?
            };
            let run = hand_eye(&obs, choice, &options)?;
            write_json(&out, &run.result).context("writing the hand-eye result")?;
            let r = &run.result;
            let t = r.flange_from_camera.t;
            let q = r.flange_from_camera.q;
            println!("robot {robot}: method {}", r.method);
            println!(
                "captures: {} used, {} rejected",
                obs.observations.len(),
                r.captures.rejected.len()
            );
            for rej in &r.captures.rejected {
                println!(
                    "  rejected {}: {}",
                    rej.image.as_deref().unwrap_or("-"),
                    rej.reason
                );
            }
            println!(
                "T_flange_camera t = [{:.6}, {:.6}, {:.6}] m",
                t[0], t[1], t[2]
            );
            println!(
                "                q = [{:.8}, {:.8}, {:.8}, {:.8}] (x, y, z, w)",
                q[0], q[1], q[2], q[3]
            );
            b2b_services::outputs::print_sigma(&r.covariance);
            println!(
                "reprojection RMS {:.3} px; detect {:.0} ms, solve {:.0} ms",
                r.reprojection_rms_px, r.timings_ms.detect, r.timings_ms.solve
            );
            if obs.estimated_intrinsics.is_some() || refine_intrinsics {
                let camera = b2b_pipeline::RobotCamera {
                    robot: robot.clone(),
                    camera: run.estimate.camera.clone(),
                    refined: choice == HandEyeChoice::Refined,
                    estimated: obs.estimated_intrinsics.clone(),
                };
                println!("{}", camera.describe());
            }
            if recorder.is_enabled() {
                let x = r.flange_from_camera.to_isometry("T_flange_camera")?;
                let c = &obs.camera;
                let intr = b2b_protocol::messages::Intrinsics {
                    width: c.width,
                    height: c.height,
                    fx: c.fx,
                    fy: c.fy,
                    cx: c.cx,
                    cy: c.cy,
                    dist: c.dist[..5].to_vec(),
                };
                let base = b2b_viz::Base::One;
                let logged = recorder.log_hand_eye(base, &x, &intr).and_then(|()| {
                    obs.observations.iter().enumerate().try_for_each(|(i, o)| {
                        recorder.set_capture_time(i as u64, i as f64);
                        recorder.log_flange(base, &o.board.base_from_flange)?;
                        recorder.log_corners(
                            base,
                            &o.board
                                .pixels
                                .iter()
                                .map(|p| [p.x, p.y])
                                .collect::<Vec<_>>(),
                            &[],
                        )?;
                        recorder.log_residual(base, o.pnp_rms_px)
                    })
                });
                if let Err(e) = logged {
                    eprintln!("warning: rerun: {}", b2b_pipeline::error_chain(&e));
                }
            }
            finish_recording(recorder);
            println!("wrote {}", out.display());
            Ok(())
        }
    })
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    #[test]
    fn every_flag_has_help() {
        let missing = b2b_services::undocumented_args(&super::Cli::command());
        assert!(missing.is_empty(), "flags without help: {missing:?}");
    }
}
