//! Datagram ⇄ message conversion with every check the wire needs.
//!
//! # Why a separate layer
//! prost alone accepts far too much for a safety-relevant link: it ignores missing proto2
//! `required` fields, keeps unknown enum values as raw integers and has no idea of FRI's
//! 1500-byte limit or message identifiers. This module is the single place where untrusted
//! bytes become typed messages, so the session core and the simulated controller can rely on
//! what they get: a decoded message has its header, a known message identifier, known enum
//! values, 7 finite values in every joint vector and at most the SDK's array sizes.
//! Everything else is rejected with a [`FriError`] naming the message and the field.
//!
//! The decoders never panic, whatever the input (fuzzed in `fuzz/` and by a proptest).

use prost::Message;

use crate::error::{FriError, Result};
use crate::messages::{
    ClientCommandMode, ConnectionQuality, ControlMode, DriveState, FriCommandMessage,
    FriIoDirection, FriIoType, FriIoValue, FriMonitoringMessage, JointValues,
    LBR_COMMAND_MESSAGE_ID, LBR_MONITOR_MESSAGE_ID, MAX_DATAGRAM_SIZE, MessageHeader, NUM_JOINTS,
    OperationMode, OverlayType, SafetyState, SessionState, TimeStamp, Transformation,
};

/// Name used in errors about monitoring messages.
pub const MONITORING: &str = "FRIMonitoringMessage";
/// Name used in errors about command messages.
pub const COMMAND: &str = "FRICommandMessage";

/// Largest number of transformations in one message (nanopb array size).
const MAX_TRANSFORMATIONS: usize = 5;
/// Largest number of IO values in one message (nanopb array size).
const MAX_IO_VALUES: usize = 10;
/// Largest transformation / IO name in bytes, excluding the NUL the SDK stores.
const MAX_NAME_BYTES: usize = 63;

/// Validated header fields.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Header {
    /// Message identifier (already checked).
    pub message_identifier: u32,
    /// Sender's sequence counter.
    pub sequence_counter: u32,
    /// Reflected sequence counter.
    pub reflected_sequence_counter: u32,
}

impl Header {
    /// The prost form.
    pub fn to_message(self) -> MessageHeader {
        MessageHeader {
            message_identifier: Some(self.message_identifier),
            sequence_counter: Some(self.sequence_counter),
            reflected_sequence_counter: Some(self.reflected_sequence_counter),
        }
    }
}

fn check_size(message: &'static str, bytes: &[u8]) -> Result<()> {
    if bytes.is_empty() {
        return Err(FriError::EmptyDatagram { message });
    }
    if bytes.len() > MAX_DATAGRAM_SIZE {
        return Err(FriError::DatagramTooLarge {
            message,
            len: bytes.len(),
            max: MAX_DATAGRAM_SIZE,
        });
    }
    Ok(())
}

/// Checks a header's presence, completeness and identifier.
pub fn check_header(
    message: &'static str,
    header: Option<&MessageHeader>,
    expected_id: u32,
) -> Result<Header> {
    let header = header.ok_or(FriError::MissingField {
        message,
        field: "header",
    })?;
    let id = header.message_identifier.ok_or(FriError::MissingField {
        message,
        field: "header.messageIdentifier",
    })?;
    let seq = header.sequence_counter.ok_or(FriError::MissingField {
        message,
        field: "header.sequenceCounter",
    })?;
    let reflected = header
        .reflected_sequence_counter
        .ok_or(FriError::MissingField {
            message,
            field: "header.reflectedSequenceCounter",
        })?;
    if id != expected_id {
        return Err(FriError::WrongMessageId {
            message,
            expected: expected_id,
            found: id,
        });
    }
    Ok(Header {
        message_identifier: id,
        sequence_counter: seq,
        reflected_sequence_counter: reflected,
    })
}

fn check_enum<E: TryFrom<i32>>(
    message: &'static str,
    field: &'static str,
    value: Option<i32>,
) -> Result<()> {
    match value {
        Some(v) if E::try_from(v).is_err() => Err(FriError::UnknownEnumValue {
            message,
            field,
            value: v,
        }),
        _ => Ok(()),
    }
}

