//! The crate's one error type.

use std::path::PathBuf;

/// Everything that can go wrong on the frame path. iceoryx2's own errors are
/// kept as text: their types differ per call and carry no more than a name.
#[derive(Debug, thiserror::Error)]
pub enum FramesError {
    /// Not a valid iceoryx2 service name.
    #[error("\"{name}\" is not a valid iceoryx2 service name: {reason}")]
    ServiceName { name: String, reason: String },
    /// The iceoryx2 node, service or port could not be created or opened (a
    /// second publisher on the same stream, an incompatible existing service,
    /// shared memory that cannot be allocated, ...).
    #[error("{service}: cannot {what}: {reason}")]
    Setup {
        service: String,
        what: &'static str,
        reason: String,
    },
    /// A frame header that makes no sense (bad kind, size, stride, intrinsics...).
    #[error("{service}: invalid frame header: {field}: {reason}")]
    InvalidHeader {
        service: String,
        field: &'static str,
        reason: String,
    },
    /// The frame is larger than the publisher's `max_bytes`.
    #[error("{service}: a {len}-byte frame does not fit the publisher's {max_bytes}-byte samples")]
    FrameTooLarge {
        service: String,
        len: usize,
        max_bytes: usize,
    },
    /// `publish_bytes` got a byte count the header does not describe.
    #[error("{service}: the header describes {expected} bytes, {got} were given")]
    WrongLength {
        service: String,
        expected: usize,
        got: usize,
    },
    /// Loaning, sending or receiving a sample failed.
    #[error("{service}: cannot {what} a frame: {reason}")]
    Transport {
        service: String,
        what: &'static str,
        reason: String,
    },
    /// The caller's fill closure failed; nothing was sent.
    #[error("{service}: the frame could not be written")]
    Fill {
        service: String,
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// An image file could not be read or is not a frame this crate carries.
    #[error("{}: {reason}", path.display())]
    Image { path: PathBuf, reason: String },
    /// The RealSense camera (feature `realsense`).
    #[error("RealSense: {0}")]
    RealSense(String),
    /// Depth could not be aligned to colour.
    #[error("aligning depth to colour: {0}")]
    Align(String),
}

#[cfg(test)]
mod tests {
    use super::*;

    use b2b_errors::assert_cause_once;

    #[test]
    fn every_wrapped_error_prints_its_cause_once() {
        assert_cause_once(&FramesError::Fill {
            service: "b2b/camera/robot1/colour".into(),
            source: "the renderer ran out of memory".into(),
        });
    }
}
