//! `agent`: one per cart. `handeye` works offline on a dataset; `run` publishes a
//! cart's captures over zenoh from a dataset replay, the simulated cart or a real arm
//! (FRI + the camera process over iceoryx2); `auto` runs the automatic pre-operative
//! routine. `--sim` starts the simulated cart, its own binary (`b2b-sim-cart`), as a
//! process.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use b2b_calib::refine::RefineOptions;
use b2b_live::WatchObserve;
use b2b_pipeline::{HandEyeChoice, RobotCamera, hand_eye, observe_robot};
use b2b_report::write::{check_destinations, refuse_output_over_input};
use b2b_routine::{Mode, RoutineConfig};
use b2b_services::agent::{AgentOptions, BusArgs, run_agent, run_replay, run_watch};
use b2b_services::outputs::{print_agent_result, print_hand_eye, print_plan};
use b2b_services::recording::{RerunArgs, finish_recording, log_hand_eye_run};
use b2b_services::setup::{Cart, LiveArgs, connect};
use b2b_services::{
    RobotNoiseArgs, init_logging, positive, run_main, stop_flag, whole_count, whole_number,
    write_json,
};
use b2b_vision::features::FeatureKind;
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
    Run(RunArgs),
    /// The automatic pre-operative routine: plan ~30 viewpoints around the board,
    /// move, settle, capture, re-centre the board in a closed loop, stop when the
    /// hand-eye is good enough; every capture is published as it is taken.
    Auto(AutoArgs),
    /// The drift watch during the operation: move to a pose with the board in
    /// view (the first planned viewpoint) and publish an observation of it
    /// (b2b/agent/ROBOT/watch) at a low rate, for `coordinator watch`.
    Watch(WatchArgs),
    /// Hand-eye (T_flange_camera) of one robot from a b2b-dataset/1 folder.
    Handeye(HandeyeArgs),
}

// The flags of `run` (the help is the variant's doc comment).
#[derive(clap::Args, Debug)]
struct RunArgs {
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
    /// Milliseconds between replayed captures.
    #[arg(long, default_value_t = 0, value_parser = whole_number, allow_negative_numbers = true)]
    pace_ms: u64,
    /// Local features for the coordinator's RGB-D method, lifted with each
    /// capture's depth image and published with it: sift, akaze, orb or none
    /// (captures without depth never carry features).
    #[arg(long, default_value = "sift")]
    features: String,
    #[command(flatten)]
    bus: BusArgs,
    #[command(flatten)]
    rerun: RerunArgs,
}

// The flags of `auto` (the help is the variant's doc comment).
#[derive(clap::Args, Debug)]
struct AutoArgs {
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
    #[arg(long, default_value_t = 0.1, value_parser = positive, allow_negative_numbers = true)]
    stop_sigma_mm: f64,
    /// ... and its 1-sigma rotation below this (deg) ...
    #[arg(long, default_value_t = 0.01, value_parser = positive, allow_negative_numbers = true)]
    stop_sigma_deg: f64,
    /// ... with at least this many good captures.
    #[arg(long, default_value_t = 20, value_parser = whole_count, allow_negative_numbers = true)]
    min_good: usize,
    /// After the coordinator's result, stay and watch for drift (as `agent
    /// watch`) at this rate until Ctrl-C.
    #[arg(long, value_parser = positive, allow_negative_numbers = true)]
    watch_hz: Option<f64>,
    /// What that watch observes, as `agent watch --observe`. The
    /// routine's own captures carry no features.
    #[arg(long, value_enum, default_value_t = WatchObserve::Auto)]
    watch_observe: WatchObserve,
    /// The kind of the watch's features: sift, akaze or orb.
    #[arg(long, default_value = "sift")]
    watch_features: String,
    #[command(flatten)]
    bus: BusArgs,
    #[command(flatten)]
    live: LiveArgs,
    #[command(flatten)]
    rerun: RerunArgs,
}

// The flags of `watch` (the help is the variant's doc comment).
#[derive(clap::Args, Debug)]
struct WatchArgs {
    /// This cart's robot id.
    #[arg(long)]
    robot: String,
    /// Simulated cart from a scene file.
    #[arg(long, conflicts_with = "fri")]
    sim: Option<PathBuf>,
    /// A real controller over KUKA FRI at HOST:PORT (needs --setup).
    #[arg(long)]
    fri: Option<String>,
    /// Observations per second.
    #[arg(long, default_value_t = 5.0, value_parser = positive, allow_negative_numbers = true)]
    hz: f64,
    /// Stop after this many seconds (default: until Ctrl-C).
    #[arg(long, value_parser = positive, allow_negative_numbers = true)]
    duration_s: Option<f64>,
    /// What to observe: `target`; `features` (the scene's local features
    /// lifted with the depth frame, for where no target is left in view);
    /// `auto` (both: the coordinator watches the target while it is in view,
    /// else the features). Features need a camera with depth.
    #[arg(long, value_enum, default_value_t = WatchObserve::Auto)]
    observe: WatchObserve,
    /// The kind of those features: sift, akaze or orb.
    #[arg(long, default_value = "sift")]
    features: String,
    #[command(flatten)]
    bus: BusArgs,
    #[command(flatten)]
    live: LiveArgs,
}

