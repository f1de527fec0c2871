//! KUKA Fast Robot Interface (FRI 1.15), client and simulated controller.
//!
//! The agent reads its LBR iiwa and moves it through FRI: UDP datagrams carrying protobuf
//! messages every 1–5 ms, the controller sending first. This crate is layered so that the
//! protocol can be tested without a robot, a network or a clock:
//!
//! | module | role | I/O |
//! |---|---|---|
//! | [`messages`] | prost types written from the FRI 1.15 field list; 2.x differences documented | none |
//! | [`codec`] | datagram ⇄ message with size, identifier, required-field and enum checks | none |
//! | [`guard`] | the [`SafetyGuard`] on every command: `b2b_robot`'s limits, box and kinematics | none |
//! | [`trajectory`] | synchronised trapezoidal joint trajectories | none |
//! | [`joints`] | controller-stamped joint states, stillness detection | none |
//! | [`session`] | [`ClientSession`], the sans-I/O client state machine | none (fed bytes and instants) |
//! | [`sim`] | [`SimulatedController`] (robot side) and a lossy [`sim::Link`] | none |
//! | [`udp`] | [`FriClient`]: a cycle thread + UDP socket driving the session | socket, clock |
//! | [`server`] | [`SimServer`]: a cycle thread + UDP socket serving the simulated controller | socket, clock |
//! | [`realtime`] | SCHED_FIFO for the cycle threads, where permitted | scheduler |
//!
//! The binary `fri-sim-controller` serves the simulated controller over UDP through a lossy
//! link.
//!
//! ```
//! use b2b_robot::{JointLimits, WorkspaceBox};
//! use kuka_fri::{ClientSession, SafetyGuard, SessionConfig};
//! # fn fk(_q: &[f64; 7]) -> [f64; 3] { [0.0, 0.0, 1.0] }
//! let guard = SafetyGuard::new(JointLimits::iiwa7(), WorkspaceBox::unbounded(), fk)?;
//! let mut session = ClientSession::new(SessionConfig::default(), guard);
//! let mut buf = [0u8; kuka_fri::messages::MAX_DATAGRAM_SIZE];
//! // for each datagram: session.handle_datagram(now, &bytes)?;
//! //                    if let Some(n) = session.poll_transmit(now, &mut buf) { send(&buf[..n]) }
//! # let _ = (&mut session, &mut buf);
//! # Ok::<(), kuka_fri::FriError>(())
//! ```

pub mod codec;
pub mod error;
pub mod guard;
pub mod joints;
pub mod messages;
pub mod realtime;
pub mod server;
pub mod session;
pub mod sim;
pub mod trajectory;
pub mod udp;

pub use error::{FriError, Result};
pub use guard::SafetyGuard;
pub use joints::{ControllerTime, JointHistory, JointState};
pub use messages::{ConnectionQuality, SessionState};
pub use realtime::{CycleScheduling, DEFAULT_CYCLE_PRIORITY};
pub use server::{SimServer, SimServerConfig, SimSnapshot};
pub use session::{
    ClientSession, Event, MonitorSnapshot, PlannedMotion, SessionConfig, SessionStats,
};
pub use sim::{Link, LinkConfig, SimConfig, SimStats, SimulatedController};
pub use trajectory::Trajectory;
pub use udp::{FriClient, FriClientConfig};
