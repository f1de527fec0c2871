//! The iceoryx2 publisher and subscriber of one stream.

use std::time::{Duration, Instant};

use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;

use crate::{FrameHeader, FramesError};

/// Frames a subscriber's queue holds before the oldest is overwritten.
pub const SUBSCRIBER_BUFFER: usize = 2;
/// Frames a subscriber may hold at once, counting the one [`FrameSubscriber::latest`]
/// keeps while it drains: hold at most `MAX_HELD_FRAMES - 1` yourself.
pub const MAX_HELD_FRAMES: usize = 3;
const MAX_SUBSCRIBERS: usize = 4;
/// A subscriber that starts late gets the newest frame at once.
const HISTORY: usize = 1;

type Service = ipc::Service;
type Factory = PortFactory<Service, [u8], FrameHeader>;

/// iceoryx2 logs a warning when no config file exists, which is the normal case
/// here. Call once at start-up to keep only its errors (`IOX2_LOG_LEVEL` still
/// overrides).
pub fn quiet_iceoryx2_logs() {
    set_log_level_from_env_or(LogLevel::Error);
}

fn setup(service: &str, what: &'static str, e: impl std::fmt::Debug) -> FramesError {
    FramesError::Setup {
        service: service.to_owned(),
        what,
        reason: format!("{e:?}"),
    }
}

/// Opens (or creates) the node and the stream's service with the settings both
/// sides must agree on.
fn open(name: &str) -> Result<(Node<Service>, Factory), FramesError> {
    let service_name = ServiceName::new(name).map_err(|e| FramesError::ServiceName {
        name: name.to_owned(),
        reason: format!("{e:?}"),
    })?;
    // The host process owns its signals (the services use ctrlc).
    let node = NodeBuilder::new()
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Service>()
        .map_err(|e| setup(name, "create an iceoryx2 node", e))?;
    let factory = node
        .service_builder(&service_name)
        .publish_subscribe::<[u8]>()
        .user_header::<FrameHeader>()
        .max_publishers(1)
        .max_subscribers(MAX_SUBSCRIBERS)
        .subscriber_max_buffer_size(SUBSCRIBER_BUFFER)
        .subscriber_max_borrowed_samples(MAX_HELD_FRAMES)
        .history_size(HISTORY)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|e| setup(name, "open or create the publish-subscribe service", e))?;
    Ok((node, factory))
}

/// What [`FramePublisher::publish_with`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Published {
    /// The [`FrameHeader::sequence`] the frame was sent with.
    pub sequence: u64,
    /// Subscribers it was delivered to (0 is not an error: nobody listens yet).
    pub subscribers: usize,
}

/// Publishes one stream's frames. Never waits for a subscriber.
pub struct FramePublisher {
    name: String,
    max_bytes: usize,
    sequence: u64,
    publisher: Publisher<Service, [u8], FrameHeader>,
    _factory: Factory,
    _node: Node<Service>,
}

impl std::fmt::Debug for FramePublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FramePublisher")
            .field("service", &self.name)
            .field("max_bytes", &self.max_bytes)
            .field("sent", &self.sequence)
            .finish()
    }
}

impl FramePublisher {
    /// The publisher of service `service_name`, with samples of `max_bytes` (the
    /// largest frame it will send) allocated now. Fails if the stream already has a
    /// live publisher. Resources of crashed processes are cleaned up first.
    pub fn new(service_name: &str, max_bytes: usize) -> Result<FramePublisher, FramesError> {
        if max_bytes == 0 {
            return Err(setup(service_name, "create a publisher", "max_bytes is 0"));
        }
        let (node, factory) = open(service_name)?;
        let _ = node.try_cleanup_dead_nodes();
        let publisher = factory
            .publisher_builder()
            .initial_max_slice_len(max_bytes)
            .allocation_strategy(AllocationStrategy::Static)
            .max_loaned_samples(1)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(|e| setup(service_name, "create the publisher", e))?;
        Ok(FramePublisher {
            name: service_name.to_owned(),
            max_bytes,
            sequence: 0,
            publisher,
            _factory: factory,
            _node: node,
        })
    }

    pub fn service_name(&self) -> &str {
        &self.name
    }

    pub fn max_bytes(&self) -> usize {
        self.max_bytes
    }

    /// Frames sent so far.
    pub fn sent(&self) -> u64 {
        self.sequence
    }

