//! The service binaries' library: the coordinator's journal, the live agent
//! and coordinator loops on the bus (`b2b-bus`, re-exported as [`bus`]), the
//! live sources (FRI and iceoryx2, the simulated cart's process), the camera
//! process (replay and RealSense into iceoryx2, [`camera`]), rerun recordings,
//! and result files and printouts.
//! What is computed lives in `b2b-pipeline`; this crate wires it to processes,
//! sockets and files, and the binaries are argument parsing and wiring.

pub mod agent;
pub mod camera;
pub mod coordinator;
pub mod error;
pub mod history;
pub mod outputs;
pub mod recording;
pub mod setup;
pub mod sim_cart;
pub mod watch;

use std::path::Path;

pub use b2b_bus as bus;
pub use b2b_bus::{ACCESS_CONTROL_TARGET, AccessRefusals, LogLimiter, pki, signing, warn_limited};
pub use b2b_store as store;
pub use error::{Result, ServiceError};

/// Logs to stderr, `RUST_LOG` overriding the default level (warn); every
/// message zenoh's access control refuses is logged too ([`AccessRefusals`]).
pub fn init_logging() {
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    use tracing_subscriber::{Layer, filter::Targets};
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(DEFAULT_LOG_FILTER));
    let fmt = tracing_subscriber::fmt::layer()
        .with_writer(std::io::stderr)
        // Colour only on a terminal: a log written to a file or a pipe stays text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_filter(filter);
    let refusals = AccessRefusals
        .with_filter(Targets::new().with_target(ACCESS_CONTROL_TARGET, tracing::Level::TRACE));
    let _ = tracing_subscriber::registry()
        .with(fmt)
        .with(refusals)
        .try_init();
}

/// What the binaries log without `RUST_LOG`: warnings, except zenoh's "Scouting
/// delay elapsed before start conditions are met", which a peer prints whenever it
/// starts before the others (the coordinator usually does); the services say
/// themselves whom they wait for.
pub const DEFAULT_LOG_FILTER: &str = "warn,zenoh::net::runtime::orchestrator=error";

/// Writes a value as pretty JSON, creating the parent folder.
pub fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(ServiceError::io("create", parent))?;
    }
    let text = serde_json::to_string_pretty(value)?;
    b2b_report::write::write_together(&[(path.to_owned(), (text + "\n").into_bytes())])?;
    Ok(())
}

/// Reads a JSON file into a value, naming the file in errors.
/// A named pipe, a device or a directory is refused without opening it (a pipe
/// would block), and so is a file over `b2b_dataset::MAX_TEXT_FILE_BYTES`.
pub fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    b2b_dataset::check_input_file(path, "expected a JSON file")?;
    let text = std::fs::read_to_string(path).map_err(ServiceError::io("read", path))?;
    serde_json::from_str(&text).map_err(|source| ServiceError::NotValidFile {
        path: path.to_owned(),
        source,
    })
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
    #[arg(long, default_value_t = 0.05, value_parser = non_negative, allow_negative_numbers = true)]
    pub robot_sigma_mm: f64,
    /// Flange rotation error per capture, 1 sigma (degrees).
    #[arg(long, default_value_t = 0.01, value_parser = non_negative, allow_negative_numbers = true)]
    pub robot_sigma_deg: f64,
    /// The arm's systematic (absolute) pose error, 1 sigma (mm): kinematic
    /// errors that do not show in the residuals. Added to the result's
    /// covariance as an error common to all captures. 0: none.
    #[arg(long, default_value_t = 0.0, value_parser = non_negative, allow_negative_numbers = true)]
    pub robot_accuracy_mm: f64,
    /// The arm's systematic orientation error, 1 sigma (degrees).
    #[arg(long, default_value_t = 0.0, value_parser = non_negative, allow_negative_numbers = true)]
    pub robot_accuracy_deg: f64,
}

impl RobotNoiseArgs {
    /// Refinement options with this noise (clap has checked each is a number >= 0).
    pub fn options(&self) -> b2b_calib::refine::RefineOptions {
        b2b_calib::refine::RefineOptions {
            systematic: b2b_calib::refine::RobotNoise {
                sigma_t_m: self.robot_accuracy_mm * 1e-3,
                sigma_r_rad: self.robot_accuracy_deg.to_radians(),
            },
            robot_noise: b2b_calib::refine::RobotNoise {
                sigma_t_m: self.robot_sigma_mm * 1e-3,
                sigma_r_rad: self.robot_sigma_deg.to_radians(),
            },
            ..Default::default()
        }
    }
}

