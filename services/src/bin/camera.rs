//! `camera`: owns one cart's camera and publishes its colour and depth frames into
//! iceoryx2 shared memory (`b2b/camera/{robot}/colour` and `.../depth`, see
//! `b2b-frames`). Sources: `--replay DIR` (a b2b-dataset/1 folder's images and
//! depth images for `--robot`, decoded straight into the loaned samples) and
//! `--realsense` (cargo feature `realsense`). The simulator's renderer publishes
//! through the same `FramePublisher` from its own process.
//!
//! On exit it prints one JSON line on stdout: frames sent per stream, wall time and
//! the slowest single publish (a slow subscriber must never make this grow).

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::{Context, bail, ensure};
use b2b_dataset::Dataset;
use b2b_frames::png::PngImage;
use b2b_frames::{FrameHeader, FramePublisher, Stream, StreamKind, service_name_in};
use b2b_services::{init_logging, run_main, stop_flag};
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

/// One stream's publisher and its counters.
struct Out {
    publisher: FramePublisher,
    slowest: Duration,
}

impl Out {
    fn new(cli: &Cli, stream: Stream, max_bytes: usize) -> anyhow::Result<Out> {
        let name = service_name_in(&cli.prefix, &cli.robot, stream);
        Ok(Out {
            publisher: FramePublisher::new(&name, max_bytes)?,
            slowest: Duration::ZERO,
        })
    }

    fn publish_png(&mut self, png: PngImage, header: &FrameHeader) -> anyhow::Result<()> {
        let t0 = Instant::now();
        self.publisher
            .try_publish_with(header, |buf| png.decode_into(buf))?;
        self.slowest = self.slowest.max(t0.elapsed());
        Ok(())
    }

    fn summary(out: Option<&Out>) -> serde_json::Value {
        match out {
            Some(o) => serde_json::json!({
                "service": o.publisher.service_name(),
                "sent": o.publisher.sent(),
                "slowest_publish_us": o.slowest.as_secs_f64() * 1e6,
            }),
            None => serde_json::Value::Null,
        }
    }
}

/// A capture's files, checked before the first frame goes out.
struct Item {
    image: Option<PathBuf>,
    depth: Option<PathBuf>,
}

/// Intrinsics and depth unit from the manifest, applied to every header.
struct Calib {
    camera: Option<([f64; 4], [f64; 5], u32, u32)>,
    depth_unit_m: Option<f64>,
}

impl Calib {
    fn of(dataset: &Dataset, robot: &str) -> anyhow::Result<Calib> {
        let manifest = dataset
            .robot_manifest(robot)
            .with_context(|| format!("robot {robot} is not in the dataset"))?;
        let camera = match &manifest.camera {
            None => None,
            Some(c) => {
                if c.dist.iter().skip(5).any(|v| *v != 0.0) {
                    bail!(
                        "{}: robot {robot}: distortion has {} coefficients; frames carry k1 k2 p1 p2 k3 only",
                        dataset.root.join(b2b_dataset::MANIFEST_FILE).display(),
                        c.dist.len()
                    );
                }
                let mut dist = [0.0; 5];
                for (d, v) in dist.iter_mut().zip(&c.dist) {
                    *d = *v;
                }
                Some(([c.fx, c.fy, c.cx, c.cy], dist, c.width, c.height))
            }
        };
        Ok(Calib {
            camera,
            depth_unit_m: manifest.depth_unit_m,
        })
    }

    /// The header of an opened image, checked against the manifest; `t_ns` is
    /// its capture's time (colour and depth of one capture share it: one
    /// exposure, as the format's aligned depth means).
    fn header(
        &self,
        png: &PngImage,
        path: &Path,
        n: u64,
        t_ns: u64,
    ) -> anyhow::Result<FrameHeader> {
        let mut h = png.header();
        if let Some(([fx, fy, cx, cy], dist, w, ht)) = self.camera {
            ensure!(
                (png.width(), png.height()) == (w, ht),
                "{}: {}x{} image, but the manifest's camera is {w}x{ht}",
                path.display(),
                png.width(),
                png.height()
            );
            h = h.with_intrinsics(fx, fy, cx, cy, dist);
        }
        if png.kind() == StreamKind::Z16 {
            h.depth_unit_m = self
                .depth_unit_m
                .context("the dataset has depth images but no depth_unit_m")?;
        }
        // Depth images of the format are aligned to the colour image: the
        // extrinsic stays the identity.
        Ok(h.at(n, t_ns))
    }
}

