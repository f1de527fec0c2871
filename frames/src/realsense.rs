//! An Intel RealSense camera (or a librealsense `.bag` recording) as a frame
//! source, through realsense-rust (feature `realsense`; needs librealsense2, see
//! the README).
//!
//! A D4xx's depth comes from another sensor than its colour, at another
//! resolution, with an extrinsic between the two. The depth published is aligned
//! to colour ([`crate::align`], with the intrinsics and extrinsic librealsense
//! reports): the colour stream's size and intrinsics, an identity extrinsic, and
//! the colour frame's number, which is how the agent pairs the two. Colour and
//! depth are paired only when librealsense's timestamps are within half a frame
//! period ([`RealSense::pair_window_ns`]); a colour frame without such a depth frame
//! is published alone (counted, and logged with the gap), never with another
//! frame's depth. What the device reports about its depth sensor (intrinsics,
//! the depth-from-colour extrinsic) is kept in [`RealSense::recorded`].
//!
//! A recording's timestamps are from when it was recorded; played back, they are
//! moved onto the host clock by one offset per pass (the first frame at the
//! moment it is played), so intervals and colour-depth gaps stay as recorded and
//! an agent waiting for a frame exposed after its arm stopped gets one. Frame
//! numbers keep increasing when a looping recording starts again.
//!
//! Colour is copied row by row from librealsense's buffer into its loaned
//! sample (one audited `unsafe` reads that buffer, [`frame_bytes`]); depth is
//! aligned from that buffer straight into its sample ([`RealSense::last_work`]
//! times both).

use std::ffi::CString;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use realsense_rust::config::Config;
use realsense_rust::context::Context;
use realsense_rust::frame::{ColorFrame, CompositeFrame, DepthFrame, FrameEx, ImageFrame};
use realsense_rust::kind::{Rs2Format, Rs2StreamKind, Rs2TimestampDomain};
use realsense_rust::pipeline::{ActivePipeline, InactivePipeline};
use realsense_rust::stream_profile::StreamProfile;

use crate::align::{Extrinsic, align_to_colour};
use crate::{FrameHeader, FramePublisher, FramesError, StreamKind};

/// What to open.
#[derive(Debug, Clone, PartialEq)]
pub struct RealSenseOptions {
    /// A device's serial number; `None`: the first device.
    pub serial: Option<String>,
    /// Play a `.bag` recording instead of a device.
    pub bag: Option<PathBuf>,
    /// Start a recording again when it ends (otherwise its end is
    /// [`Played::End`]).
    pub loop_playback: bool,
    pub colour: (u32, u32),
    pub depth: (u32, u32),
    /// Frames per second asked of a device; a recording plays at its own
    /// rate. Half its period is the colour-depth pairing window.
    pub fps: u32,
}

impl Default for RealSenseOptions {
    fn default() -> Self {
        RealSenseOptions {
            serial: None,
            bag: None,
            loop_playback: true,
            colour: (1280, 720),
            depth: (848, 480),
            fps: 30,
        }
    }
}

fn rs(what: &str, e: impl std::fmt::Display) -> FramesError {
    FramesError::RealSense(format!("{what}: {e}"))
}

/// What the device (or the recording) reports about its streams, before
/// alignment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Recorded {
    /// The colour stream's header: size, intrinsics.
    pub colour: FrameHeader,
    /// The depth sensor's own header: size, intrinsics and `depth_from_colour`.
    pub depth: FrameHeader,
}

/// What [`RealSense::publish_next`] did, in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Played {
    /// Colour frame `number` was published.
    Colour { number: u64 },
    /// Its depth frame, aligned to colour, was published.
    Depth { number: u64 },
    /// Colour frame `number` goes without depth: no depth frame came within
    /// the pairing window before the next colour frame; the nearest one seen
    /// was this far away (ns), if any.
    Unpaired {
        number: u64,
        nearest_depth_ns: Option<u64>,
    },
    /// A recording played without looping has ended.
    End,
}