    /// Connects subscribers that appeared since the last frame and hands them the
    /// newest frame sent (the history). Sending does this too; call it while the
    /// camera is paused so that a late subscriber still gets the last frame.
    pub fn update_connections(&self) -> Result<(), FramesError> {
        use iceoryx2::port::update_connections::UpdateConnections;
        self.publisher
            .update_connections()
            .map_err(|e| self.transport("connect", e))
    }

    fn check(&self, header: &FrameHeader) -> Result<usize, FramesError> {
        let len = header.payload_len();
        if len > self.max_bytes {
            return Err(FramesError::FrameTooLarge {
                service: self.name.clone(),
                len,
                max_bytes: self.max_bytes,
            });
        }
        header.validate(&self.name, len)?;
        Ok(len)
    }

    fn transport(&self, what: &'static str, e: impl std::fmt::Debug) -> FramesError {
        FramesError::Transport {
            service: self.name.clone(),
            what,
            reason: format!("{e:?}"),
        }
    }

    /// Loans a sample in shared memory, lets `fill` write the frame's
    /// `header.payload_len()` bytes into it (they start zeroed), and sends it with
    /// `header` (its `sequence` set by the publisher).
    pub fn publish_with(
        &mut self,
        header: &FrameHeader,
        fill: impl FnOnce(&mut [u8]),
    ) -> Result<Published, FramesError> {
        self.try_publish_with(header, |buf| {
            fill(buf);
            Ok::<(), std::convert::Infallible>(())
        })
    }

    /// [`publish_with`](Self::publish_with) for a `fill` that can fail (a decoder);
    /// on its error nothing is sent and the sequence does not advance.
    pub fn try_publish_with<E>(
        &mut self,
        header: &FrameHeader,
        fill: impl FnOnce(&mut [u8]) -> Result<(), E>,
    ) -> Result<Published, FramesError>
    where
        E: Into<Box<dyn std::error::Error + Send + Sync>>,
    {
        let len = self.check(header)?;
        let mut sample = self
            .publisher
            .loan_slice(len)
            .map_err(|e| self.transport("loan", e))?;
        fill(sample.payload_mut()).map_err(|e| FramesError::Fill {
            service: self.name.clone(),
            source: e.into(),
        })?;
        let sequence = self.sequence + 1;
        *sample.user_header_mut() = FrameHeader {
            sequence,
            ..*header
        };
        let subscribers = sample.send().map_err(|e| self.transport("send", e))?;
        self.sequence = sequence;
        Ok(Published {
            sequence,
            subscribers,
        })
    }

    /// Sends a frame that already sits in memory: one copy, into the loaned sample.
    pub fn publish_bytes(
        &mut self,
        header: &FrameHeader,
        bytes: &[u8],
    ) -> Result<Published, FramesError> {
        let len = self.check(header)?;
        if bytes.len() != len {
            return Err(FramesError::WrongLength {
                service: self.name.clone(),
                expected: len,
                got: bytes.len(),
            });
        }
        let mut sample = self
            .publisher
            .loan_slice_uninit(len)
            .map_err(|e| self.transport("loan", e))?;
        let sequence = self.sequence + 1;
        *sample.user_header_mut() = FrameHeader {
            sequence,
            ..*header
        };
        let subscribers = sample
            .write_from_slice(bytes)
            .send()
            .map_err(|e| self.transport("send", e))?;
        self.sequence = sequence;
        Ok(Published {
            sequence,
            subscribers,
        })
    }
}

/// One received frame: a view of the shared-memory sample, released when dropped.
pub struct Frame {
    sample: Sample<Service, [u8], FrameHeader>,
}

impl std::fmt::Debug for Frame {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Frame")
            .field("header", self.header())
            .field("bytes", &self.data().len())
            .finish()
    }
}

impl Frame {
    /// The header, checked against the payload when the frame was received.
    pub fn header(&self) -> &FrameHeader {
        self.sample.user_header()
    }

    /// The frame's bytes, `header().payload_len()` of them, in shared memory.
    pub fn data(&self) -> &[u8] {
        self.sample.payload()
    }

    /// Row `y` without its padding.
    pub fn row(&self, y: u32) -> Option<&[u8]> {
        let h = self.header();
        let kind = h.stream_kind().ok()?;
        let start = h.stride as usize * y as usize;
        let len = h.width as usize * kind.bytes_per_pixel() as usize;
        (y < h.height).then(|| &self.data()[start..start + len])
    }
}

