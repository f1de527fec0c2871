//! Starting the simulated cart, its own binary next to the simulator
//! (`b2b-sim-cart`): the setup it derives for an agent, and the running cart as a
//! child process. The agent's `--sim` and the end-to-end tests use this one way in.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use crate::{Result, ServiceError};

/// The simulated cart's binary: `B2B_SIM_CART`, or `b2b-sim-cart` beside this
/// process's own executable (cargo builds the agent and the cart into one folder).
pub fn exe() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("B2B_SIM_CART") {
        return Ok(PathBuf::from(p));
    }
    let own = std::env::current_exe().map_err(ServiceError::OwnExecutable)?;
    let cart = own.with_file_name(format!("b2b-sim-cart{}", std::env::consts::EXE_SUFFIX));
    if !cart.is_file() {
        return Err(ServiceError::NoCartBinary { path: cart });
    }
    Ok(cart)
}

/// What `b2b-sim-cart setup` prints.
#[derive(Debug, serde::Deserialize)]
struct SetupAnswer {
    setup: PathBuf,
}

/// Runs `exe setup` for `robot` of `scene` into `dir`: the setup file the cart
/// derived (board and mount off by a setup sheet's error; the target's files
/// beside it).
pub fn derive_setup(exe: &Path, scene: &Path, robot: &str, dir: &Path) -> Result<PathBuf> {
    let out = Command::new(exe)
        .args(["setup", "--robot", robot, "--scene"])
        .arg(scene)
        .arg("--dir")
        .arg(dir)
        .stdin(Stdio::null())
        .output()
        .map_err(|source| ServiceError::CartStart {
            exe: exe.to_owned(),
            source,
        })?;
    if !out.status.success() {
        return Err(ServiceError::CartRefused {
            scene: scene.to_owned(),
            stderr: String::from_utf8_lossy(&out.stderr).trim().to_owned(),
        });
    }
    let answer: SetupAnswer =
        serde_json::from_slice(&out.stdout).map_err(|source| ServiceError::CartAnswer {
            stdout: String::from_utf8_lossy(&out.stdout).trim().to_owned(),
            source,
        })?;
    Ok(answer.setup)
}

/// Where and how a simulated cart runs.
#[derive(Debug, Clone)]
pub struct CartRun<'a> {
    pub scene: &'a Path,
    pub robot: &'a str,
    /// The agent's FRI client address, which the cart's FRI server answers.
    pub client: SocketAddr,
    /// The arm's realisation (its errors) and sensor noise.
    pub seed: u64,
    /// The iceoryx2 service root the camera renders into.
    pub camera_prefix: &'a str,
    /// A folder the cart watches for commands (`b2b-sim-cart bump`).
    pub control: Option<&'a Path>,
}

/// A running simulated cart; killed when dropped, and the folder of the setup
/// derived for it (when the agent derived one) removed.
#[derive(Debug)]
pub struct CartProcess {
    child: std::process::Child,
    derived_setup: Option<std::path::PathBuf>,
}

impl CartProcess {
    /// Removes `dir` (the derived setup and the target's files) with the cart.
    pub fn owning(mut self, dir: Option<std::path::PathBuf>) -> Self {
        self.derived_setup = dir;
        self
    }
}

impl Drop for CartProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if let Some(dir) = &self.derived_setup {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

/// Starts `exe run` for `run`.
pub fn spawn(exe: &Path, run: &CartRun<'_>) -> Result<CartProcess> {
    let child = Command::new(exe)
        .args(["run", "--robot", run.robot, "--client"])
        .arg(run.client.to_string())
        .arg("--scene")
        .arg(run.scene)
        .args(["--seed", &run.seed.to_string()])
        .args(["--camera-prefix", run.camera_prefix])
        .args(
            run.control
                .iter()
                .flat_map(|c| [std::ffi::OsStr::new("--control"), c.as_os_str()]),
        )
        .stdin(Stdio::null())
        .spawn()
        .map_err(|source| ServiceError::CartStart {
            exe: exe.to_owned(),
            source,
        })?;
    Ok(CartProcess {
        child,
        derived_setup: None,
    })
}
