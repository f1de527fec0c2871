//! `b2b-sim-cart`: the simulated cart as its own process, next to the simulator.
//! `agent run --sim` and `agent auto --sim` start it; the agent then talks to it
//! exactly as to a real cart (FRI over UDP, frames from iceoryx2) and never links
//! the simulator.
//!
//! - `b2b-sim-cart setup --scene FILE --robot ID --dir DIR` writes the cell setup
//!   the agent is given for this cart (`DIR/setup-ID.json`, and the target's
//!   files; `depth` says whether the camera renders depth) and prints
//!   `{"setup": path}`.
//! - `b2b-sim-cart run --scene FILE --robot ID --client ADDR` runs the cart: an
//!   FRI server answering `ADDR` and the camera rendering into iceoryx2.

mod cart;
mod setup;

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "b2b-sim-cart",
    version,
    about = "The simulated cart: an iiwa behind a real FRI server and a rendering camera"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Write the cell setup an agent is given for this cart (board and mount
    /// deliberately off by a setup sheet's error) and print where it is.
    Setup {
        /// The simulator scene file.
        #[arg(long)]
        scene: PathBuf,
        /// The robot id in the scene.
        #[arg(long)]
        robot: String,
        /// Folder for `setup-ROBOT.json` and the target's files.
        #[arg(long)]
        dir: PathBuf,
    },
    /// Run the cart until its FRI client is silent for 5 s or Ctrl-C.
    Run {
        /// The simulator scene file.
        #[arg(long)]
        scene: PathBuf,
        /// The robot id in the scene.
        #[arg(long)]
        robot: String,
        /// The FRI client's (the agent's) address.
        #[arg(long)]
        client: std::net::SocketAddr,
        /// Where the FRI server binds.
        #[arg(long, default_value = "127.0.0.1:0")]
        bind: std::net::SocketAddr,
        /// Seed of the arm's realisation (the same as `sim generate`'s) and noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// iceoryx2 service root of the camera.
        #[arg(long, default_value = "b2b/camera")]
        camera_prefix: String,
        /// A folder the cart watches for commands (`bump`, `take-target`).
        #[arg(long)]
        control: Option<PathBuf>,
    },
    /// Bump a running cart: its base moves by the given offset (in its own base
    /// frame) at its next frame, as when someone knocks into a wheeled cart.
    Bump {
        /// The folder the cart was started with (`run --control`).
        #[arg(long)]
        control: PathBuf,
        /// The robot id of the cart.
        #[arg(long)]
        robot: String,
        /// The shift, mm: x,y,z.
        #[arg(long, value_delimiter = ',', default_value = "0,0,0")]
        t_mm: Vec<f64>,
        /// The turn, degrees: roll,pitch,yaw.
        #[arg(long, value_delimiter = ',', default_value = "0,0,0")]
        rpy_deg: Vec<f64>,
    },
    /// Take the target away: every cart started with this control folder
    /// renders the scene without it from its next frame on, as when the board
    /// is carried off after calibration.
    TakeTarget {
        /// The folder the carts were started with (`run --control`).
        #[arg(long)]
        control: PathBuf,
    },
}

fn main() -> std::process::ExitCode {
    b2b_services::run_main::<anyhow::Error>(|| {
        let cli = Cli::parse();
        b2b_services::init_logging();
        match cli.command {
            Command::Setup { scene, robot, dir } => {
                let setup = setup::cell_setup(&scene, &robot, &dir)?;
                let file = dir.join(format!("setup-{robot}.json"));
                std::fs::write(&file, serde_json::to_string_pretty(&setup)?)
                    .with_context(|| format!("cannot write {}", file.display()))?;
                println!("{}", serde_json::json!({ "setup": file }));
                Ok(())
            }
            Command::Run {
                scene,
                robot,
                client,
                bind,
                seed,
                camera_prefix,
                control,
            } => {
                b2b_frames::quiet_iceoryx2_logs();
                let stop = b2b_services::stop_flag();
                let s = b2b_sim::scene::Scene::load(&scene)?;
                let r = s
                    .robots
                    .iter()
                    .position(|x| x.id == robot)
                    .with_context(|| format!("robot '{robot}' is not in {}", scene.display()))?;
                let camera = s.camera(r)?;
                let mut sink =
                    cart::IceoryxSink::new(&camera_prefix, &robot, &camera, s.depth.is_some())?;
                let opts = cart::CartOptions {
                    scene,
                    robot,
                    client,
                    bind,
                    seed,
                    send_period_ms: 5,
                    idle_timeout: Duration::from_secs(5),
                    control,
                    frame_period: cart::FRAME_PERIOD,
                };
                cart::run_cart(&opts, &mut sink, &stop)?;
                Ok(())
            }
            Command::Bump {
                control,
                robot,
                t_mm,
                rpy_deg,
            } => {
                b2b_protocol::messages::validate_cart_id(&robot)?;
                anyhow::ensure!(
                    t_mm.len() == 3
                        && rpy_deg.len() == 3
                        && t_mm.iter().chain(&rpy_deg).all(|v| v.is_finite()),
                    "--t-mm and --rpy-deg take three finite numbers each, e.g. 1,0,0"
                );
                let spec = serde_json::json!({
                    "t": [t_mm[0] * 1e-3, t_mm[1] * 1e-3, t_mm[2] * 1e-3],
                    "rpy_deg": rpy_deg,
                });
                let file = cart::bump_file(&control, &robot);
                // Written whole, then renamed, so the cart never reads half a file.
                let tmp = file.with_extension("tmp");
                std::fs::write(&tmp, spec.to_string())
                    .with_context(|| format!("cannot write {}", tmp.display()))?;
                std::fs::rename(&tmp, &file)
                    .with_context(|| format!("cannot write {}", file.display()))?;
                println!("{}", serde_json::json!({ "bump": file }));
                Ok(())
            }
            Command::TakeTarget { control } => {
                let file = cart::target_taken_file(&control);
                std::fs::write(&file, "")
                    .with_context(|| format!("cannot write {}", file.display()))?;
                println!("{}", serde_json::json!({ "target_taken": file }));
                Ok(())
            }
        }
    })
}

b2b_services::every_flag_has_help!(Cli);