/// A subscriber's counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrameStats {
    /// Frames taken from the service (handed out or skipped).
    pub received: u64,
    /// Frames the publisher sent that never reached this subscriber (its queue
    /// overflowed): gaps in [`FrameHeader::sequence`].
    pub dropped: u64,
    /// Frames received but passed over by [`FrameSubscriber::latest`].
    pub skipped: u64,
    /// Frames the camera itself skipped: gaps in [`FrameHeader::frame_number`]
    /// between frames that arrived back to back.
    pub source_gaps: u64,
    /// Frames refused because their header was invalid.
    pub invalid: u64,
    /// Times a new publisher (a restarted camera) appeared.
    pub publisher_changes: u64,
}

/// Subscribes to one stream. Polls; never slows the publisher down.
pub struct FrameSubscriber {
    name: String,
    stats: FrameStats,
    last: Option<(iceoryx2::identifiers::UniquePublisherId, u64, u64)>,
    subscriber: Subscriber<Service, [u8], FrameHeader>,
    _factory: Factory,
    _node: Node<Service>,
}

impl std::fmt::Debug for FrameSubscriber {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameSubscriber")
            .field("service", &self.name)
            .field("stats", &self.stats)
            .finish()
    }
}

impl FrameSubscriber {
    /// A subscriber of service `service_name` (created if no publisher exists yet).
    pub fn new(service_name: &str) -> Result<FrameSubscriber, FramesError> {
        let (node, factory) = open(service_name)?;
        let subscriber = factory
            .subscriber_builder()
            .buffer_size(SUBSCRIBER_BUFFER)
            .create()
            .map_err(|e| setup(service_name, "create the subscriber", e))?;
        Ok(FrameSubscriber {
            name: service_name.to_owned(),
            stats: FrameStats::default(),
            last: None,
            subscriber,
            _factory: factory,
            _node: node,
        })
    }

    pub fn service_name(&self) -> &str {
        &self.name
    }

    /// The counters so far.
    pub fn stats(&self) -> FrameStats {
        self.stats
    }

    /// The oldest frame waiting, or `None` when there is none. Never blocks.
    #[allow(clippy::should_implement_trait)] // fallible, so not an Iterator
    pub fn next(&mut self) -> Result<Option<Frame>, FramesError> {
        let Some(sample) = self
            .subscriber
            .receive()
            .map_err(|e| FramesError::Transport {
                service: self.name.clone(),
                what: "receive",
                reason: format!("{e:?}"),
            })?
        else {
            return Ok(None);
        };
        self.stats.received += 1;
        let header = *sample.user_header();
        if let Err(e) = header.validate(&self.name, sample.payload().len()) {
            self.stats.invalid += 1;
            return Err(e);
        }
        let origin = sample.origin();
        match self.last {
            Some((o, seq, frame)) if o == origin && header.sequence > seq => {
                self.stats.dropped += header.sequence - seq - 1;
                if header.sequence == seq + 1 && header.frame_number > frame {
                    self.stats.source_gaps += header.frame_number - frame - 1;
                }
            }
            Some((o, ..)) if o != origin => self.stats.publisher_changes += 1,
            // The same publisher going backwards cannot happen; start over.
            Some(_) => {}
            None => {}
        }
        self.last = Some((origin, header.sequence, header.frame_number));
        Ok(Some(Frame { sample }))
    }

    /// Drains the queue and returns the newest frame (`None` when nothing is
    /// waiting); the older ones are counted in [`FrameStats::skipped`]. An invalid
    /// frame on the way is an error; the valid ones after it are still there.
    pub fn latest(&mut self) -> Result<Option<Frame>, FramesError> {
        let mut newest = None;
        while let Some(frame) = self.next()? {
            if newest.replace(frame).is_some() {
                self.stats.skipped += 1;
            }
        }
        Ok(newest)
    }

    /// The next frame, waiting up to `timeout` for one (polling: yields for the
    /// first millisecond, then sleeps 200 us between looks).
    pub fn wait_next(&mut self, timeout: Duration) -> Result<Option<Frame>, FramesError> {
        let start = Instant::now();
        loop {
            if let Some(frame) = self.next()? {
                return Ok(Some(frame));
            }
            let waited = start.elapsed();
            if waited >= timeout {
                return Ok(None);
            }
            if waited < Duration::from_millis(1) {
                std::thread::yield_now();
            } else {
                std::thread::sleep(Duration::from_micros(200));
            }
        }
    }
}
