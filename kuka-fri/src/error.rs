//! The crate's one error type.
//!
//! Every variant names *what* was wrong (which message, which field, which joint) so that a
//! log line is enough to find the fault without a packet capture.

use std::time::Duration;

use crate::messages::SessionState;

/// Errors of the FRI crate.
#[derive(Debug, thiserror::Error)]
pub enum FriError {
    /// A datagram with no bytes.
    #[error("{message}: empty datagram")]
    EmptyDatagram {
        /// Which message was expected.
        message: &'static str,
    },
    /// A datagram larger than FRI allows.
    #[error("{message}: datagram of {len} bytes exceeds the FRI maximum of {max} bytes")]
    DatagramTooLarge {
        /// Which message was expected.
        message: &'static str,
        /// Received length.
        len: usize,
        /// Maximum allowed length.
        max: usize,
    },
    /// The bytes are not valid protobuf for the expected message (truncated or malformed).
    #[error("{message}: malformed or truncated protobuf")]
    Decode {
        /// Which message was being decoded.
        message: &'static str,
        /// prost's description.
        #[source]
        source: prost::DecodeError,
    },
    /// A proto2 `required` field (or one the session needs) is absent.
    #[error("{message}: missing required field `{field}`")]
    MissingField {
        /// Which message.
        message: &'static str,
        /// Field path, e.g. `header.sequenceCounter`.
        field: &'static str,
    },
    /// The header's message identifier is not the expected one.
    #[error("{message}: wrong message identifier {found:#x}, expected {expected:#x}")]
    WrongMessageId {
        /// Which message.
        message: &'static str,
        /// Expected identifier.
        expected: u32,
        /// Received identifier.
        found: u32,
    },
    /// An enum field holds a value that the schema does not define.
    #[error("{message}: field `{field}` has unknown enum value {value}")]
    UnknownEnumValue {
        /// Which message.
        message: &'static str,
        /// Field path.
        field: &'static str,
        /// Received value.
        value: i32,
    },
    /// A joint vector with the wrong number of values.
    #[error("{message}: field `{field}` has {found} values, expected {expected}")]
    JointCount {
        /// Which message.
        message: &'static str,
        /// Field path.
        field: &'static str,
        /// Expected count.
        expected: usize,
        /// Received count.
        found: usize,
    },
    /// A NaN or infinite value where a finite one is needed.
    #[error("{what}: non-finite value at joint {joint}")]
    NonFinite {
        /// Where it was found.
        what: &'static str,
        /// Joint index (0-based; A1 is 0).
        joint: usize,
    },
    /// A value outside what FRI or this crate allows (e.g. a 0 ms send period).
    #[error("{what}: invalid value {value}")]
    InvalidValue {
        /// Which value.
        what: &'static str,
        /// The value as text.
        value: String,
    },
    /// The output buffer cannot hold the encoded message.
    #[error("{message}: encoded size {needed} bytes does not fit in {available} bytes")]
    BufferTooSmall {
        /// Which message.
        message: &'static str,
        /// Encoded length.
        needed: usize,
        /// Buffer length (or the FRI maximum, whichever is smaller).
        available: usize,
    },
    /// A command outside the safety envelope (joint limits, velocity limits, workspace
    /// box), or limits that cannot describe a real arm: `b2b_robot`'s verdict.
    #[error(transparent)]
    Robot(#[from] b2b_robot::RobotError),
    /// A command or motion was requested outside COMMANDING_ACTIVE.
    #[error("commands are only sent in COMMANDING_ACTIVE; session is {state}")]
    NotCommanding {
        /// The current state.
        state: SessionState,
    },
    /// A motion was requested while another one is running.
    #[error("a motion is already in progress")]
    MotionInProgress,
    /// A motion planned from a command origin that has moved since (plan it again).
    #[error("the command origin moved while the motion was being planned")]
    MotionOriginMoved,
    /// The running motion was stopped before reaching its target.
    #[error("motion aborted: {reason}")]
    MotionAborted {
        /// Why.
        reason: String,
    },
    /// Waiting for something took too long.
    #[error("timed out after {waited:?} waiting for {what}")]
    Timeout {
        /// What was awaited.
        what: &'static str,
        /// How long.
        waited: Duration,
    },
    /// The UDP driver thread has stopped.
    #[error("the FRI driver thread has stopped")]
    DriverStopped,
    /// Socket error.
    #[error("UDP socket")]
    Io(#[from] std::io::Error),
}

pub(crate) use b2b_errors::chain;

/// Result alias of this crate.
pub type Result<T, E = FriError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    use b2b_errors::assert_cause_once;

    #[test]
    fn every_wrapped_error_prints_its_cause_once() {
        let e = crate::codec::decode_monitoring(&[0x0a, 0xff, 0xff]).unwrap_err();
        assert!(matches!(e, FriError::Decode { .. }), "{e}");
        assert_cause_once(&e);
        let io = std::io::Error::new(std::io::ErrorKind::AddrInUse, "address in use by test");
        assert_cause_once(&FriError::from(io));
    }
}