fn require_enum<E: TryFrom<i32>>(
    message: &'static str,
    field: &'static str,
    value: Option<i32>,
) -> Result<E> {
    let v = value.ok_or(FriError::MissingField { message, field })?;
    E::try_from(v).map_err(|_| FriError::UnknownEnumValue {
        message,
        field,
        value: v,
    })
}

/// Reads a 7-joint vector, checking count and finiteness.
pub fn joints(
    message: &'static str,
    field: &'static str,
    values: &JointValues,
) -> Result<[f64; NUM_JOINTS]> {
    let found = values.value.len();
    if found != NUM_JOINTS {
        return Err(FriError::JointCount {
            message,
            field,
            expected: NUM_JOINTS,
            found,
        });
    }
    let mut q = [0.0; NUM_JOINTS];
    for (i, (dst, &src)) in q.iter_mut().zip(&values.value).enumerate() {
        if !src.is_finite() {
            return Err(FriError::NonFinite {
                what: field,
                joint: i,
            });
        }
        *dst = src;
    }
    Ok(q)
}

fn check_joints(message: &'static str, field: &'static str, v: Option<&JointValues>) -> Result<()> {
    match v {
        Some(v) => joints(message, field, v).map(|_| ()),
        None => Ok(()),
    }
}

fn check_timestamp(
    message: &'static str,
    field: &'static str,
    t: Option<&TimeStamp>,
) -> Result<()> {
    let Some(t) = t else { return Ok(()) };
    if t.sec.is_none() {
        return Err(FriError::MissingField { message, field });
    }
    match t.nanosec {
        None => Err(FriError::MissingField { message, field }),
        Some(ns) if ns >= 1_000_000_000 => Err(FriError::InvalidValue {
            what: field,
            value: format!("nanosec = {ns}"),
        }),
        Some(_) => Ok(()),
    }
}

fn check_transformations(message: &'static str, list: &[Transformation]) -> Result<()> {
    if list.len() > MAX_TRANSFORMATIONS {
        return Err(FriError::InvalidValue {
            what: "transformations",
            value: format!("{} entries (max {MAX_TRANSFORMATIONS})", list.len()),
        });
    }
    for t in list {
        let name = t.name.as_ref().ok_or(FriError::MissingField {
            message,
            field: "Transformation.name",
        })?;
        if name.len() > MAX_NAME_BYTES {
            return Err(FriError::InvalidValue {
                what: "Transformation.name",
                value: format!("{} bytes (max {MAX_NAME_BYTES})", name.len()),
            });
        }
        if t.matrix.len() > 12 {
            return Err(FriError::InvalidValue {
                what: "Transformation.matrix",
                value: format!("{} values (max 12)", t.matrix.len()),
            });
        }
        check_timestamp(message, "Transformation.timestamp", t.timestamp.as_ref())?;
    }
    Ok(())
}