/// A running RealSense pipeline with colour (RGB8) and depth (Z16) streams.
pub struct RealSense {
    /// `None` only while being dropped (see the `Drop` impl).
    pipeline: Option<ActivePipeline>,
    recorded: Recorded,
    colour_from_depth: Extrinsic,
    /// One depth frame copied from librealsense, and aligned: used only
    /// when its buffer or the loaned sample cannot be read as `u16` in place.
    raw_depth: Vec<u16>,
    aligned: Vec<u16>,
    waiting: Option<Waiting>,
    last_depth_raw: u64,
    /// The published headers: colour, and depth aligned to it.
    colour: FrameHeader,
    depth: FrameHeader,
    playback: bool,
    pair_window_ns: u64,
    /// Per pass of a recording: host time minus recorded time (ns).
    clock_offset: Option<i128>,
    last_raw_number: u64,
    number_offset: u64,
    unpaired: u64,
    last_work: Work,
}

/// Time spent on one frameset.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Work {
    /// Its depth frame: copied, aligned to colour and published (zero when
    /// none went out).
    pub depth: Duration,
    /// The rest: its colour frame copied and published, the bookkeeping.
    pub colour: Duration,
}

impl std::fmt::Debug for RealSense {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RealSense")
            .field("recorded", &self.recorded)
            .field("unpaired", &self.unpaired)
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
            // librealsense accepts any path here and fails later without naming it.
            std::fs::File::open(bag).map_err(|e| rs(&format!("{}", bag.display()), e))?;
            config
                .enable_device_from_file(bag, options.loop_playback)
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
        let what = options
            .bag
            .as_ref()
            .map_or_else(|| "the device".to_owned(), |b| format!("{}", b.display()));
        let pipeline = InactivePipeline::try_from(&context)
            .map_err(|e| rs("pipeline", e))?
            .start(Some(config))
            .map_err(|e| rs(&format!("cannot start the pipeline on {what}"), e))?;
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
        let depth = header(StreamKind::Z16, depth_profile, "depth intrinsics")?;
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
        let recorded = Recorded {
            colour,
            depth: FrameHeader {
                depth_from_colour_rotation: rotation,
                depth_from_colour_translation_m: t.map(f64::from),
                ..depth
            },
        };
        // Aligned depth: the colour stream's geometry, an identity extrinsic.
        let aligned = FrameHeader {
            depth_unit_m: 0.0, // set from each depth frame
            ..FrameHeader::new(StreamKind::Z16, colour.width, colour.height).with_intrinsics(
                colour.fx,
                colour.fy,
                colour.cx,
                colour.cy,
                colour.dist,
            )
        };
        let colour_from_depth = Extrinsic::colour_from_depth(&recorded.depth);
        Ok(RealSense {
            pipeline: Some(pipeline),
            recorded,
            colour_from_depth,
            raw_depth: Vec::new(),
            aligned: Vec::new(),
            waiting: None,
            last_depth_raw: 0,
            colour,
            depth: aligned,
            playback: options.bag.is_some(),
            // Half a frame period: a colour frame pairs with its own exposure or none.
            pair_window_ns: 500_000_000 / u64::from(options.fps.max(1)),
            clock_offset: None,
            last_raw_number: 0,
            number_offset: 0,
            unpaired: 0,
            last_work: Work::default(),
        })
    }

    /// The streams as the device reports them, before alignment.
    pub fn recorded(&self) -> &Recorded {
        &self.recorded
    }

    /// Colour frames published without depth: none within the pairing window.
    pub fn unpaired(&self) -> u64 {
        self.unpaired
    }

    /// The largest gap (ns) between a colour frame's and a depth frame's
    /// timestamps for them to be one capture.
    pub fn pair_window_ns(&self) -> u64 {
        self.pair_window_ns
    }

    /// The colour frame waiting for depth goes without it.
    fn give_up_waiting(&mut self, out: &mut Vec<Played>) {
        if let Some(w) = self.waiting.take() {
            self.unpaired += 1;
            out.push(Played::Unpaired {
                number: w.number,
                nearest_depth_ns: w.nearest_gap_ns,
            });
        }
    }

    /// The sample sizes the two publishers need: (colour, aligned depth).
    pub fn max_bytes(&self) -> (usize, usize) {
        (self.colour.payload_len(), self.depth.payload_len())
    }

    /// A frame's time on the host clock (see the module docs), ns.
    fn host_time(&mut self, f: &impl FrameEx) -> u64 {
        if !self.playback {
            // Two frame periods: a USB camera's usual delivery latency and more.
            return time_ns(f, 4 * self.pair_window_ns);
        }
        let recorded = (f.timestamp() * 1e6) as i128;
        let offset = *self
            .clock_offset
            .get_or_insert_with(|| i128::from(crate::now_ns()) - recorded);
        u64::try_from(recorded + offset).unwrap_or(0)
    }

    /// Waits for the next frameset and publishes what is new in it: a new
    /// colour frame at once; a depth frame, aligned to colour, once it is
    /// within the pairing window of the colour frame still waiting for one
    /// (librealsense's syncer may deliver a colour frame with the previous
    /// depth frame first, and its own depth frame in the next frameset). A
    /// colour frame still waiting when the next one arrives goes without depth
    /// ([`Played::Unpaired`]).
    pub fn publish_next(
        &mut self,
        colour: &mut FramePublisher,
        depth: &mut FramePublisher,
        timeout: Duration,
    ) -> Result<Vec<Played>, FramesError> {
        let mut out = Vec::new();
        let Some(pipeline) = self.pipeline.as_mut() else {
            return Ok(vec![Played::End]);
        };
        let frames = match pipeline.wait(Some(timeout)) {
            Ok(f) => f,
            // A recording played once ends with no more frames.
            Err(_) if self.playback && self.last_raw_number > 0 => {
                self.give_up_waiting(&mut out);
                out.push(Played::End);
                return Ok(out);
            }
            Err(e) => return Err(rs("waiting for frames", e)),
        };
        let arrived = Instant::now();
        self.last_work.depth = Duration::ZERO;
        let published = self.publish_frameset(&frames, colour, depth, out);
        self.last_work.colour = arrived.elapsed().saturating_sub(self.last_work.depth);
        published
    }

    /// How long the last [`RealSense::publish_next`] worked on its frameset,
    /// from librealsense handing it over to the last publish, without the
    /// wait for it.
    pub fn last_work(&self) -> Work {
        self.last_work
    }

    fn publish_frameset(
        &mut self,
        frames: &CompositeFrame,
        colour: &mut FramePublisher,
        depth: &mut FramePublisher,
        mut out: Vec<Played>,
    ) -> Result<Vec<Played>, FramesError> {
        // The frameset's depth frame (and its time), unless it already went out.
        let d = frames
            .frames_of_type::<DepthFrame>()
            .into_iter()
            .next()
            .filter(|d| d.frame_number() != self.last_depth_raw)
            .map(|d| {
                let t = self.host_time(&d);
                (d, t)
            });
        let c = frames
            .frames_of_type::<ColorFrame>()
            .into_iter()
            .next()
            .filter(|c| c.frame_number() != self.last_raw_number);
        // A depth frame for the colour frame waiting for one.
        let mut depth_used = false;
        if let (Some((d, t)), Some(w)) = (&d, self.waiting) {
            let gap = t.abs_diff(w.time_ns);
            if gap <= self.pair_window_ns {
                self.publish_depth(depth, d, w.number, *t)?;
                out.push(Played::Depth { number: w.number });
                self.waiting = None;
                depth_used = true;
            } else if let Some(w) = self.waiting.as_mut() {
                w.nearest_gap_ns = Some(w.nearest_gap_ns.map_or(gap, |g| g.min(gap)));
            }
        }
        let Some(c) = c else {
            return Ok(out);
        };
        self.give_up_waiting(&mut out);
        let raw = c.frame_number();
        if raw < self.last_raw_number {
            // The recording started again: numbers go on, times start afresh.
            self.number_offset += self.last_raw_number;
            self.clock_offset = None;
        }
        self.last_raw_number = raw;
        let number = raw + self.number_offset;
        let colour_time = self.host_time(&c);
        let h = self.colour.at(number, colour_time);
        check_size(&h, c.width(), c.height())?;
        let bgr = match c.stream_profile().format() {
            Rs2Format::Rgb8 => false,
            Rs2Format::Bgr8 => true,
            other => {
                return Err(FramesError::RealSense(format!(
                    "colour frame {number} is {other:?}; only RGB8 and BGR8 are published"
                )));
            }
        };
        let rows = image_rows(&c, 3, "colour")?;
        colour.publish_with(&h, |buf| {
            for (dst, src) in buf.chunks_exact_mut(rows.width_bytes).zip(rows.iter()) {
                if bgr {
                    for (d, s) in dst.chunks_exact_mut(3).zip(src.chunks_exact(3)) {
                        d.copy_from_slice(&[s[2], s[1], s[0]]);
                    }
                } else {
                    dst.copy_from_slice(src);
                }
            }
        })?;
        out.push(Played::Colour { number });
        let mut waiting = Waiting {
            number,
            time_ns: colour_time,
            nearest_gap_ns: None,
        };
        if let Some((d, t)) = d.as_ref().filter(|_| !depth_used) {
            let gap = t.abs_diff(colour_time);
            if gap <= self.pair_window_ns {
                self.publish_depth(depth, d, number, *t)?;
                out.push(Played::Depth { number });
                return Ok(out);
            }
            waiting.nearest_gap_ns = Some(gap);
        }
        self.waiting = Some(waiting);
        Ok(out)
    }

    /// Aligns `d` to colour and publishes it as colour frame `number`'s depth.
    fn publish_depth(
        &mut self,
        depth: &mut FramePublisher,
        d: &DepthFrame,
        number: u64,
        time_ns: u64,
    ) -> Result<(), FramesError> {
        let started = Instant::now();
        let unit = f64::from(d.depth_units().map_err(|e| rs("depth unit", e))?);
        check_size(&self.recorded.depth, d.width(), d.height())?;
        self.last_depth_raw = d.frame_number();
        if d.stream_profile().format() != Rs2Format::Z16 {
            return Err(FramesError::RealSense(format!(
                "depth frame {} is {:?}; only Z16 is aligned",
                d.frame_number(),
                d.stream_profile().format()
            )));
        }
        let rows = image_rows(d, 2, "depth")?;
        // Packed little-endian rows on a 2-byte boundary are aligned straight
        // from librealsense's buffer; anything else is copied first.
        let packed = (rows.stride == rows.width_bytes && cfg!(target_endian = "little"))
            .then(|| {
                bytemuck::try_cast_slice::<u8, u16>(&rows.bytes[..rows.width_bytes * rows.height])
                    .ok()
            })
            .flatten();
        let raw: &[u16] = match packed {
            Some(px) => px,
            None => {
                self.raw_depth.clear();
                for r in rows.iter() {
                    self.raw_depth
                        .extend(r.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])));
                }
                &self.raw_depth
            }
        };
        let h = FrameHeader {
            depth_unit_m: unit,
            ..self.depth.at(number, time_ns)
        };
        let (recorded, extrinsic, aligned) =
            (&self.recorded, &self.colour_from_depth, &mut self.aligned);
        // Aligned straight into the loaned sample when it sits on a 2-byte
        // boundary (little-endian, the header's byte order), else through a
        // buffer.
        depth.try_publish_with(&h, |buf| {
            match bytemuck::try_cast_slice_mut::<u8, u16>(buf) {
                Ok(out) if cfg!(target_endian = "little") => {
                    align_to_colour(raw, &recorded.depth, &recorded.colour, extrinsic, unit, out)
                }
                _ => {
                    aligned.resize(buf.len() / 2, 0);
                    align_to_colour(
                        raw,
                        &recorded.depth,
                        &recorded.colour,
                        extrinsic,
                        unit,
                        aligned,
                    )?;
                    for (dst, z) in buf.chunks_exact_mut(2).zip(aligned.iter()) {
                        dst.copy_from_slice(&z.to_le_bytes());
                    }
                    Ok(())
                }
            }
        })?;
        self.last_work.depth += started.elapsed();
        Ok(())
    }
}

