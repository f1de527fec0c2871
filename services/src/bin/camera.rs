//! `camera`: owns one cart's camera and publishes its colour and depth frames into
//! iceoryx2 shared memory (`b2b/camera/{robot}/colour` and `.../depth`, see
//! `b2b-frames`). Sources: `--replay DIR` (a b2b-dataset/1 folder's images and
//! depth images for `--robot`, decoded straight into the loaned samples) and
//! `--realsense` (cargo feature `realsense`). The simulator's renderer publishes
//! through the same `FramePublisher` from its own process.
//!
//! This binary parses the flags; the camera process itself is
//! `b2b_services::camera`. On exit it prints one JSON line on stdout: frames sent
//! per stream, wall time and the slowest single publish (a slow subscriber must
//! never make this grow).

use std::path::PathBuf;

use b2b_services::camera::{CameraOptions, run};
use b2b_services::{init_logging, run_main};
use clap::Parser;

#[derive(Parser, Debug)]
#[command(
    name = "camera",
    version,
    about = "Publish a cart camera's colour and depth frames over iceoryx2 shared memory"
)]
struct Cli {
    /// Robot id (as in the dataset; used in the service names).
    #[arg(long)]
    robot: String,
    /// Replay the images and depth images of a b2b-dataset/1 folder.
    #[arg(long, conflicts_with = "realsense")]
    replay: Option<PathBuf>,
    /// A RealSense camera (needs a build with `--features realsense`).
    #[arg(long)]
    realsense: bool,
    /// With --realsense: play this librealsense .bag recording instead of a device.
    #[arg(long, requires = "realsense")]
    bag: Option<PathBuf>,
    /// With --realsense: the device's serial number (default: the first one).
    #[arg(long, requires = "realsense")]
    serial: Option<String>,
    /// Frames per second of the replay (0: as fast as possible). RealSense: the
    /// stream rate asked of the device.
    #[arg(long, default_value_t = 30.0)]
    fps: f64,
    /// Play the replay or the recording once instead of looping.
    #[arg(long)]
    once: bool,
    /// Stop after this many frames per stream.
    #[arg(long)]
    frames: Option<u64>,
    /// Root of the service names.
    #[arg(long, default_value = b2b_frames::SERVICE_PREFIX)]
    prefix: String,
}

fn main() -> std::process::ExitCode {
    init_logging();
    b2b_frames::quiet_iceoryx2_logs();
    let cli = Cli::parse();
    let options = CameraOptions {
        robot: cli.robot,
        replay: cli.replay,
        realsense: cli.realsense,
        bag: cli.bag,
        serial: cli.serial,
        fps: cli.fps,
        once: cli.once,
        frames: cli.frames,
        prefix: cli.prefix,
    };
    run_main::<anyhow::Error>(|| {
        println!("{}", run(&options)?);
        Ok(())
    })
}

b2b_services::every_flag_has_help!(Cli);