fn check_io(message: &'static str, list: &[FriIoValue]) -> Result<()> {
    if list.len() > MAX_IO_VALUES {
        return Err(FriError::InvalidValue {
            what: "FriIOValue list",
            value: format!("{} entries (max {MAX_IO_VALUES})", list.len()),
        });
    }
    for io in list {
        let name = io.name.as_ref().ok_or(FriError::MissingField {
            message,
            field: "FriIOValue.name",
        })?;
        if name.len() > MAX_NAME_BYTES {
            return Err(FriError::InvalidValue {
                what: "FriIOValue.name",
                value: format!("{} bytes (max {MAX_NAME_BYTES})", name.len()),
            });
        }
        require_enum::<FriIoType>(message, "FriIOValue.type", io.r#type)?;
        require_enum::<FriIoDirection>(message, "FriIOValue.direction", io.direction)?;
    }
    Ok(())
}

/// Checks a monitoring message as the client receives it.
pub fn validate_monitoring(msg: &FriMonitoringMessage) -> Result<Header> {
    const M: &str = MONITORING;
    let header = check_header(M, msg.header.as_ref(), LBR_MONITOR_MESSAGE_ID)?;
    // The session needs the state; the controller always sends connectionInfo.
    let ci = msg.connection_info.as_ref().ok_or(FriError::MissingField {
        message: M,
        field: "connectionInfo",
    })?;
    require_enum::<SessionState>(M, "connectionInfo.sessionState", ci.session_state)?;
    require_enum::<ConnectionQuality>(M, "connectionInfo.quality", ci.quality)?;
    if let Some(period) = ci.send_period
        && !(1..=100).contains(&period)
    {
        return Err(FriError::InvalidValue {
            what: "connectionInfo.sendPeriod",
            value: format!("{period} ms (allowed 1..=100)"),
        });
    }
    if let Some(mult) = ci.receive_multiplier
        && !(1..=100).contains(&mult)
    {
        return Err(FriError::InvalidValue {
            what: "connectionInfo.receiveMultiplier",
            value: format!("{mult} (allowed 1..=100)"),
        });
    }
    if let Some(ri) = &msg.robot_info {
        check_enum::<SafetyState>(M, "robotInfo.safetyState", ri.safety_state)?;
        check_enum::<OperationMode>(M, "robotInfo.operationMode", ri.operation_mode)?;
        check_enum::<ControlMode>(M, "robotInfo.controlMode", ri.control_mode)?;
        if ri.drive_state.len() > 12 {
            return Err(FriError::InvalidValue {
                what: "robotInfo.driveState",
                value: format!("{} entries (max 12)", ri.drive_state.len()),
            });
        }
        for &d in &ri.drive_state {
            check_enum::<DriveState>(M, "robotInfo.driveState", Some(d))?;
        }
    }
    if let Some(md) = &msg.monitor_data {
        check_joints(
            M,
            "monitorData.measuredJointPosition",
            md.measured_joint_position.as_ref(),
        )?;
        check_joints(M, "monitorData.measuredTorque", md.measured_torque.as_ref())?;
        check_joints(
            M,
            "monitorData.commandedJointPosition",
            md.commanded_joint_position.as_ref(),
        )?;
        check_joints(
            M,
            "monitorData.commandedTorque",
            md.commanded_torque.as_ref(),
        )?;
        check_joints(M, "monitorData.externalTorque", md.external_torque.as_ref())?;
        check_io(M, &md.read_io_request)?;
        check_timestamp(M, "monitorData.timestamp", md.timestamp.as_ref())?;
    }
    if let Some(ipo) = &msg.ipo_data {
        check_joints(M, "ipoData.jointPosition", ipo.joint_position.as_ref())?;
        check_enum::<ClientCommandMode>(M, "ipoData.clientCommandMode", ipo.client_command_mode)?;
        check_enum::<OverlayType>(M, "ipoData.overlayType", ipo.overlay_type)?;
        if let Some(tp) = ipo.tracking_performance
            && !(tp.is_finite() && (0.0..=1.0).contains(&tp))
        {
            return Err(FriError::InvalidValue {
                what: "ipoData.trackingPerformance",
                value: format!("{tp} (allowed 0..=1)"),
            });
        }
    }
    check_transformations(M, &msg.requested_transformations)?;
    Ok(header)
}

/// Checks a command message as the controller receives it.
pub fn validate_command(msg: &FriCommandMessage) -> Result<Header> {
    const M: &str = COMMAND;
    let header = check_header(M, msg.header.as_ref(), LBR_COMMAND_MESSAGE_ID)?;
    if let Some(cd) = &msg.command_data {
        check_joints(M, "commandData.jointPosition", cd.joint_position.as_ref())?;
        check_joints(M, "commandData.jointTorque", cd.joint_torque.as_ref())?;
        if let Some(w) = &cd.cartesian_wrench_feed_forward {
            if w.element.len() > 6 {
                return Err(FriError::InvalidValue {
                    what: "commandData.cartesianWrenchFeedForward",
                    value: format!("{} values (max 6)", w.element.len()),
                });
            }
            if let Some(i) = w.element.iter().position(|v| !v.is_finite()) {
                return Err(FriError::NonFinite {
                    what: "commandData.cartesianWrenchFeedForward",
                    joint: i,
                });
            }
        }
        check_transformations(M, &cd.commanded_transformations)?;
        check_io(M, &cd.write_io_request)?;
    }
    Ok(header)
}

/// Decodes and validates a monitoring datagram (client side).
pub fn decode_monitoring(bytes: &[u8]) -> Result<FriMonitoringMessage> {
    decode_monitoring_with_header(bytes).map(|(_, msg)| msg)
}

/// [`decode_monitoring`], also returning the validated header.
pub fn decode_monitoring_with_header(bytes: &[u8]) -> Result<(Header, FriMonitoringMessage)> {
    check_size(MONITORING, bytes)?;
    let msg = FriMonitoringMessage::decode(bytes).map_err(|source| FriError::Decode {
        message: MONITORING,
        source,
    })?;
    let header = validate_monitoring(&msg)?;
    Ok((header, msg))
}

/// Decodes and validates a command datagram (controller side).
pub fn decode_command(bytes: &[u8]) -> Result<FriCommandMessage> {
    decode_command_with_header(bytes).map(|(_, msg)| msg)
}

/// [`decode_command`], also returning the validated header.
pub fn decode_command_with_header(bytes: &[u8]) -> Result<(Header, FriCommandMessage)> {
    check_size(COMMAND, bytes)?;
    let msg = FriCommandMessage::decode(bytes).map_err(|source| FriError::Decode {
        message: COMMAND,
        source,
    })?;
    let header = validate_command(&msg)?;
    Ok((header, msg))
}

fn encode_into<M: Message>(message: &'static str, msg: &M, buf: &mut [u8]) -> Result<usize> {
    let needed = msg.encoded_len();
    let available = buf.len().min(MAX_DATAGRAM_SIZE);
    if needed > available {
        return Err(FriError::BufferTooSmall {
            message,
            needed,
            available,
        });
    }
    let mut out = &mut buf[..needed];
    msg.encode(&mut out).map_err(|_| FriError::BufferTooSmall {
        message,
        needed,
        available,
    })?;
    Ok(needed)
}

/// Validates and encodes a command message into `buf` (client side); returns its length.
pub fn encode_command(msg: &FriCommandMessage, buf: &mut [u8]) -> Result<usize> {
    validate_command(msg)?;
    encode_into(COMMAND, msg, buf)
}

/// Validates and encodes a monitoring message into `buf` (controller side); returns its length.
pub fn encode_monitoring(msg: &FriMonitoringMessage, buf: &mut [u8]) -> Result<usize> {
    validate_monitoring(msg)?;
    encode_into(MONITORING, msg, buf)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::{ConnectionInfo, MessageCommandData, MessageMonitorData};

    fn monitoring() -> FriMonitoringMessage {
        FriMonitoringMessage {
            header: Some(
                Header {
                    message_identifier: LBR_MONITOR_MESSAGE_ID,
                    sequence_counter: 5,
                    reflected_sequence_counter: 4,
                }
                .to_message(),
            ),
            connection_info: Some(ConnectionInfo {
                session_state: Some(SessionState::MonitoringReady as i32),
                quality: Some(ConnectionQuality::Excellent as i32),
                send_period: Some(5),
                receive_multiplier: Some(1),
            }),
            monitor_data: Some(MessageMonitorData {
                measured_joint_position: Some(JointValues::from_array(&[0.1; 7])),
                timestamp: Some(TimeStamp {
                    sec: Some(10),
                    nanosec: Some(20),
                }),
                ..Default::default()
            }),
            ..Default::default()
        }
    }

    fn encode_raw<M: Message>(m: &M) -> Vec<u8> {
        m.encode_to_vec()
    }

    #[test]
    fn round_trip_monitoring() {
        let m = monitoring();
        let mut buf = [0u8; MAX_DATAGRAM_SIZE];
        let n = encode_monitoring(&m, &mut buf).unwrap();
        assert_eq!(decode_monitoring(&buf[..n]).unwrap(), m);
    }

    #[test]
    fn joint_values_are_unpacked_on_the_wire() {
        // Field 1, wire type 1 (fixed64) => tag byte 0x09, once per element, as the SDK writes.
        let jv = JointValues::from_array(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        let bytes = encode_raw(&jv);
        assert_eq!(bytes.len(), 7 * 9);
        assert!(bytes.chunks(9).all(|c| c[0] == 0x09));
    }

    #[test]
    fn packed_joint_values_also_decode() {
        // 0x0a = field 1, length-delimited: the packed layout.
        let mut bytes = vec![0x0a, 56];
        for i in 0..7 {
            bytes.extend_from_slice(&(i as f64).to_le_bytes());
        }
        let jv = JointValues::decode(bytes.as_slice()).unwrap();
        assert_eq!(jv.value, vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
    }

    #[test]
    fn rejects_wrong_message_id() {
        let mut m = monitoring();
        if let Some(h) = m.header.as_mut() {
            h.message_identifier = Some(LBR_COMMAND_MESSAGE_ID);
        }
        let err = decode_monitoring(&encode_raw(&m)).unwrap_err();
        assert!(
            matches!(
                err,
                FriError::WrongMessageId {
                    found: LBR_COMMAND_MESSAGE_ID,
                    ..
                }
            ),
            "{err}"
        );
    }

    #[test]
    fn rejects_missing_required_field() {
        let mut m = monitoring();
        if let Some(h) = m.header.as_mut() {
            h.sequence_counter = None;
        }
        let err = decode_monitoring(&encode_raw(&m)).unwrap_err();
        assert_eq!(
            err.to_string(),
            "FRIMonitoringMessage: missing required field `header.sequenceCounter`"
        );
        let mut m = monitoring();
        m.header = None;
        assert!(matches!(
            decode_monitoring(&encode_raw(&m)),
            Err(FriError::MissingField {
                field: "header",
                ..
            })
        ));
    }

    #[test]
    fn rejects_oversized_truncated_and_empty() {
        assert!(matches!(
            decode_monitoring(&[]),
            Err(FriError::EmptyDatagram { .. })
        ));
        assert!(matches!(
            decode_monitoring(&[0u8; MAX_DATAGRAM_SIZE + 1]),
            Err(FriError::DatagramTooLarge { len: 1501, .. })
        ));
        let bytes = encode_raw(&monitoring());
        for cut in 1..bytes.len() {
            assert!(
                decode_monitoring(&bytes[..cut]).is_err(),
                "truncated at {cut} accepted"
            );
        }
    }

    #[test]
    fn rejects_unknown_enum_and_bad_joint_count() {
        let mut m = monitoring();
        if let Some(ci) = m.connection_info.as_mut() {
            ci.session_state = Some(9);
        }
        let err = decode_monitoring(&encode_raw(&m)).unwrap_err();
        assert!(
            matches!(err, FriError::UnknownEnumValue { value: 9, .. }),
            "{err}"
        );

        let mut m = monitoring();
        if let Some(md) = m.monitor_data.as_mut() {
            md.measured_joint_position = Some(JointValues {
                value: vec![0.0; 6],
            });
        }
        let err = decode_monitoring(&encode_raw(&m)).unwrap_err();
        assert!(
            matches!(err, FriError::JointCount { found: 6, .. }),
            "{err}"
        );

        let mut m = monitoring();
        if let Some(md) = m.monitor_data.as_mut() {
            md.measured_joint_position = Some(JointValues {
                value: vec![0.0, 0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0],
            });
        }
        assert!(matches!(
            decode_monitoring(&encode_raw(&m)),
            Err(FriError::NonFinite { joint: 2, .. })
        ));
    }

    #[test]
    fn command_round_trip_and_buffer_check() {
        let c = FriCommandMessage {
            header: Some(
                Header {
                    message_identifier: LBR_COMMAND_MESSAGE_ID,
                    sequence_counter: 1,
                    reflected_sequence_counter: 5,
                }
                .to_message(),
            ),
            command_data: Some(MessageCommandData {
                joint_position: Some(JointValues::from_array(&[0.2; 7])),
                ..Default::default()
            }),
            end_of_message_data: None,
        };
        let mut buf = [0u8; 256];
        let n = encode_command(&c, &mut buf).unwrap();
        assert_eq!(decode_command(&buf[..n]).unwrap(), c);
        let mut small = [0u8; 10];
        assert!(matches!(
            encode_command(&c, &mut small),
            Err(FriError::BufferTooSmall { .. })
        ));
        // A command is not a monitoring message: its body does not parse as one, and a bare
        // command header is caught by the identifier check.
        assert!(decode_monitoring(&buf[..n]).is_err());
        let bare = FriCommandMessage {
            command_data: None,
            ..c
        };
        let n = encode_command(&bare, &mut buf).unwrap();
        assert!(matches!(
            decode_monitoring(&buf[..n]),
            Err(FriError::WrongMessageId {
                found: LBR_COMMAND_MESSAGE_ID,
                ..
            })
        ));
    }
}