/// An image frame's rows as librealsense holds them.
struct Rows<'a> {
    bytes: &'a [u8],
    stride: usize,
    width_bytes: usize,
    height: usize,
}

impl<'a> Rows<'a> {
    fn iter(&self) -> impl Iterator<Item = &'a [u8]> + '_ {
        (0..self.height).map(|y| &self.bytes[y * self.stride..y * self.stride + self.width_bytes])
    }
}

/// `f`'s rows of `bytes_per_pixel`-byte pixels, checked against the buffer's
/// size.
fn image_rows<'a, K>(
    f: &'a ImageFrame<K>,
    bytes_per_pixel: usize,
    what: &str,
) -> Result<Rows<'a>, FramesError> {
    let bytes = frame_bytes(f);
    let (width_bytes, height, stride) = (f.width() * bytes_per_pixel, f.height(), f.stride());
    let needed = if height == 0 {
        0
    } else {
        stride * (height - 1) + width_bytes
    };
    if stride < width_bytes || bytes.len() < needed || f.bits_per_pixel() != 8 * bytes_per_pixel {
        return Err(FramesError::RealSense(format!(
            "a {what} frame of {}x{height} pixels at {} bits holds {} bytes with a stride of {stride}",
            f.width(),
            f.bits_per_pixel(),
            bytes.len()
        )));
    }
    Ok(Rows {
        bytes,
        stride,
        width_bytes,
        height,
    })
}

