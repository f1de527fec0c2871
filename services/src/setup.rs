//! What an agent must be told about its cell before it moves an arm: the arm model,
//! the target's geometry, where the board roughly is and how the camera is roughly
//! mounted (a setup sheet and the mount's drawing: approximations, refined by the
//! calibration itself), and the safe workspace. Given as `--setup FILE` for a real
//! cart; for the simulated cart it is derived from the scene file with the board
//! position and the mount deliberately off by a setup sheet's error, so the agent
//! never plans with the truth.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use b2b_dataset::Target;
use b2b_protocol::Pose;
use b2b_robot::{Arm, IiwaModel, WorkspaceBox};
use kuka_fri::{FriClient, FriClientConfig, SafetyGuard};
use serde::{Deserialize, Serialize};

use b2b_routine::Mode;

use crate::{Result, ServiceError};
use b2b_live::{FrameSource, IceoryxFrames, LiveConfig, LiveSource};
use b2b_routine::plan::PlanConfig;

/// One cart's setup (`--setup FILE`, JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellSetup {
    pub model: IiwaModel,
    /// The target, exactly as `dataset.json` describes it (`kind`: checkerboard,
    /// charuco, aruco_grid, multimarker); a multimarker file's relative path is
    /// taken from the setup file's folder.
    pub target: Target,
    /// Roughly where the board is in this robot's base.
    #[serde(rename = "T_base_target_approx")]
    pub base_from_target_approx: Pose,
    /// Roughly how the camera is mounted (the drawing).
    #[serde(rename = "T_flange_camera_approx")]
    pub flange_from_camera_approx: Pose,
    /// The box (robot base frame, m) the flange must stay in.
    pub workspace_min: [f64; 3],
    pub workspace_max: [f64; 3],
    /// Commands stay this far inside every joint limit, rad.
    #[serde(default = "default_margin")]
    pub joint_margin_rad: f64,
    /// Fraction of the rated joint velocities and accelerations the routine uses.
    #[serde(default = "default_speed")]
    pub speed_fraction: f64,
    /// The camera process publishes a depth image with each colour frame (a
    /// RealSense does; a simulated scene without `depth` does not).
    #[serde(default = "default_depth")]
    pub depth: bool,
    /// The file this setup was read from (or stands for), which relative paths
    /// in it are taken from.
    #[serde(skip)]
    pub source: PathBuf,
}

/// Default of `joint_margin_rad`.
pub fn default_margin() -> f64 {
    5f64.to_radians()
}

/// Default of `speed_fraction`.
pub fn default_speed() -> f64 {
    1.0
}

/// Default of `depth`.
pub fn default_depth() -> bool {
    true
}

impl CellSetup {
    /// Reads a setup file.
    pub fn load(file: &Path) -> Result<Self> {
        let mut setup: CellSetup = crate::read_json(file)?;
        setup.source = file.to_owned();
        setup.check().map_err(|e| e.in_file(file))?;
        Ok(setup)
    }

    /// The target, read as a dataset's is ([`b2b_pipeline::target_from_manifest`]:
    /// one model for datasets and live agents). A target with a symmetry (a
    /// checkerboard with `cols + rows` even) is labelled capture by capture from
    /// `T_base_target_approx` (the live source's detection): for such a board the
    /// setup sheet must also say which corner is the origin, and both carts' sheets
    /// the same corner.
    pub fn read_target(&self) -> Result<b2b_vision::Target> {
        Ok(b2b_pipeline::target_from_manifest(
            &self.target,
            &self.source,
        )?)
    }

    /// Refuses a setup that cannot be used (bad poses, target, margin or speed).
    pub fn check(&self) -> Result<()> {
        self.base_from_target_approx
            .to_isometry("T_base_target_approx")?;
        self.flange_from_camera_approx
            .to_isometry("T_flange_camera_approx")?;
        WorkspaceBox::new(self.workspace_min, self.workspace_max)?;
        b2b_pipeline::target_from_manifest(&self.target, &self.source)
            .map_err(|e| ServiceError::SetupTarget(Box::new(e)))?;
        if !(self.joint_margin_rad.is_finite() && (0.0..0.5).contains(&self.joint_margin_rad)) {
            return Err(ServiceError::JointMargin {
                value: self.joint_margin_rad,
            });
        }
        if !(self.speed_fraction.is_finite()
            && self.speed_fraction > 0.0
            && self.speed_fraction <= 1.0)
        {
            return Err(ServiceError::SpeedFraction {
                value: self.speed_fraction,
            });
        }
        Ok(())
    }

