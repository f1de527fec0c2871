//! The frame header that travels in front of every frame's bytes.

use iceoryx2::prelude::ZeroCopySend;

use crate::FramesError;

/// The pixel format of a frame's bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum StreamKind {
    /// 8-bit red, green, blue, interleaved.
    Rgb8,
    /// 8-bit grey.
    Gray8,
    /// 16-bit depth, little-endian, in units of [`FrameHeader::depth_unit_m`];
    /// 0 means no depth.
    Z16,
}

impl StreamKind {
    /// Every kind, for tests and help texts.
    pub const ALL: [StreamKind; 3] = [StreamKind::Rgb8, StreamKind::Gray8, StreamKind::Z16];

    /// Bytes per pixel.
    pub fn bytes_per_pixel(self) -> u32 {
        match self {
            StreamKind::Rgb8 => 3,
            StreamKind::Gray8 => 1,
            StreamKind::Z16 => 2,
        }
    }

    /// The code written into [`FrameHeader::kind`].
    pub fn code(self) -> u32 {
        match self {
            StreamKind::Rgb8 => 1,
            StreamKind::Gray8 => 2,
            StreamKind::Z16 => 3,
        }
    }

    /// The kind of a header code, `None` for an unknown one.
    pub fn from_code(code: u32) -> Option<StreamKind> {
        StreamKind::ALL.into_iter().find(|k| k.code() == code)
    }

    pub fn name(self) -> &'static str {
        match self {
            StreamKind::Rgb8 => "rgb8",
            StreamKind::Gray8 => "gray8",
            StreamKind::Z16 => "z16",
        }
    }
}

/// The two streams of a camera, one iceoryx2 service each.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stream {
    /// Colour or grey images ([`StreamKind::Rgb8`] or [`StreamKind::Gray8`]).
    Colour,
    /// Depth images ([`StreamKind::Z16`]).
    Depth,
}

impl Stream {
    pub fn name(self) -> &'static str {
        match self {
            Stream::Colour => "colour",
            Stream::Depth => "depth",
        }
    }
}

/// The root of the camera services' names.
pub const SERVICE_PREFIX: &str = "b2b/camera";

/// The service of one stream of robot `robot`'s camera: `b2b/camera/{robot}/{stream}`.
pub fn service_name(robot: &str, stream: Stream) -> String {
    service_name_in(SERVICE_PREFIX, robot, stream)
}

/// [`service_name`] under another root (tests and benchmarks use unique ones).
pub fn service_name_in(prefix: &str, robot: &str, stream: Stream) -> String {
    format!("{prefix}/{robot}/{}", stream.name())
}

/// What a subscriber needs to know about a frame besides its bytes. `#[repr(C)]`
/// and self-contained: it lives in shared memory as iceoryx2's user header.
///
/// Rows are `stride` bytes apart (`stride >= width * bytes_per_pixel`); the payload
/// is exactly `stride * height` bytes.
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[repr(C)]
pub struct FrameHeader {
    /// [`StreamKind::code`]; read it with [`FrameHeader::stream_kind`].
    pub kind: u32,
    pub width: u32,
    pub height: u32,
    /// Bytes from one row to the next.
    pub stride: u32,
    /// Pinhole intrinsics in pixels; all four 0 when unknown.
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// OpenCV distortion `k1, k2, p1, p2, k3` (RealSense's Brown-Conrady order).
    pub dist: [f64; 5],
    /// Metres per depth unit for [`StreamKind::Z16`]; 0 for colour.
    pub depth_unit_m: f64,
    /// Rotation of `depth_from_colour`, row-major: `p_in_depth = R * p_in_colour + t`.
    /// The identity when depth is aligned to colour.
    pub depth_from_colour_rotation: [f64; 9],
    /// Translation of `depth_from_colour`, metres.
    pub depth_from_colour_translation_m: [f64; 3],
    /// The source's frame number (the camera's counter, or the replay's index).
    pub frame_number: u64,
    /// Capture time, nanoseconds since the Unix epoch ([`crate::now_ns`]).
    pub timestamp_ns: u64,
    /// Set by the publisher: 1 for its first frame, then +1 per frame sent. A
    /// subscriber counts gaps in it as dropped frames.
    pub sequence: u64,
}

const IDENTITY: [f64; 9] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];

