//! An Intel RealSense camera (or a librealsense `.bag` recording) as a frame
//! source, through realsense-rust (feature `realsense`; needs librealsense2, see
//! the README).
//!
//! Frames are written into the loaned samples pixel by pixel through
//! realsense-rust's safe pixel accessor: its raw data pointer is `unsafe`, which
//! the workspace denies. That costs a few milliseconds per frame, not a copy.

use std::ffi::CString;
use std::path::PathBuf;
use std::time::Duration;

use realsense_rust::config::Config;
use realsense_rust::context::Context;
use realsense_rust::frame::{ColorFrame, DepthFrame, FrameEx, PixelKind};
use realsense_rust::kind::{Rs2Format, Rs2StreamKind, Rs2TimestampDomain};
use realsense_rust::pipeline::{ActivePipeline, InactivePipeline};
use realsense_rust::stream_profile::StreamProfile;

use crate::{FrameHeader, FramePublisher, FramesError, StreamKind};

/// What to open.
#[derive(Debug, Clone, PartialEq)]
pub struct RealSenseOptions {
    /// A device's serial number; `None`: the first device.
    pub serial: Option<String>,
    /// Play a `.bag` recording (looping) instead of a device.
    pub bag: Option<PathBuf>,
    pub colour: (u32, u32),
    pub depth: (u32, u32),
    pub fps: u32,
}

impl Default for RealSenseOptions {
    fn default() -> Self {
        RealSenseOptions {
            serial: None,
            bag: None,
            colour: (1280, 720),
            depth: (848, 480),
            fps: 30,
        }
    }
}

fn rs(what: &str, e: impl std::fmt::Display) -> FramesError {
    FramesError::RealSense(format!("{what}: {e}"))
}

/// A running RealSense pipeline with colour (RGB8) and depth (Z16) streams.
pub struct RealSense {
    pipeline: ActivePipeline,
    colour: FrameHeader,
    depth: FrameHeader,
}

impl std::fmt::Debug for RealSense {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RealSense")
            .field("colour", &self.colour)
            .field("depth", &self.depth)
            .finish()
    }
}

fn header(
    kind: StreamKind,
    profile: &StreamProfile,
    what: &str,
) -> Result<FrameHeader, FramesError> {
    let i = profile.intrinsics().map_err(|e| rs(what, e))?;
    let d = i.distortion().coeffs.map(f64::from);
    Ok(
        FrameHeader::new(kind, i.width() as u32, i.height() as u32).with_intrinsics(
            f64::from(i.fx()),
            f64::from(i.fy()),
            f64::from(i.ppx()),
            f64::from(i.ppy()),
            d,
        ),
    )
}

impl RealSense {
    /// Starts the pipeline and reads intrinsics, the depth unit and the
    /// depth-from-colour extrinsic.
    pub fn open(options: &RealSenseOptions) -> Result<RealSense, FramesError> {
        let context = Context::new().map_err(|e| rs("no librealsense context", e))?;
        let mut config = Config::new();
        if let Some(bag) = &options.bag {
            config
                .enable_device_from_file(bag, true)
                .map_err(|e| rs(&format!("{}", bag.display()), e))?;
        } else if let Some(serial) = &options.serial {
            let s = CString::new(serial.as_str()).map_err(|e| rs("serial", e))?;
            config
                .enable_device_from_serial(&s)
                .map_err(|e| rs("serial", e))?;
        }
        if options.bag.is_none() {
            let fps = options.fps as usize;
            config
                .enable_stream(
                    Rs2StreamKind::Color,
                    None,
                    options.colour.0 as usize,
                    options.colour.1 as usize,
                    Rs2Format::Rgb8,
                    fps,
                )
                .map_err(|e| rs("colour stream", e))?
                .enable_stream(
                    Rs2StreamKind::Depth,
                    None,
                    options.depth.0 as usize,
                    options.depth.1 as usize,
                    Rs2Format::Z16,
                    fps,
                )
                .map_err(|e| rs("depth stream", e))?;
        }
        let pipeline = InactivePipeline::try_from(&context)
            .map_err(|e| rs("pipeline", e))?
            .start(Some(config))
            .map_err(|e| rs("cannot start the pipeline", e))?;
        let streams = pipeline.profile().streams();
        let find = |kind: Rs2StreamKind| {
            streams
                .iter()
                .find(|s| s.kind() == kind)
                .ok_or_else(|| FramesError::RealSense(format!("the device has no {kind:?} stream")))
        };
        let (colour_profile, depth_profile) =
            (find(Rs2StreamKind::Color)?, find(Rs2StreamKind::Depth)?);
        let colour = header(StreamKind::Rgb8, colour_profile, "colour intrinsics")?;
        let mut depth = header(StreamKind::Z16, depth_profile, "depth intrinsics")?;
        // p_in_depth = R * p_in_colour + t; librealsense's rotation is column-major.
        let e = colour_profile
            .extrinsics(depth_profile)
            .map_err(|e| rs("depth-from-colour extrinsics", e))?;
        let (c, t) = (e.rotation(), e.translation());
        let mut rotation = [0.0; 9];
        for i in 0..3 {
            for j in 0..3 {
                rotation[3 * i + j] = f64::from(c[3 * j + i]);
            }
        }
        let with_extrinsic = |h: FrameHeader| FrameHeader {
            depth_from_colour_rotation: rotation,
            depth_from_colour_translation_m: t.map(f64::from),
            ..h
        };
        depth = with_extrinsic(depth);
        let colour = with_extrinsic(colour);
        depth.depth_unit_m = 0.0; // set from the first depth frame
        Ok(RealSense {
            pipeline,
            colour,
            depth,
        })
    }