fn replay(cli: &Cli, dir: &Path) -> anyhow::Result<serde_json::Value> {
    let dataset = Dataset::load(dir).with_context(|| format!("cannot load {}", dir.display()))?;
    let robot = dataset
        .robot(&cli.robot)
        .with_context(|| format!("{}: no robot {}", dir.display(), cli.robot))?;
    let calib = Calib::of(&dataset, &cli.robot)?;
    let items: Vec<Item> = robot
        .captures
        .iter()
        .map(|c| Item {
            image: dataset.image_path(&cli.robot, c),
            depth: dataset.depth_path(&cli.robot, c),
        })
        .filter(|i| i.image.is_some() || i.depth.is_some())
        .collect();
    ensure!(
        !items.is_empty(),
        "{}: robot {} has no images to replay",
        dir.display(),
        cli.robot
    );
    // Read every header first: sizes the samples, and a bad file fails now.
    let (mut colour_bytes, mut depth_bytes) = (0usize, 0usize);
    for item in &items {
        if let Some(p) = &item.image {
            let png = PngImage::open(p)?;
            ensure!(
                png.kind() != StreamKind::Z16,
                "{}: a 16-bit image in the image column",
                p.display()
            );
            calib.header(&png, p, 0, 0)?;
            colour_bytes = colour_bytes.max(png.header().payload_len());
        }
        if let Some(p) = &item.depth {
            let png = PngImage::open(p)?;
            ensure!(
                png.kind() == StreamKind::Z16,
                "{}: a depth image must be a 16-bit grey PNG, this is {}",
                p.display(),
                png.kind().name()
            );
            calib.header(&png, p, 0, 0)?;
            depth_bytes = depth_bytes.max(png.header().payload_len());
        }
    }
    let mut colour = (colour_bytes > 0)
        .then(|| Out::new(cli, Stream::Colour, colour_bytes))
        .transpose()?;
    let mut depth = (depth_bytes > 0)
        .then(|| Out::new(cli, Stream::Depth, depth_bytes))
        .transpose()?;

    let stop = stop_flag();
    let period = (cli.fps > 0.0).then(|| Duration::from_secs_f64(1.0 / cli.fps));
    let start = Instant::now();
    let mut next = start;
    let mut n = 0u64;
    'replay: loop {
        for item in &items {
            if stop.load(Ordering::SeqCst) || cli.frames.is_some_and(|max| n >= max) {
                break 'replay;
            }
            n += 1;
            let t_ns = b2b_frames::now_ns();
            if let (Some(p), Some(out)) = (&item.image, colour.as_mut()) {
                let png = PngImage::open(p)?;
                let h = calib.header(&png, p, n, t_ns)?;
                out.publish_png(png, &h)?;
            }
            if let (Some(p), Some(out)) = (&item.depth, depth.as_mut()) {
                let png = PngImage::open(p)?;
                let h = calib.header(&png, p, n, t_ns)?;
                out.publish_png(png, &h)?;
            }
            if let Some(period) = period {
                next += period;
                let now = Instant::now();
                if next > now {
                    std::thread::sleep(next - now);
                } else {
                    // Behind schedule (slow decoding): no burst to catch up.
                    next = now;
                }
            }
        }
        if cli.once {
            break;
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    Ok(serde_json::json!({
        "robot": cli.robot,
        "source": "replay",
        "frames": n,
        "seconds": seconds,
        "colour": Out::summary(colour.as_ref()),
        "depth": Out::summary(depth.as_ref()),
    }))
}

#[cfg(feature = "realsense")]
fn realsense(cli: &Cli) -> anyhow::Result<serde_json::Value> {
    use b2b_frames::realsense::{Played, RealSense, RealSenseOptions};
    let fps = cli.fps.round().max(1.0) as u32;
    let options = RealSenseOptions {
        serial: cli.serial.clone(),
        bag: cli.bag.clone(),
        loop_playback: !cli.once,
        fps,
        ..RealSenseOptions::default()
    };
    let mut camera = RealSense::open(&options)?;
    let recorded = *camera.recorded();
    let (colour_bytes, depth_bytes) = camera.max_bytes();
    let mut colour = Out::new(cli, Stream::Colour, colour_bytes)?;
    let mut depth = Out::new(cli, Stream::Depth, depth_bytes)?;
    let stop = stop_flag();
    let start = Instant::now();
    let mut n = 0u64;
    // Per frameset, from its arrival to its last publish (not the wait).
    let mut slowest = Duration::ZERO;
    'frames: while !stop.load(Ordering::SeqCst) && cli.frames.is_none_or(|max| n < max) {
        let events = camera.publish_next(
            &mut colour.publisher,
            &mut depth.publisher,
            Duration::from_secs(5),
        )?;
        let work = camera.last_work();
        slowest = slowest.max(work.colour + work.depth);
        for event in events {
            match event {
                Played::End => break 'frames,
                Played::Colour { .. } => n += 1,
                Played::Depth { .. } => {}
                Played::Unpaired {
                    number,
                    nearest_depth_ns,
                } => match nearest_depth_ns {
                    Some(gap) => tracing::warn!(
                        "colour frame {number}: the nearest depth frame was exposed {:.1} ms away (window {:.1} ms); published without depth",
                        gap as f64 / 1e6,
                        camera.pair_window_ns() as f64 / 1e6
                    ),
                    None => tracing::warn!(
                        "colour frame {number}: no depth frame came with it; published without depth"
                    ),
                },
            }
        }
    }
    let intrinsics = |h: &FrameHeader| {
        serde_json::json!({
            "width": h.width, "height": h.height,
            "fx": h.fx, "fy": h.fy, "cx": h.cx, "cy": h.cy, "dist": h.dist,
        })
    };
    Ok(serde_json::json!({
        "robot": cli.robot,
        "source": "realsense",
        "frames": n,
        "without_depth": camera.unpaired(),
        "slowest_frameset_us": slowest.as_secs_f64() * 1e6,
        "seconds": start.elapsed().as_secs_f64(),
        "colour": Out::summary(Some(&colour)),
        "depth": Out::summary(Some(&depth)),
        "recorded": {
            "colour": intrinsics(&recorded.colour),
            "depth": intrinsics(&recorded.depth),
            "depth_from_colour": {
                "rotation": recorded.depth.depth_from_colour_rotation,
                "translation_m": recorded.depth.depth_from_colour_translation_m,
            },
        },
    }))
}

#[cfg(not(feature = "realsense"))]
fn realsense(_: &Cli) -> anyhow::Result<serde_json::Value> {
    bail!(
        "this camera was built without RealSense support: install librealsense2 (see the README) and rebuild with `cargo build -p b2b-services --features realsense`"
    )
}

fn main() -> std::process::ExitCode {
    init_logging();
    b2b_frames::quiet_iceoryx2_logs();
    let cli = Cli::parse();
    run_main::<anyhow::Error>(|| {
        ensure!(
            cli.fps.is_finite() && cli.fps >= 0.0,
            "--fps must be a number >= 0"
        );
        let summary = match (&cli.replay, cli.realsense) {
            (Some(dir), _) => replay(&cli, dir)?,
            (None, true) => realsense(&cli)?,
            (None, false) => bail!("no source: give --replay DIR or --realsense"),
        };
        println!("{summary}");
        Ok(())
    })
}

b2b_services::every_flag_has_help!(Cli);
