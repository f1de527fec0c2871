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

use anyhow::Context;
use b2b_dataset::Target;
use b2b_pipeline::TargetSpec;
use b2b_protocol::Pose;
use b2b_robot::{Arm, IiwaModel, WorkspaceBox};
use kuka_fri::{FriClient, FriClientConfig, SafetyGuard};
use serde::{Deserialize, Serialize};

use crate::live::{FrameSource, LiveConfig, LiveMode, LiveSource, LiveTarget};
use crate::plan::PlanConfig;

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

impl CellSetup {
    /// Reads a setup file.
    pub fn load(file: &Path) -> anyhow::Result<Self> {
        let mut setup: CellSetup = crate::read_json(file)?;
        setup.source = file.to_owned();
        setup.check().with_context(|| file.display().to_string())?;
        Ok(setup)
    }

    /// The target as the pipeline knows it (one model for datasets and live
    /// agents). A target with a symmetry (a checkerboard with `cols + rows` even)
    /// is refused: the agent publishes each capture as it is taken and cannot
    /// choose its labelling from motion the way the offline pipeline does.
    pub fn target_spec(&self) -> anyhow::Result<TargetSpec> {
        let spec = TargetSpec::from_manifest(&self.target, &self.source)?;
        anyhow::ensure!(
            spec.symmetry().is_trivial(),
            "{}: a {} looks the same turned by 180°, and the live agent cannot choose its \
             labelling capture by capture; use an asymmetric board (e.g. 9x6 inner corners \
             = 10x7 squares) or a ChArUco board, or calibrate offline from a dataset",
            self.source.display(),
            spec.describe()
        );
        Ok(spec)
    }

    /// Refuses a setup that cannot be used (bad poses, target, margin or speed).
    pub fn check(&self) -> anyhow::Result<()> {
        self.base_from_target_approx
            .to_isometry("T_base_target_approx")?;
        self.flange_from_camera_approx
            .to_isometry("T_flange_camera_approx")?;
        WorkspaceBox::new(self.workspace_min, self.workspace_max)?;
        self.target_spec().context("target")?;
        anyhow::ensure!(
            self.joint_margin_rad.is_finite() && (0.0..0.5).contains(&self.joint_margin_rad),
            "joint_margin_rad must be in [0, 0.5)"
        );
        anyhow::ensure!(
            self.speed_fraction.is_finite()
                && self.speed_fraction > 0.0
                && self.speed_fraction <= 1.0,
            "speed_fraction must be in (0, 1]"
        );
        Ok(())
    }

    /// The safety guard every command passes: joint limits with the margin, rated
    /// velocities scaled, the flange inside the workspace box (nominal kinematics).
    pub fn guard(&self) -> anyhow::Result<SafetyGuard> {
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
    mode: LiveMode,
    plan: PlanConfig,
    fri: FriClient,
    frames: Box<dyn FrameSource>,
    features: Option<b2b_pipeline::rgbd::RgbdOptions>,
) -> anyhow::Result<LiveSource> {
    let target = LiveTarget::new(setup.target_spec()?);
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
}

/// Starts the FRI client for `setup` on `conn`.
pub fn fri_client(setup: &CellSetup, conn: &Connection) -> anyhow::Result<FriClient> {
    let mut config = FriClientConfig::new(conn.bind);
    config.controller = conn.controller;
    FriClient::start(config, setup.guard()?)
        .with_context(|| format!("cannot start the FRI client on {}", conn.bind))
}
