//! The agent's capture sources, behind one port ([`CaptureSource`]): the live
//! arm and camera ([`LiveSource`], generic over the arm port and the clock, with
//! frames from any [`FrameSource`]; iceoryx2's is [`IceoryxFrames`]) and the
//! dataset replay ([`ReplaySource`]). Everything after a source is the same code
//! in `b2b-services`, which wires a source to the bus; this crate links no bus,
//! no database and no recording, so its decisions are tested in-process on a
//! fake arm, fake frames and a virtual clock.

mod error;
pub mod live;
pub mod ports;
pub mod replay;
pub mod source;

pub use error::{LiveError, Result};
pub use live::{
    FrameSource, IceoryxFrames, LiveConfig, LiveFrame, LiveSource, LiveTimings, WatchObserve,
};
pub use ports::{ArmPort, Clock, SystemClock};
pub use replay::ReplaySource;
pub use source::{CaptureSource, Progress, SourceCapture};