    /// The sample sizes the two publishers need: (colour, depth).
    pub fn max_bytes(&self) -> (usize, usize) {
        (self.colour.payload_len(), self.depth.payload_len())
    }

    /// Waits for the next frameset and publishes its colour and depth frames;
    /// returns which of the two were present.
    pub fn publish_next(
        &mut self,
        colour: &mut FramePublisher,
        depth: &mut FramePublisher,
        timeout: Duration,
    ) -> Result<(bool, bool), FramesError> {
        let frames = self
            .pipeline
            .wait(Some(timeout))
            .map_err(|e| rs("waiting for frames", e))?;
        let mut got = (false, false);
        if let Some(f) = frames.frames_of_type::<ColorFrame>().into_iter().next() {
            let h = self.colour.at(f.frame_number(), time_ns(&f));
            check_size(&h, f.width(), f.height())?;
            colour.publish_with(&h, |buf| {
                let w = h.width as usize;
                for (k, p) in f.iter().enumerate().take(w * h.height as usize) {
                    let o = k * 3;
                    match p {
                        PixelKind::Bgr8 { b, g, r } | PixelKind::Rgb8 { r, g, b } => {
                            buf[o..o + 3].copy_from_slice(&[*r, *g, *b]);
                        }
                        _ => {}
                    }
                }
            })?;
            got.0 = true;
        }
        if let Some(f) = frames.frames_of_type::<DepthFrame>().into_iter().next() {
            let unit = f.depth_units().map_err(|e| rs("depth unit", e))?;
            let h = FrameHeader {
                depth_unit_m: f64::from(unit),
                ..self.depth.at(f.frame_number(), time_ns(&f))
            };
            check_size(&h, f.width(), f.height())?;
            depth.publish_with(&h, |buf| {
                for (k, p) in f.iter().enumerate().take(buf.len() / 2) {
                    if let PixelKind::Z16 { depth } = p {
                        buf[2 * k..2 * k + 2].copy_from_slice(&depth.to_le_bytes());
                    }
                }
            })?;
            got.1 = true;
        }
        Ok(got)
    }
}

fn check_size(h: &FrameHeader, width: usize, height: usize) -> Result<(), FramesError> {
    if (width, height) != (h.width as usize, h.height as usize) {
        return Err(FramesError::RealSense(format!(
            "a {width}x{height} frame on a {}x{} stream",
            h.width, h.height
        )));
    }
    Ok(())
}

/// The frame's capture time on the host clock when librealsense gives one,
/// otherwise the arrival time.
fn time_ns(f: &impl FrameEx) -> u64 {
    match f.timestamp_domain() {
        Rs2TimestampDomain::SystemTime | Rs2TimestampDomain::GlobalTime => {
            (f.timestamp() * 1e6) as u64
        }
        _ => crate::now_ns(),
    }
}
