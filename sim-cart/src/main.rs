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
    },
}

fn main() -> std::process::ExitCode {
    b2b_services::run_main(|| {
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
                };
                cart::run_cart(&opts, &mut sink, &stop)?;
                Ok(())
            }
        }
    })
}

b2b_services::every_flag_has_help!(Cli);