/// Shows the pipeline's long stages (detection in every image) as progress bars
/// on stderr; drawn only when stderr is a terminal, so logs and pipes stay clean.
pub fn show_pipeline_progress() {
    #[derive(Debug, Default)]
    struct Bars(std::sync::Mutex<Option<indicatif::ProgressBar>>);
    impl b2b_pipeline::progress::ProgressSink for Bars {
        fn begin(&self, what: &str, total: u64) {
            let bar = indicatif::ProgressBar::new(total).with_prefix(what.to_owned());
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{prefix} [{bar:30}] {pos}/{len} ({elapsed})",
                )
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
            );
            if let Ok(mut b) = self.0.lock() {
                *b = Some(bar);
            }
        }
        fn step(&self) {
            if let Ok(b) = self.0.lock()
                && let Some(bar) = b.as_ref()
            {
                bar.inc(1);
            }
        }
        fn end(&self) {
            if let Ok(mut b) = self.0.lock()
                && let Some(bar) = b.take()
            {
                bar.finish_and_clear();
            }
        }
    }
    b2b_pipeline::progress::set_sink(Box::new(Bars::default()));
}

/// clap's parser of a number that must be finite and `>= 0` (sigmas, tolerances).
pub fn non_negative(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        Ok(_) => Err(format!("{text} is not a number >= 0")),
        Err(e) => Err(format!("{text}: {e}")),
    }
}

/// clap's parser of a whole number `>= 0` (counts, milliseconds); with
/// `allow_negative_numbers` on the flag, `-1` reaches it and is refused naming
/// the flag, not taken for another flag.
pub fn whole_number(text: &str) -> Result<u64, String> {
    match text.parse::<i128>() {
        Ok(v) if v < 0 => Err(format!("{text} is not a whole number >= 0")),
        Ok(v) => u64::try_from(v).map_err(|_| format!("{text} is too large")),
        Err(_) => Err(format!("{text} is not a whole number >= 0")),
    }
}

/// [`whole_number`] as a `usize`.
pub fn whole_count(text: &str) -> Result<usize, String> {
    whole_number(text).and_then(|v| usize::try_from(v).map_err(|_| format!("{text} is too large")))
}

/// clap's parser of a number that must be finite and `> 0` (rates, durations).
pub fn positive(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        Ok(_) => Err(format!("{text} is not a number > 0")),
        Err(e) => Err(format!("{text}: {e}")),
    }
}

/// clap's parser of two different robot ids `a,b` (`verify --pair`).
pub fn robot_pair(text: &str) -> Result<(String, String), String> {
    let Some((a, b)) = text.split_once(',') else {
        return Err(format!(
            "'{text}' is not two robot ids separated by a comma, e.g. robot1,robot3"
        ));
    };
    let (a, b) = (a.trim(), b.trim());
    if a.is_empty() || b.is_empty() || b.contains(',') {
        return Err(format!(
            "'{text}' is not two robot ids separated by a comma, e.g. robot1,robot3"
        ));
    }
    if a == b {
        return Err(format!("'{text}': a pair needs two different robots"));
    }
    Ok((a.to_owned(), b.to_owned()))
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

/// An outcome that is not a failure of the command but must end it with a
/// documented exit status (`coordinator watch --until-alarm`: 3).
#[derive(Debug)]
pub struct ExitStatus {
    pub code: u8,
    pub message: String,
}

impl std::fmt::Display for ExitStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for ExitStatus {}

/// Runs a command body, printing a one-line reason and exiting non-zero on error
/// (shared/interfaces.md: never a panic, never a backtrace for bad input). The
/// binaries' error type is named at the call (`run_main::<E>`): any error that
/// shows itself as a standard error, printed with its whole chain, "a: b: c",
/// so each cause appears once. An [`ExitStatus`] in the chain ends the command
/// with its code and message instead.
pub fn run_main<E>(body: impl FnOnce() -> std::result::Result<(), E>) -> std::process::ExitCode
where
    E: AsRef<dyn std::error::Error + Send + Sync + 'static>,
{
    let Err(e) = body() else {
        return std::process::ExitCode::SUCCESS;
    };
    let e: &(dyn std::error::Error + Send + Sync + 'static) = e.as_ref();
    match exit_status(e) {
        Some(status) => {
            eprintln!("{status}");
            std::process::ExitCode::from(status.code)
        }
        None => {
            eprintln!("error: {}", b2b_pipeline::error_chain(e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// The [`ExitStatus`] an error is, or carries in its chain (a [`ServiceError`]
/// wrapping another keeps it boxed).
fn exit_status<'a>(e: &'a (dyn std::error::Error + 'static)) -> Option<&'a ExitStatus> {
    std::iter::successors(Some(e), |e| e.source()).find_map(|e| {
        let service = e
            .downcast_ref::<ServiceError>()
            .or(e.downcast_ref::<Box<ServiceError>>().map(|b| &**b));
        match service {
            Some(ServiceError::Exit(status)) => Some(status),
            _ => e.downcast_ref::<ExitStatus>(),
        }
    })
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

/// The test every binary carries: each flag of its command line has a help text.
/// `b2b_services::every_flag_has_help!(Cli);` in a binary with a clap `Cli`.
#[macro_export]
macro_rules! every_flag_has_help {
    ($cli:ident) => {
        #[cfg(test)]
        mod every_flag_has_help {
            #[test]
            fn every_flag_has_help() {
                let missing =
                    $crate::undocumented_args(&<super::$cli as ::clap::CommandFactory>::command());
                assert!(missing.is_empty(), "flags without help: {missing:?}");
            }
        }
    };
}
