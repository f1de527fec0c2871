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
use b2b_protocol::Pose;
use b2b_robot::{Arm, IiwaModel, WorkspaceBox};
use kuka_fri::{FriClient, FriClientConfig, SafetyGuard};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::live::{FrameSource, LiveConfig, LiveMode, LiveSource, LiveTarget};
use crate::plan::PlanConfig;

/// The calibration board of a cell.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetSetup {
    /// Inner corners `[columns, rows]` of the checkerboard.
    pub inner_corners: [u32; 2],
    pub square_m: f64,
}

/// One cart's setup (`--setup FILE`, JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellSetup {
    pub model: IiwaModel,
    pub target: TargetSetup,
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
}

fn default_margin() -> f64 {
    5f64.to_radians()
}

fn default_speed() -> f64 {
    1.0
}

impl CellSetup {
    /// Reads a setup file.
    pub fn load(file: &Path) -> anyhow::Result<Self> {
        let setup: CellSetup = crate::read_json(file)?;
        setup.check().with_context(|| file.display().to_string())?;
        Ok(setup)
    }

    fn check(&self) -> anyhow::Result<()> {
        self.base_from_target_approx
            .to_isometry("T_base_target_approx")?;
        self.flange_from_camera_approx
            .to_isometry("T_flange_camera_approx")?;
        WorkspaceBox::new(self.workspace_min, self.workspace_max)?;
        anyhow::ensure!(
            self.target.inner_corners.iter().all(|&n| n >= 2)
                && self.target.square_m.is_finite()
                && self.target.square_m > 0.0,
            "target: inner_corners must be >= 2 each and square_m > 0"
        );
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

    /// The setup of `robot` in a simulator scene, with the board position off by
    /// 2 cm / 4 deg and the mount by 5 mm / 2 deg (what a setup sheet and a drawing
    /// give), so that nothing the agent plans with is the truth.
    pub fn from_scene(scene_file: &Path, robot: &str) -> anyhow::Result<Self> {
        let scene = b2b_sim::scene::Scene::load(scene_file)?;
        let r = scene
            .robots
            .iter()
            .position(|s| s.id == robot)
            .with_context(|| format!("robot '{robot}' is not in {}", scene_file.display()))?;
        let spec = &scene.robots[r];
        let board_spec = scene.board.as_ref().with_context(|| {
            format!(
                "{}: the live routine needs a checkerboard scene (other targets are not wired to it yet)",
                scene_file.display()
            )
        })?;
        let base1_from_target = board_spec
            .base1_from_target
            .to_iso(scene_file, "board.base1_from_target")?;
        let base1_from_base = if r == 0 {
            Isometry3::identity()
        } else {
            scene
                .base1_from_base2
                .to_iso(scene_file, "base1_from_base2")?
        };
        let off = |t: [f64; 3], axis: [f64; 3], deg: f64| {
            Isometry3::from_parts(
                Translation3::new(t[0], t[1], t[2]),
                UnitQuaternion::from_scaled_axis(
                    Vector3::from(axis).normalize() * deg.to_radians(),
                ),
            )
        };
        let board = base1_from_base.inverse()
            * base1_from_target
            * off([0.015, -0.012, 0.004], [0.3, 1.0, 0.2], 4.0);
        let mount = spec
            .flange_from_camera
            .to_iso(scene_file, &format!("robots[{r}].flange_from_camera"))?
            * off([0.003, -0.003, 0.002], [1.0, -0.4, 0.3], 2.0);
        Ok(CellSetup {
            model: spec.model,
            target: TargetSetup {
                inner_corners: board_spec.inner_corners,
                square_m: board_spec.square_m,
            },
            base_from_target_approx: Pose::from_isometry(&board),
            flange_from_camera_approx: Pose::from_isometry(&mount),
            workspace_min: [-0.3, -0.9, 0.12],
            workspace_max: [1.1, 0.9, 1.3],
            joint_margin_rad: default_margin(),
            speed_fraction: default_speed(),
        })
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

/// The scene file of `--sim`, and the cart process it starts.
#[derive(Debug, Clone)]
pub struct SimCart {
    pub scene: PathBuf,
    pub seed: u64,
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
    let target = LiveTarget::checkerboard(
        setup.target.inner_corners[0] as usize,
        setup.target.inner_corners[1] as usize,
        setup.target.square_m,
    )?;
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