    /// The safety guard every command passes: joint limits with the margin, rated
    /// velocities scaled, the flange inside the workspace box (nominal kinematics).
    pub fn guard(&self) -> Result<SafetyGuard> {
        let arm = Arm::new(self.model);
        let limits = arm.limits.scaled(self.speed_fraction)?;
        let guard = SafetyGuard::new(
            limits,
            WorkspaceBox::new(self.workspace_min, self.workspace_max)?,
            arm,
        )?
        .with_position_margin(self.joint_margin_rad)?;
        Ok(guard)
    }
}

/// How the agent reaches the arm and the camera.
#[derive(Debug, Clone)]
pub struct Connection {
    /// Where the FRI client binds (the cell's client port).
    pub bind: SocketAddr,
    /// The controller's address, when known (datagrams from others are ignored).
    pub controller: Option<SocketAddr>,
    /// The iceoryx2 service root of the camera (`b2b/camera`).
    pub camera_prefix: String,
}

/// Builds the live source: FRI client (with the guard) and frame subscriber.
pub fn live_source(
    setup: &CellSetup,
    robot: &str,
    mode: Mode,
    plan: PlanConfig,
    fri: FriClient,
    frames: Box<dyn FrameSource>,
    features: Option<b2b_pipeline::rgbd::RgbdOptions>,
) -> Result<LiveSource> {
    let target = setup.read_target()?;
    let cfg = LiveConfig {
        robot: robot.to_owned(),
        mode,
        plan,
        board_approx: setup
            .base_from_target_approx
            .to_isometry("T_base_target_approx")?,
        mount_approx: setup
            .flange_from_camera_approx
            .to_isometry("T_flange_camera_approx")?,
        still_window: Duration::from_millis(250),
        still_tol_rad: 2e-4,
        settle_timeout: Duration::from_secs(10),
        frame_timeout: Duration::from_secs(20),
        features,
    };
    LiveSource::connect(
        cfg,
        fri,
        frames,
        Arm::new(setup.model),
        setup.guard()?,
        target,
    )
    .map_err(ServiceError::from)
}

/// Starts the FRI client for `setup` on `conn`.
pub fn fri_client(setup: &CellSetup, conn: &Connection) -> Result<FriClient> {
    let mut config = FriClientConfig::new(conn.bind);
    config.controller = conn.controller;
    FriClient::start(config, setup.guard()?).map_err(|source| ServiceError::FriStart {
        bind: conn.bind,
        source: Box::new(source),
    })
}

/// Options of the live sources (`--sim`, `--fri`) of `agent run` and `agent auto`.
#[derive(clap::Args, Debug, Clone)]
pub struct LiveArgs {
    /// Cell setup (JSON: arm model, target, approximate board and mount, workspace
    /// box, whether the camera has depth); required with --fri, derived from the
    /// scene with --sim.
    #[arg(long)]
    pub setup: Option<PathBuf>,
    /// Where the FRI client binds (the cell's client port).
    #[arg(long, default_value = "0.0.0.0:30200")]
    pub fri_bind: SocketAddr,
    /// The camera's iceoryx2 service root.
    #[arg(long, default_value = "b2b/camera")]
    pub camera_prefix: String,
    /// Viewpoints to plan.
    #[arg(long, default_value_t = 30, value_parser = crate::whole_count, allow_negative_numbers = true)]
    pub count: usize,
    /// Seed of the simulated cart (its robot errors and sensor noise).
    #[arg(long, default_value_t = 1, value_parser = crate::whole_number, allow_negative_numbers = true)]
    pub seed: u64,
    /// Simulated cart only: a folder the cart watches for commands (a bump of
    /// its base: `b2b-sim-cart bump --control DIR --robot ID --t-mm x,y,z`).
    #[arg(long)]
    pub sim_control: Option<PathBuf>,
    #[command(flatten)]
    pub noise: crate::RobotNoiseArgs,
}