impl FrameHeader {
    /// A header for a `width` x `height` frame of `kind` with packed rows, no
    /// intrinsics, an identity extrinsic, and (for depth) a millimetre unit.
    pub fn new(kind: StreamKind, width: u32, height: u32) -> FrameHeader {
        FrameHeader {
            kind: kind.code(),
            width,
            height,
            stride: width.saturating_mul(kind.bytes_per_pixel()),
            depth_unit_m: if kind == StreamKind::Z16 { 0.001 } else { 0.0 },
            depth_from_colour_rotation: IDENTITY,
            ..FrameHeader::default()
        }
    }

    /// The same header with pinhole intrinsics.
    pub fn with_intrinsics(mut self, fx: f64, fy: f64, cx: f64, cy: f64, dist: [f64; 5]) -> Self {
        (self.fx, self.fy, self.cx, self.cy, self.dist) = (fx, fy, cx, cy, dist);
        self
    }

    /// The same header with a capture time and a source frame number.
    pub fn at(mut self, frame_number: u64, timestamp_ns: u64) -> Self {
        self.frame_number = frame_number;
        self.timestamp_ns = timestamp_ns;
        self
    }

    /// The pixel format, or an error for an unknown code.
    pub fn stream_kind(&self) -> Result<StreamKind, FramesError> {
        StreamKind::from_code(self.kind).ok_or_else(|| FramesError::InvalidHeader {
            service: String::new(),
            field: "kind",
            reason: format!("unknown stream kind code {}", self.kind),
        })
    }

    /// `stride * height`: the payload length the header describes (saturating).
    pub fn payload_len(&self) -> usize {
        (self.stride as usize).saturating_mul(self.height as usize)
    }

