//! The camera process (`camera` binary): one cart's camera publishing its
//! colour and depth frames into iceoryx2 shared memory (`b2b/camera/{robot}/colour`
//! and `.../depth`, see `b2b-frames`). Sources: a replay of a b2b-dataset/1
//! folder's images and depth images for one robot, decoded straight into the
//! loaned samples and paced, and a RealSense camera or `.bag` recording (cargo
//! feature `realsense`; without it, [`run`] says how to enable it). The binary
//! parses its flags into [`CameraOptions`] and prints what [`run`] returns.

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use b2b_dataset::Dataset;
use b2b_frames::png::PngImage;
use b2b_frames::{FrameHeader, FramePublisher, Stream, StreamKind, service_name_in};

use crate::{Result, ServiceError, stop_flag};

/// What the camera process is asked to do (the `camera` binary's flags).
#[derive(Debug, Clone)]
pub struct CameraOptions {
    /// Robot id (as in the dataset; used in the service names).
    pub robot: String,
    /// Replay the images and depth images of this b2b-dataset/1 folder.
    pub replay: Option<PathBuf>,
    /// A RealSense camera (when there is no replay).
    pub realsense: bool,
    /// With `realsense`: play this librealsense `.bag` recording instead of a device.
    pub bag: Option<PathBuf>,
    /// With `realsense`: the device's serial number (`None`: the first one).
    pub serial: Option<String>,
    /// Frames per second of the replay (0: as fast as possible). RealSense: the
    /// stream rate asked of the device.
    pub fps: f64,
    /// Play the replay or the recording once instead of looping.
    pub once: bool,
    /// Stop after this many frames per stream.
    pub frames: Option<u64>,
    /// Root of the service names.
    pub prefix: String,
}

/// Runs the camera process until the source ends, `frames` are sent or Ctrl-C;
/// returns its summary (the binary's one JSON line): frames sent per stream,
/// wall time and the slowest single publish (a slow subscriber must never make
/// this grow).
pub fn run(options: &CameraOptions) -> Result<serde_json::Value> {
    if !(options.fps.is_finite() && options.fps >= 0.0) {
        return Err(ServiceError::CameraFps { fps: options.fps });
    }
    match (&options.replay, options.realsense) {
        (Some(dir), _) => replay(options, dir),
        (None, true) => realsense(options),
        (None, false) => Err(ServiceError::NoCameraSource),
    }
}

/// One stream's publisher and its counters.
struct Out {
    publisher: FramePublisher,
    slowest: Duration,
}

impl Out {
    fn new(options: &CameraOptions, stream: Stream, max_bytes: usize) -> Result<Out> {
        let name = service_name_in(&options.prefix, &options.robot, stream);
        Ok(Out {
            publisher: FramePublisher::new(&name, max_bytes)?,
            slowest: Duration::ZERO,
        })
    }