/// Where a live agent's arm and camera are.
#[derive(Debug, Clone, Copy)]
pub enum Cart<'a> {
    /// The simulated cart of a scene file, started as a child process.
    Sim(&'a Path),
    /// A real controller over KUKA FRI at `HOST:PORT`.
    Fri(&'a str),
}

impl<'a> Cart<'a> {
    /// From `--sim` / `--fri` (clap keeps them exclusive).
    pub fn from_flags(sim: Option<&'a Path>, fri: Option<&'a str>) -> Result<Self> {
        match (sim, fri) {
            (Some(scene), None) => Ok(Self::Sim(scene)),
            (None, Some(addr)) => Ok(Self::Fri(addr)),
            _ => Err(ServiceError::NoCart),
        }
    }
}

/// Connects to the arm and camera of `cart`: the live source, and for a
/// simulated cart its process (kept alive while the source is used).
pub fn connect(
    robot: &str,
    cart: Cart<'_>,
    live: &LiveArgs,
    mode: Mode,
    features: Option<b2b_vision::features::FeatureKind>,
) -> Result<(LiveSource, Option<crate::sim_cart::CartProcess>)> {
    b2b_protocol::messages::validate_cart_id(robot)?;
    b2b_frames::quiet_iceoryx2_logs();
    let plan = PlanConfig {
        count: live.count,
        ..Default::default()
    };
    let cart_exe = match cart {
        Cart::Sim(_) => Some(crate::sim_cart::exe()?),
        Cart::Fri(_) => None,
    };
    // The folder of a setup derived here, removed with the cart.
    let mut derived = None;
    let (setup, conn) = match cart {
        Cart::Sim(scene) => {
            let setup = match &live.setup {
                Some(f) => CellSetup::load(f)?,
                // The simulated cart's own binary derives the setup from the scene
                // (board and mount off by a setup sheet's error); the target's
                // files go into a folder of this agent process.
                None => {
                    let dir = std::env::temp_dir()
                        .join(format!("b2b-agent-{}-{robot}", std::process::id()));
                    let exe = match &cart_exe {
                        Some(exe) => exe.clone(),
                        None => crate::sim_cart::exe()?,
                    };
                    let file = crate::sim_cart::derive_setup(&exe, scene, robot, &dir);
                    derived = Some(dir);
                    CellSetup::load(&file?)?
                }
            };
            // A unique service root per run, so two simulated cells never mix.
            let conn = Connection {
                bind: SocketAddr::from(([127, 0, 0, 1], 0)),
                controller: None,
                camera_prefix: format!("{}/sim{}", live.camera_prefix, std::process::id()),
            };
            (setup, conn)
        }
        Cart::Fri(addr) => {
            let file = live.setup.as_ref().ok_or(ServiceError::FriNeedsSetup)?;
            let controller: SocketAddr =
                addr.parse().map_err(|source| ServiceError::FriAddress {
                    addr: addr.to_owned(),
                    source,
                })?;
            let conn = Connection {
                bind: live.fri_bind,
                controller: Some(controller),
                camera_prefix: live.camera_prefix.clone(),
            };
            (CellSetup::load(file)?, conn)
        }
    };
    let fri = fri_client(&setup, &conn)?;
    let mut frames = IceoryxFrames::new(&conn.camera_prefix, robot)?;
    let features = features.map(b2b_pipeline::rgbd::RgbdOptions::with_kind);
    if features.is_some() && setup.depth {
        frames = frames.with_depth(&conn.camera_prefix, robot)?;
    }
    let process = match (cart, &cart_exe) {
        (Cart::Sim(scene), Some(exe)) => Some(
            crate::sim_cart::spawn(
                exe,
                &crate::sim_cart::CartRun {
                    scene,
                    robot,
                    client: fri.local_addr(),
                    seed: live.seed,
                    camera_prefix: &conn.camera_prefix,
                    control: live.sim_control.as_deref(),
                },
            )?
            .owning(derived),
        ),
        _ => None,
    };
    let source = live_source(&setup, robot, mode, plan, fri, Box::new(frames), features)?;
    Ok((source, process))
}