// The flags of `handeye` (the help is the variant's doc comment).
#[derive(clap::Args, Debug)]
struct HandeyeArgs {
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
}

/// `--features`: a kind of local features, or `none`.
fn feature_kind(kind: &str) -> anyhow::Result<Option<FeatureKind>> {
    match kind {
        "none" => Ok(None),
        kind => Ok(Some(FeatureKind::parse(kind)?)),
    }
}

/// The features a watch that observes `observe` needs: none for the target alone.
fn features_to_watch(observe: WatchObserve, kind: &str) -> anyhow::Result<Option<FeatureKind>> {
    match observe {
        WatchObserve::Target => Ok(None),
        _ => Ok(Some(FeatureKind::parse(kind)?)),
    }
}

/// The options every run on the bus shares.
fn agent_options(
    robot: &str,
    bus: BusArgs,
    pace: Duration,
    refine: RefineOptions,
    rerun: &RerunArgs,
) -> anyhow::Result<AgentOptions> {
    Ok(AgentOptions {
        robot: robot.to_owned(),
        zenoh: bus.zenoh,
        state_dir: bus.state_dir,
        pace,
        wait_result: Duration::from_secs(bus.wait_result_s),
        progress: !bus.quiet,
        refine,
        rerun: Arc::new(rerun.recorder(&format!("b2b-agent-{robot}"))?),
    })
}

/// Closes the run's recording (after the source, which may hold a clone, is
/// gone), then reports the coordinator's result.
fn finish(
    opts: AgentOptions,
    result: anyhow::Result<Option<b2b_protocol::CalibrationResult>>,
) -> anyhow::Result<()> {
    if let Ok(rec) = Arc::try_unwrap(opts.rerun) {
        finish_recording(rec);
    }
    Ok(print_agent_result(
        &opts.robot,
        result?,
        opts.wait_result.as_secs(),
    )?)
}

/// `run`: this cart's captures over zenoh, from a replay, the simulated cart or a real arm.
fn run(args: RunArgs) -> anyhow::Result<()> {
    let RunArgs {
        robot,
        replay,
        sim,
        fri,
        pace_ms,
        features,
        bus,
        live,
        rerun,
    } = args;
    let features = feature_kind(&features)?;
    let pace = Duration::from_millis(pace_ms);
    let opts = agent_options(&robot, bus, pace, live.noise.options(), &rerun)?;
    let stop = stop_flag();
    let result = match (replay, Cart::from_flags(sim.as_deref(), fri.as_deref())) {
        (Some(dataset), _) => {
            run_replay(&opts, &dataset, features, &stop).map_err(anyhow::Error::from)
        }
        (None, Ok(cart)) => connect(&robot, cart, &live, Mode::Program, features)
            .and_then(|(mut source, _cart)| run_agent(&opts, &mut source, &stop))
            .map_err(anyhow::Error::from),
        (None, Err(_)) => Err(anyhow::anyhow!(
            "give a source: --replay DIR, --sim SCENE or --fri HOST:PORT"
        )),
    };
    finish(opts, result)
}