    /// Checks the header on its own and against a payload of `payload_len`
    /// bytes; `service` names the stream in the error.
    pub fn validate(&self, service: &str, payload_len: usize) -> Result<(), FramesError> {
        let bad = |field: &'static str, reason: String| FramesError::InvalidHeader {
            service: service.to_owned(),
            field,
            reason,
        };
        let kind = StreamKind::from_code(self.kind)
            .ok_or_else(|| bad("kind", format!("unknown stream kind code {}", self.kind)))?;
        if self.width == 0 || self.height == 0 {
            return Err(bad(
                "width/height",
                format!("empty frame {}x{}", self.width, self.height),
            ));
        }
        let row = u64::from(self.width) * u64::from(kind.bytes_per_pixel());
        if u64::from(self.stride) < row {
            return Err(bad(
                "stride",
                format!(
                    "{} bytes is less than a {} row of {} pixels ({row} bytes)",
                    self.stride,
                    kind.name(),
                    self.width
                ),
            ));
        }
        if payload_len != self.payload_len() {
            return Err(bad(
                "stride",
                format!(
                    "stride {} x height {} = {} bytes, but the payload has {payload_len}",
                    self.stride,
                    self.height,
                    self.payload_len()
                ),
            ));
        }
        let pinhole = [self.fx, self.fy, self.cx, self.cy];
        let unknown = pinhole.iter().all(|v| *v == 0.0);
        let usable = self.fx > 0.0 && self.fy > 0.0 && pinhole.iter().all(|v| v.is_finite());
        if !unknown && !usable {
            return Err(bad(
                "fx/fy/cx/cy",
                format!(
                    "{pinhole:?}: focal lengths must be > 0 and all finite (or all 0: unknown)"
                ),
            ));
        }
        if !self.dist.iter().all(|v| v.is_finite()) {
            return Err(bad("dist", format!("{:?} is not finite", self.dist)));
        }
        let unit_ok = match kind {
            StreamKind::Z16 => self.depth_unit_m > 0.0 && self.depth_unit_m < 1.0,
            _ => self.depth_unit_m >= 0.0 && self.depth_unit_m < 1.0,
        };
        if !unit_ok {
            return Err(bad(
                "depth_unit_m",
                format!(
                    "{} m per unit for a {} frame (depth needs 0 < unit < 1 m)",
                    self.depth_unit_m,
                    kind.name()
                ),
            ));
        }
        let r = &self.depth_from_colour_rotation;
        let orthonormal = (0..3).all(|i| {
            (0..3).all(|j| {
                let dot: f64 = (0..3).map(|k| r[3 * i + k] * r[3 * j + k]).sum();
                (dot - if i == j { 1.0 } else { 0.0 }).abs() < 1e-6
            })
        });
        let det = r[0] * (r[4] * r[8] - r[5] * r[7]) - r[1] * (r[3] * r[8] - r[5] * r[6])
            + r[2] * (r[3] * r[7] - r[4] * r[6]);
        if !orthonormal || (det - 1.0).abs() > 1e-6 {
            return Err(bad(
                "depth_from_colour_rotation",
                format!("{r:?} is not a rotation matrix"),
            ));
        }
        let t = &self.depth_from_colour_translation_m;
        if !t.iter().all(|v| v.is_finite() && v.abs() < 1.0) {
            return Err(bad(
                "depth_from_colour_translation_m",
                format!("{t:?}: a camera's depth-to-colour offset is finite and under 1 m"),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn good() -> FrameHeader {
        FrameHeader::new(StreamKind::Z16, 848, 480)
            .with_intrinsics(425.0, 425.0, 424.0, 240.0, [0.0; 5])
    }

    #[test]
    fn kinds_round_trip_and_unknown_codes_are_refused() {
        for k in StreamKind::ALL {
            assert_eq!(StreamKind::from_code(k.code()), Some(k));
        }
        assert_eq!(StreamKind::from_code(0), None);
        assert_eq!(StreamKind::from_code(4), None);
        let h = FrameHeader { kind: 9, ..good() };
        let e = h.validate("svc", h.payload_len()).unwrap_err().to_string();
        assert!(
            e.contains("svc") && e.contains("kind") && e.contains('9'),
            "{e}"
        );
    }

    #[test]
    fn a_good_header_passes_and_describes_its_payload() {
        let h = good();
        assert_eq!(h.stride, 848 * 2);
        assert_eq!(h.payload_len(), 848 * 480 * 2);
        h.validate("svc", 814_080).unwrap();
        let e = h.validate("svc", 814_079).unwrap_err().to_string();
        assert!(e.contains("814079"), "{e}");
    }

    #[test]
    fn bad_fields_are_named() {
        let cases: Vec<(FrameHeader, &str)> = vec![
            (FrameHeader { width: 0, ..good() }, "width/height"),
            (
                FrameHeader {
                    stride: 100,
                    ..good()
                },
                "stride",
            ),
            (FrameHeader { fx: -1.0, ..good() }, "fx/fy/cx/cy"),
            (
                FrameHeader {
                    cx: f64::NAN,
                    ..good()
                },
                "fx/fy/cx/cy",
            ),
            (
                FrameHeader {
                    dist: [0.0, f64::INFINITY, 0.0, 0.0, 0.0],
                    ..good()
                },
                "dist",
            ),
            (
                FrameHeader {
                    depth_unit_m: 0.0,
                    ..good()
                },
                "depth_unit_m",
            ),
            (
                FrameHeader {
                    depth_from_colour_rotation: [2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    ..good()
                },
                "depth_from_colour_rotation",
            ),
            (
                // A reflection is orthonormal but not a rotation.
                FrameHeader {
                    depth_from_colour_rotation: [-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    ..good()
                },
                "depth_from_colour_rotation",
            ),
            (
                FrameHeader {
                    depth_from_colour_translation_m: [0.015, 0.0, 15.0],
                    ..good()
                },
                "depth_from_colour_translation_m",
            ),
        ];
        for (h, field) in cases {
            let e = h.validate("svc", h.payload_len()).unwrap_err();
            match e {
                FramesError::InvalidHeader { field: f, .. } => assert_eq!(f, field, "{e}"),
                other => panic!("{other}"),
            }
        }
    }

    #[test]
    fn a_padded_stride_and_a_real_extrinsic_are_accepted() {
        let c = std::f64::consts::FRAC_1_SQRT_2;
        let h = FrameHeader {
            stride: 1280 * 3 + 64,
            depth_from_colour_rotation: [c, -c, 0.0, c, c, 0.0, 0.0, 0.0, 1.0],
            depth_from_colour_translation_m: [-0.015, 0.0001, 0.0],
            ..FrameHeader::new(StreamKind::Rgb8, 1280, 720)
        };
        h.validate("svc", (1280 * 3 + 64) * 720).unwrap();
    }

    #[test]
    fn service_names_follow_the_pattern() {
        assert_eq!(
            service_name("robot1", Stream::Colour),
            "b2b/camera/robot1/colour"
        );
        assert_eq!(
            service_name("robot2", Stream::Depth),
            "b2b/camera/robot2/depth"
        );
    }
}
