//! The service binaries' library: the zenoh bus, the coordinator's journal, the
//! live agent and coordinator loops, and result files. What is computed lives in
//! `b2b-pipeline`; this crate wires it to processes, sockets and files.

pub mod agent;
pub mod bus;
pub mod coordinator;
pub mod live;
pub mod outputs;
pub mod plan;
pub mod setup;
pub mod store;

use std::path::Path;

use anyhow::Context;

/// Logs to stderr, `RUST_LOG` overriding the default level (warn).
pub fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(DEFAULT_LOG_FILTER));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        // Colour only on a terminal: a log written to a file or a pipe stays text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
}

/// What the binaries log without `RUST_LOG`: warnings, except zenoh's "Scouting
/// delay elapsed before start conditions are met", which a peer prints whenever it
/// starts before the others (the coordinator usually does); the services say
/// themselves whom they wait for.
pub const DEFAULT_LOG_FILTER: &str = "warn,zenoh::net::runtime::orchestrator=error";

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

/// The robot pose noise every estimating command takes. `--robot-sigma-*` is
/// the per-capture error the first fit assumes (the iiwa's repeatability); the
/// fit then estimates the noise from its residuals. `--robot-accuracy-*` is the
/// arm's systematic error when its kinematic model is not calibrated: it
/// biases a fit without showing in its residuals, so it is added to the
/// result's covariance as given.
#[derive(Debug, Clone, Copy, clap::Args)]
pub struct RobotNoiseArgs {
    /// Flange translation error per capture for the first fit, 1 sigma (mm).
    #[arg(long, default_value_t = 0.05)]
    pub robot_sigma_mm: f64,
    /// Flange rotation error per capture, 1 sigma (degrees).
    #[arg(long, default_value_t = 0.01)]
    pub robot_sigma_deg: f64,
    /// The arm's systematic (absolute) pose error, 1 sigma (mm): kinematic
    /// errors that do not show in the residuals. Added to the result's
    /// covariance as an error common to all captures. 0: none.
    #[arg(long, default_value_t = 0.0)]
    pub robot_accuracy_mm: f64,
    /// The arm's systematic orientation error, 1 sigma (degrees).
    #[arg(long, default_value_t = 0.0)]
    pub robot_accuracy_deg: f64,
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
        anyhow::ensure!(
            self.robot_accuracy_mm.is_finite() && self.robot_accuracy_mm >= 0.0,
            "--robot-accuracy-mm must be a number >= 0"
        );
        anyhow::ensure!(
            self.robot_accuracy_deg.is_finite() && self.robot_accuracy_deg >= 0.0,
            "--robot-accuracy-deg must be a number >= 0"
        );
        Ok(b2b_calib::refine::RefineOptions {
            systematic: b2b_calib::refine::RobotNoise {
                sigma_t_m: self.robot_accuracy_mm * 1e-3,
                sigma_r_rad: self.robot_accuracy_deg.to_radians(),
            },
            robot_noise: b2b_calib::refine::RobotNoise {
                sigma_t_m: self.robot_sigma_mm * 1e-3,
                sigma_r_rad: self.robot_sigma_deg.to_radians(),
            },
            ..Default::default()
        })
    }
}

/// Where a command's rerun recording goes: `--rerun-save FILE.rrd` and/or
/// `--rerun-connect ADDR` (a running viewer); neither: no recording.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct RerunArgs {
    /// Write a rerun recording of this run to FILE.rrd.
    #[arg(long, value_name = "FILE.rrd", conflicts_with = "rerun_connect")]
    pub rerun_save: Option<std::path::PathBuf>,
    /// Stream the recording to a running rerun viewer
    /// (e.g. rerun+http://127.0.0.1:9876/proxy).
    #[arg(long, value_name = "ADDR")]
    pub rerun_connect: Option<String>,
}

impl RerunArgs {
    /// The recorder these flags ask for.
    pub fn recorder(&self, app_id: &str) -> anyhow::Result<b2b_viz::Recorder> {
        Ok(match (&self.rerun_save, &self.rerun_connect) {
            (Some(path), _) => b2b_viz::Recorder::save(app_id, path)
                .with_context(|| format!("cannot write the recording {}", path.display()))?,
            (None, Some(addr)) => b2b_viz::Recorder::connect(app_id, addr)
                .with_context(|| format!("cannot stream to the rerun viewer at {addr}"))?,
            (None, None) => b2b_viz::Recorder::disabled(),
        })
    }
}

/// Closes a recording; a viewer that went away is a warning, not a failed run.
pub fn finish_recording(rec: b2b_viz::Recorder) {
    if !rec.is_enabled() {
        return;
    }
    if let Err(e) = rec.finish() {
        eprintln!(
            "warning: the rerun recording did not finish cleanly: {}",
            b2b_pipeline::error_chain(&e)
        );
    }
}

/// Logs a result (both bases, hand-eyes, uncertainty) to a recording; robot 1 is
/// the first id of `order` (default: sorted ids).
pub fn log_result(
    rec: &b2b_viz::Recorder,
    result: &b2b_protocol::CalibrationResult,
    order: Option<&[String]>,
) {
    if !rec.is_enabled() {
        return;
    }
    let ids: Vec<String> = match order {
        Some(o) if o.len() >= 2 => o.to_vec(),
        _ => result.hand_eye.keys().cloned().collect(),
    };
    if ids.len() >= 2
        && let Err(e) = rec.log_result(result, [ids[0].as_str(), ids[1].as_str()], 1.0)
    {
        tracing::warn!("rerun: {}", b2b_pipeline::error_chain(&e));
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
            // `{:#}` prints the chain "a: b: c"; every library message leaves its
            // source out, so each cause appears once.
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Every argument of `cmd` and its visible subcommands that has no help text, as
/// "subcommand --flag" (the binaries' tests require none).
pub fn undocumented_args(cmd: &clap::Command) -> Vec<String> {
    fn walk(cmd: &clap::Command, path: &str, out: &mut Vec<String>) {
        for arg in cmd.get_arguments() {
            let id = arg.get_id().as_str();
            if arg.is_hide_set() || id == "help" || id == "version" {
                continue;
            }
            if arg.get_help().is_none() && arg.get_long_help().is_none() {
                let name = arg
                    .get_long()
                    .map_or_else(|| id.to_owned(), |l| format!("--{l}"));
                out.push(format!("{path} {name}").trim().to_owned());
            }
        }
        for sub in cmd.get_subcommands() {
            if !sub.is_hide_set() {
                walk(sub, &format!("{path} {}", sub.get_name()), out);
            }
        }
    }
    let mut out = vec![];
    walk(cmd, "", &mut out);
    out
}