/// `auto`: the automatic pre-operative routine, then the watch if asked.
fn auto(args: AutoArgs) -> anyhow::Result<()> {
    let AutoArgs {
        robot,
        sim,
        fri,
        dry_run,
        stop_sigma_mm,
        stop_sigma_deg,
        min_good,
        watch_hz,
        watch_observe,
        watch_features,
        bus,
        live,
        rerun,
    } = args;
    let observe = watch_observe;
    let features = match watch_hz {
        Some(_) => features_to_watch(observe, &watch_features)?,
        None => None,
    };
    let routine = RoutineConfig {
        stop_sigma_t_m: stop_sigma_mm * 1e-3,
        stop_sigma_r_rad: stop_sigma_deg.to_radians(),
        min_good,
        ..Default::default()
    };
    routine
        .validate()
        .context("--stop-sigma-mm and --stop-sigma-deg must be > 0")?;
    let cart = Cart::from_flags(sim.as_deref(), fri.as_deref())?;
    let (mut source, _cart) = connect(&robot, cart, &live, Mode::Auto(routine), features)?;
    // The routine's captures go to the board method: the features are
    // the watch's, after it.
    let features = source.set_features(None);
    if dry_run {
        print_plan(&robot, source.plan_only()?);
        return Ok(());
    }
    let (zenoh, state_dir) = (bus.zenoh.clone(), bus.state_dir.clone());
    let opts = agent_options(&robot, bus, Duration::ZERO, live.noise.options(), &rerun)?;
    let stop = stop_flag();
    let result = run_agent(&opts, &mut source, &stop).map_err(anyhow::Error::from);
    let calibrated = result.as_ref().is_ok_and(Option::is_some);
    let watched = match watch_hz {
        Some(hz) if calibrated => {
            let bus = b2b_services::bus::ZenohBus::open(
                zenoh.as_deref(),
                b2b_services::bus::Role::Agent,
            )?;
            let period = Duration::from_secs_f64(1.0 / hz);
            eprintln!(
                "{robot}: the coordinator has its result; watching for drift at {hz} Hz until Ctrl-C (the result is printed after)"
            );
            source.set_features(features);
            Some(run_watch(
                &bus,
                &robot,
                &state_dir,
                &mut source,
                period,
                observe,
                &stop,
            ))
        }
        _ => None,
    };
    drop(source);
    finish(opts, result)?;
    if let Some(n) = watched {
        eprintln!("{robot}: {} watch observations published", n?);
    }
    Ok(())
}

/// `watch`: the drift watch's observations.
fn watch(args: WatchArgs) -> anyhow::Result<()> {
    let WatchArgs {
        robot,
        sim,
        fri,
        hz,
        duration_s,
        observe,
        features,
        bus,
        live,
    } = args;
    let features = features_to_watch(observe, &features)?;
    let cart = Cart::from_flags(sim.as_deref(), fri.as_deref())?;
    let (mut source, _cart) = connect(&robot, cart, &live, Mode::Program, features)?;
    let zenoh =
        b2b_services::bus::ZenohBus::open(bus.zenoh.as_deref(), b2b_services::bus::Role::Agent)?;
    let stop = stop_flag();
    if let Some(s) = duration_s {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs_f64(s));
            stop.store(true, std::sync::atomic::Ordering::SeqCst);
        });
    }
    let n = run_watch(
        &zenoh,
        &robot,
        &bus.state_dir,
        &mut source,
        Duration::from_secs_f64(1.0 / hz),
        observe,
        &stop,
    )?;
    eprintln!("{robot}: {n} watch observations published");
    Ok(())
}

/// `handeye`: one robot's hand-eye from a dataset.
fn handeye(args: HandeyeArgs) -> anyhow::Result<()> {
    let HandeyeArgs {
        dataset,
        robot,
        method,
        refine_intrinsics,
        out,
        noise,
        rerun,
    } = args;
    refuse_output_over_input("--out", &out, Some(&dataset), &[])?;
    check_destinations(&[&out])?;
    let recorder = rerun.recorder(&format!("b2b-handeye-{robot}"))?;
    let choice: HandEyeChoice = method.parse().map_err(anyhow::Error::msg)?;
    b2b_services::show_pipeline_progress();
    // One robot's hand-eye uses no touches: a touch file (even one a
    // one-robot dataset should not have) is not its business.
    let ds = b2b_dataset::Dataset::load_without_touches(&dataset)?;
    let obs = observe_robot(&ds, &robot)?;
    let options = RefineOptions {
        refine_intrinsics,
        ..noise.options()
    };
    let run = hand_eye(&obs, choice, &options)?;
    write_json(&out, &run.result).context("writing the hand-eye result")?;
    print_hand_eye(&run, &obs);
    if let Some(w) = run.systematic_warning() {
        eprintln!("warning: {w}");
    }
    if obs.estimated_intrinsics.is_some() || refine_intrinsics {
        let camera = RobotCamera {
            robot: robot.clone(),
            camera: run.estimate.camera.clone(),
            refined: choice == HandEyeChoice::Refined,
            estimated: obs.estimated_intrinsics.clone(),
            pose_error: None,
        };
        println!("{}", camera.describe());
    }
    log_hand_eye_run(&recorder, &ds, &obs, &run.result)?;
    finish_recording(recorder);
    println!("wrote {}", out.display());
    Ok(())
}

fn main() -> std::process::ExitCode {
    init_logging();
    let cli = Cli::parse();
    run_main::<anyhow::Error>(|| match cli.command {
        Command::Run(args) => run(args),
        Command::Auto(args) => auto(args),
        Command::Watch(args) => watch(args),
        Command::Handeye(args) => handeye(args),
    })
}

b2b_services::every_flag_has_help!(Cli);
