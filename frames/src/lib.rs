//! Camera frames over iceoryx2 shared memory. The only crate of the workspace that
//! links iceoryx2.
//!
//! One publish-subscribe service per stream (`b2b/camera/{robot}/colour`,
//! `b2b/camera/{robot}/depth`, see [`service_name`]). A sample is a [`FrameHeader`]
//! (iceoryx2's user header: kind, size, intrinsics, depth unit, the
//! depth-from-colour extrinsic, frame number, capture time) and the pixel rows as
//! a `[u8]` payload.
//!
//! Why it is built this way:
//!
//! * **No copy on the way.** [`FramePublisher::publish_with`] loans the sample in
//!   shared memory and hands its bytes to the caller, who decodes or converts the
//!   frame straight into it; a subscriber in another process reads the very same
//!   bytes ([`Frame::data`] borrows the sample). The only safe loan API of iceoryx2
//!   that gives `&mut [u8]` is `loan_slice`, which zero-fills the slot first (a
//!   memset, cheap next to a frame's conversion). When the frame already sits in a
//!   buffer (a driver's), [`FramePublisher::publish_bytes`] copies it into the loan
//!   once, without the memset.
//! * **A slow subscriber never blocks the camera.** The service is configured with
//!   safe overflow: when a subscriber's buffer is full the oldest frame in it is
//!   replaced, and the publisher's back-pressure strategy is to discard, never to
//!   wait. The subscriber learns about it: the publisher numbers every sample it
//!   sends ([`FrameHeader::sequence`]), and [`FrameSubscriber`] counts the gaps as
//!   dropped frames ([`FrameStats`]). Gaps in the camera's own frame numbers are
//!   counted apart, as the source's drops.
//! * **Shared memory is input.** Another process wrote the header: every frame is
//!   checked ([`FrameHeader::validate`]) before it is handed out, and a bad one is an
//!   error naming the service and the field.
//! * **Sizes are fixed up front.** The publisher allocates its samples once
//!   (`max_bytes` each); a frame larger than that is an error, not a reallocation
//!   in the middle of a capture.
//!
//! The memory a service takes: `(4 subscribers * (2 buffered + 3 held) + 1 history
//! + 1 loan) * max_bytes` of `/dev/shm`; for 1280x720 RGB that is 61 MB.
//! iceoryx2 keeps its bookkeeping under `/tmp/iceoryx2` and `/dev/shm/iox2_*`.

pub mod align;
mod error;
mod header;
pub mod png;
#[cfg(feature = "realsense")]
pub mod realsense;
mod transport;

pub use error::FramesError;
pub use header::{FrameHeader, SERVICE_PREFIX, Stream, StreamKind, service_name, service_name_in};
pub use transport::{
    Frame, FramePublisher, FrameStats, FrameSubscriber, MAX_HELD_FRAMES, Published,
    SUBSCRIBER_BUFFER, quiet_iceoryx2_logs,
};

/// Nanoseconds since the Unix epoch on this host's realtime clock: the
/// timebase of [`FrameHeader::timestamp_ns`].
pub fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}