    fn publish_png(&mut self, png: PngImage, header: &FrameHeader) -> Result<()> {
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
    fn of(dataset: &Dataset, robot: &str) -> Result<Calib> {
        let manifest =
            dataset
                .robot_manifest(robot)
                .ok_or_else(|| ServiceError::RobotNotInManifest {
                    robot: robot.to_owned(),
                })?;
        let camera = match &manifest.camera {
            None => None,
            Some(c) => {
                if c.dist.iter().skip(5).any(|v| *v != 0.0) {
                    return Err(ServiceError::TooManyDistortionCoefficients {
                        manifest: dataset.root.join(b2b_dataset::MANIFEST_FILE),
                        robot: robot.to_owned(),
                        count: c.dist.len(),
                    });
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
    fn header(&self, png: &PngImage, path: &Path, n: u64, t_ns: u64) -> Result<FrameHeader> {
        let mut h = png.header();
        if let Some(([fx, fy, cx, cy], dist, w, ht)) = self.camera {
            if (png.width(), png.height()) != (w, ht) {
                return Err(ServiceError::ImageNotManifestSize {
                    path: path.to_owned(),
                    size: (png.width(), png.height()),
                    manifest: (w, ht),
                });
            }
            h = h.with_intrinsics(fx, fy, cx, cy, dist);
        }
        if png.kind() == StreamKind::Z16 {
            h.depth_unit_m = self.depth_unit_m.ok_or(ServiceError::NoDatasetDepthUnit)?;
        }
        // Depth images of the format are aligned to the colour image: the
        // extrinsic stays the identity.
        Ok(h.at(n, t_ns))
    }
}

/// Replays `dir`'s images and depth images of the robot, paced at `fps`.
fn replay(options: &CameraOptions, dir: &Path) -> Result<serde_json::Value> {
    let robot_id = &options.robot;
    let dataset = Dataset::load(dir).map_err(|source| ServiceError::LoadDataset {
        dir: dir.to_owned(),
        source: Box::new(source),
    })?;
    let robot = dataset
        .robot(robot_id)
        .ok_or_else(|| ServiceError::NoReplayRobot {
            dir: dir.to_owned(),
            robot: robot_id.clone(),
        })?;
    let calib = Calib::of(&dataset, robot_id)?;
    let items: Vec<Item> = robot
        .captures
        .iter()
        .map(|c| Item {
            image: dataset.image_path(robot_id, c),
            depth: dataset.depth_path(robot_id, c),
        })
        .filter(|i| i.image.is_some() || i.depth.is_some())
        .collect();
    if items.is_empty() {
        return Err(ServiceError::NoImagesToReplay {
            dir: dir.to_owned(),
            robot: robot_id.clone(),
        });
    }
    // Read every header first: sizes the samples, and a bad file fails now.
    let (mut colour_bytes, mut depth_bytes) = (0usize, 0usize);
    for item in &items {
        if let Some(p) = &item.image {
            let png = PngImage::open(p)?;
            if png.kind() == StreamKind::Z16 {
                return Err(ServiceError::DepthInImageColumn { path: p.clone() });
            }
            calib.header(&png, p, 0, 0)?;
            colour_bytes = colour_bytes.max(png.header().payload_len());
        }
        if let Some(p) = &item.depth {
            let png = PngImage::open(p)?;
            if png.kind() != StreamKind::Z16 {
                return Err(ServiceError::DepthImageNotZ16 {
                    path: p.clone(),
                    kind: png.kind(),
                });
            }
            calib.header(&png, p, 0, 0)?;
            depth_bytes = depth_bytes.max(png.header().payload_len());
        }
    }
    let mut colour = (colour_bytes > 0)
        .then(|| Out::new(options, Stream::Colour, colour_bytes))
        .transpose()?;
    let mut depth = (depth_bytes > 0)
        .then(|| Out::new(options, Stream::Depth, depth_bytes))
        .transpose()?;

    let stop = stop_flag();
    let period = (options.fps > 0.0).then(|| Duration::from_secs_f64(1.0 / options.fps));
    let start = Instant::now();
    let mut next = start;
    let mut n = 0u64;
    'replay: loop {
        for item in &items {
            if stop.load(Ordering::SeqCst) || options.frames.is_some_and(|max| n >= max) {
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
        if options.once {
            break;
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    Ok(serde_json::json!({
        "robot": robot_id,
        "source": "replay",
        "frames": n,
        "seconds": seconds,
        "colour": Out::summary(colour.as_ref()),
        "depth": Out::summary(depth.as_ref()),
    }))
}

/// The target of the camera's log lines: the binary's name, as when they were
/// logged from the binary (`RUST_LOG=camera=...` still selects them).
#[cfg(feature = "realsense")]
const LOG_TARGET: &str = "camera";

/// Publishes a RealSense device's or recording's framesets.
#[cfg(feature = "realsense")]
fn realsense(options: &CameraOptions) -> Result<serde_json::Value> {
    use b2b_frames::realsense::{Played, RealSense, RealSenseOptions};
    let fps = options.fps.round().max(1.0) as u32;
    let rs_options = RealSenseOptions {
        serial: options.serial.clone(),
        bag: options.bag.clone(),
        loop_playback: !options.once,
        fps,
        ..RealSenseOptions::default()
    };
    let mut camera = RealSense::open(&rs_options)?;
    let recorded = *camera.recorded();
    let (colour_bytes, depth_bytes) = camera.max_bytes();
    let mut colour = Out::new(options, Stream::Colour, colour_bytes)?;
    let mut depth = Out::new(options, Stream::Depth, depth_bytes)?;
    let stop = stop_flag();
    let start = Instant::now();
    let mut n = 0u64;
    // Per frameset, from its arrival to its last publish (not the wait).
    let mut slowest = Duration::ZERO;
    'frames: while !stop.load(Ordering::SeqCst) && options.frames.is_none_or(|max| n < max) {
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
                        target: LOG_TARGET,
                        "colour frame {number}: the nearest depth frame was exposed {:.1} ms away (window {:.1} ms); published without depth",
                        gap as f64 / 1e6,
                        camera.pair_window_ns() as f64 / 1e6
                    ),
                    None => tracing::warn!(
                        target: LOG_TARGET,
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
        "robot": options.robot,
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

/// Without the feature: says how to build with it.
#[cfg(not(feature = "realsense"))]
fn realsense(_: &CameraOptions) -> Result<serde_json::Value> {
    Err(ServiceError::NoRealSenseSupport)
}
