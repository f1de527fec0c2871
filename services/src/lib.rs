//! The service binaries' library: the zenoh bus, the coordinator's journal, the
//! live agent and coordinator loops, and result files. What is computed lives in
//! `b2b-pipeline`; this crate wires it to processes, sockets and files.

pub mod agent;
pub mod bus;
pub mod coordinator;
pub mod outputs;
pub mod store;

use std::path::Path;

use anyhow::Context;

/// Logs to stderr, `RUST_LOG` overriding the default level (warn).
pub fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// Writes a value as pretty JSON, creating the parent folder.
pub fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> anyhow::Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("cannot create {}", parent.display()))?;
    }
    let text = serde_json::to_string_pretty(value)?;
    std::fs::write(path, text + "\n").with_context(|| format!("cannot write {}", path.display()))
}

/// Reads a JSON file into a value, naming the file in errors.
pub fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> anyhow::Result<T> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    serde_json::from_str(&text)
        .with_context(|| format!("{}: not a valid file of this kind", path.display()))
}

/// The robot pose noise every estimating command takes: one standard deviation
/// of the flange pose error per capture. The default is the iiwa's repeatability;
/// give the arm's absolute accuracy when its kinematic model is not calibrated
/// (systematic error biases a fit without showing in its residuals).
#[derive(Debug, Clone, Copy, clap::Args)]
pub struct RobotNoiseArgs {
    /// Flange translation error per capture, 1 sigma (mm).
    #[arg(long, default_value_t = 0.05)]
    pub robot_sigma_mm: f64,
    /// Flange rotation error per capture, 1 sigma (degrees).
    #[arg(long, default_value_t = 0.01)]
    pub robot_sigma_deg: f64,
}

impl RobotNoiseArgs {
    /// Refinement options with this noise.
    pub fn options(&self) -> anyhow::Result<b2b_calib::refine::RefineOptions> {
        anyhow::ensure!(
            self.robot_sigma_mm.is_finite() && self.robot_sigma_mm >= 0.0,
            "--robot-sigma-mm must be a number >= 0"
        );
        anyhow::ensure!(
            self.robot_sigma_deg.is_finite() && self.robot_sigma_deg >= 0.0,
            "--robot-sigma-deg must be a number >= 0"
        );
        Ok(b2b_calib::refine::RefineOptions {
            robot_noise: b2b_calib::refine::RobotNoise {
                sigma_t_m: self.robot_sigma_mm * 1e-3,
                sigma_r_rad: self.robot_sigma_deg.to_radians(),
            },
            ..Default::default()
        })
    }
}

/// A flag set by Ctrl-C (SIGINT/SIGTERM), for loops that stop gracefully.
pub fn stop_flag() -> std::sync::Arc<std::sync::atomic::AtomicBool> {
    let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let f = std::sync::Arc::clone(&flag);
    if let Err(e) = ctrlc::set_handler(move || f.store(true, std::sync::atomic::Ordering::SeqCst)) {
        tracing::warn!("no Ctrl-C handler: {e}");
    }
    flag
}

/// Runs a command body, printing a one-line reason and exiting non-zero on error
/// (shared/interfaces.md: never a panic, never a backtrace for bad input).
pub fn run_main(body: impl FnOnce() -> anyhow::Result<()>) -> std::process::ExitCode {
    match body() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            let chain: Vec<String> = e.chain().map(|c| c.to_string()).collect();
            eprintln!("error: {}", chain.join(": "));
            std::process::ExitCode::FAILURE
        }
    }
}