/// A frame's pixel buffer as librealsense holds it, without a copy.
/// realsense-rust's safe accessor goes pixel by pixel: with it a frameset
/// (colour and depth) took 17.9 ms per colour frame (dev profile), with this
/// a colour frame takes 0.6 ms (`benches/playback.rs`, release).
#[allow(unsafe_code)]
fn frame_bytes<K>(f: &ImageFrame<K>) -> &[u8] {
    let len = f.get_data_size();
    // SAFETY: `get_data` points at the frame's pixel buffer, `get_data_size()`
    // bytes long, which librealsense keeps alive and unchanged while the
    // frame lives; the slice borrows the frame, so it cannot outlive it. u8
    // has no alignment or validity requirements.
    unsafe { std::slice::from_raw_parts(std::ptr::from_ref(f.get_data()).cast::<u8>(), len) }
}

/// A published colour frame still without its depth frame.
#[derive(Debug, Clone, Copy)]
struct Waiting {
    number: u64,
    time_ns: u64,
    /// The nearest depth frame seen so far, outside the window.
    nearest_gap_ns: Option<u64>,
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

/// The frame's capture time on the host clock when librealsense gives one
/// (a D4xx's global time, on by default). Otherwise the arrival time less
/// `latency_ns`, the most a frame may take to arrive: a frame must not look
/// exposed later than it was, or an agent waiting for a frame exposed after
/// its arm stopped could take one that shows the arm moving.
fn time_ns(f: &impl FrameEx, latency_ns: u64) -> u64 {
    match f.timestamp_domain() {
        Rs2TimestampDomain::SystemTime | Rs2TimestampDomain::GlobalTime => {
            (f.timestamp() * 1e6) as u64
        }
        _ => crate::now_ns().saturating_sub(latency_ns),
    }
}

/// realsense-rust deletes a running pipeline without stopping it, so the
/// pipeline is stopped first. Stopping a played-back recording also leaves
/// librealsense finishing the playback device's stop on a detached thread
/// (`playback_device::stop_internal`, which reads the recording's device
/// description again and logs). A process that exits meanwhile destroys
/// librealsense's static logger under that thread, which then crashes: a core
/// of the playback bench, which failed a CI run as it ended, shows exactly
/// that, the main thread in `exit` and the detached thread in the logger. So
/// a dropped playback waits [`PLAYBACK_STOP_GRACE`] for that thread; a live
/// camera has no such thread and does not wait.
impl Drop for RealSense {
    fn drop(&mut self) {
        if let Some(pipeline) = self.pipeline.take() {
            drop(pipeline.stop());
            if self.playback {
                std::thread::sleep(PLAYBACK_STOP_GRACE);
            }
        }
    }
}

/// How long a dropped playback waits for librealsense's detached stop thread
/// ([`RealSense`]'s `Drop`): it takes milliseconds; this leaves room for a
/// loaded machine.
pub const PLAYBACK_STOP_GRACE: Duration = Duration::from_millis(500);
