//! FRI 1.15 protobuf messages, written by hand for prost.
//!
//! # Why by hand
//! KUKA's FRI Client SDK ships nanopb-generated C (`FRIMessages.pb.{c,h}`, nanopb 0.2.8) but
//! no `.proto` file, and this build has no `protoc`. The schema below was rebuilt from the
//! field list of the 1.15 descriptor tables (shared/facts.md §1.2): every field number, type
//! and label matches the 1.15 layout, so bytes from the SDK decode here and bytes encoded here
//! decode in the SDK. Nothing of KUKA's code is copied.
//!
//! # proto2 `required` fields
//! FRI is proto2. prost never checks `required` fields on decode (a missing one would read as
//! zero, which for `sessionState` means IDLE and for `messageIdentifier` means "0"). To be
//! able to reject a datagram that lacks one, every proto2 `required` field is declared here
//! as *optional* (`Option<T>`) and [`crate::codec`] checks presence and names the missing
//! field. The encoders always set them, so the wire image is that of a `required` field.
//!
//! # Wire layout details that matter
//! * [`JointValues::value`] is a `repeated double` that the SDK writes **unpacked** (one
//!   `0x09` tag per element); it is declared `packed = "false"` so prost writes the same.
//! * `CartesianVector.element`, `Transformation.matrix` and `RobotInfo.driveState` are static
//!   nanopb arrays, which nanopb 0.2.8 writes **packed**; declared packed here.
//! * Decoding accepts both layouts for every repeated scalar (prost and nanopb both do).
//!
//! # What FRI 2.x changes (not implemented; this crate speaks 1.15)
//! * `MessageMonitorData.commandedJointPosition` (3) is **removed** in 2.x. Code reading it
//!   must fall back to the interpolator position (`MessageIpoData.jointPosition`).
//! * 2.7 adds `MessageMonitorData.externalForce` (6, `CartesianVector`),
//!   `measuredCartesianPose` (9, `QuaternionTransformation`) and
//!   `measuredRedundancyInformation` (10).
//! * 2.x adds `MessageIpoData.cartesianPose` (2) and `redundancyInformation` (3), and
//!   `MessageCommandData.cartesianPose` (6) and `redundancyInformation` (7).
//! * 2.x replaces `Transformation` (name + 3x4 matrix, mm) by `QuaternionTransformation`
//!   (`element` = `[t_x, t_y, t_z, q_w, q_x, q_y, q_z]`, t in mm).
//! * `ClientCommandMode::Position` is renamed `JOINT_POSITION` and `CARTESIAN_POSE = 4` is
//!   added; 2.x adds a `RedundancyStrategy` enum (E1 = 0, NONE = 4).
//! * `endOfMessageData` (15) is still present in 2.5 and removed in 2.7.
//! * The message identifiers (0x245142 / 0x34001) are the same from 1.11 to 2.7.
//!
//! Because protobuf skips unknown fields, a 2.x monitoring message without field 3 still
//! decodes here; [`crate::session`] falls back to the interpolator position for the
//! monitor-mode echo when `commandedJointPosition` is absent.

/// `LBRState::LBRMONITORMESSAGEID`: identifier of controller → client messages.
pub const LBR_MONITOR_MESSAGE_ID: u32 = 0x0024_5142;
/// `LBRCommand::LBRCOMMANDMESSAGEID`: identifier of client → controller messages.
pub const LBR_COMMAND_MESSAGE_ID: u32 = 0x0003_4001;
/// `FRI_MONITOR_MSG_MAX_SIZE` and `FRI_COMMAND_MSG_MAX_SIZE`: largest datagram either side sends.
pub const MAX_DATAGRAM_SIZE: usize = 1500;
/// Number of joint values in an LBR message: the arm's joints.
pub const NUM_JOINTS: usize = b2b_robot::N_JOINTS;
/// The port the client binds by default (KUKA allows 30200..=30209).
pub const DEFAULT_PORT: u16 = 30200;

/// `FRISessionState`: the FRI session state reported by the controller.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum SessionState {
    /// `IDLE`: no session; the client never replies.
    Idle = 0,
    /// `MONITORING_WAIT`: connection open, not yet real-time capable.
    MonitoringWait = 1,
    /// `MONITORING_READY`: real-time exchange running; commanding may start.
    MonitoringReady = 2,
    /// `COMMANDING_WAIT`: the overlay motion is being synchronised.
    CommandingWait = 3,
    /// `COMMANDING_ACTIVE`: client joint positions are applied to the robot.
    CommandingActive = 4,
}

impl SessionState {
    /// The name the FRI protocol uses.
    pub fn proto_name(self) -> &'static str {
        match self {
            SessionState::Idle => "IDLE",
            SessionState::MonitoringWait => "MONITORING_WAIT",
            SessionState::MonitoringReady => "MONITORING_READY",
            SessionState::CommandingWait => "COMMANDING_WAIT",
            SessionState::CommandingActive => "COMMANDING_ACTIVE",
        }
    }
}

impl std::fmt::Display for SessionState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.proto_name())
    }
}

/// `FRIConnectionQuality`, as judged by the controller.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum ConnectionQuality {
    /// `POOR`.
    Poor = 0,
    /// `FAIR`: "insufficient for command mode" (SDK comment).
    Fair = 1,
    /// `GOOD`: "sufficient for command mode".
    Good = 2,
    /// `EXCELLENT`.
    Excellent = 3,
}

/// `SafetyState`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum SafetyState {
    /// `NORMAL_OPERATION`.
    NormalOperation = 0,
    /// `SAFETY_STOP_LEVEL_0`.
    SafetyStopLevel0 = 1,
    /// `SAFETY_STOP_LEVEL_1`.
    SafetyStopLevel1 = 2,
    /// `SAFETY_STOP_LEVEL_2`.
    SafetyStopLevel2 = 3,
}

/// `OperationMode`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum OperationMode {
    /// `TEST_MODE_1` (T1).
    TestMode1 = 0,
    /// `TEST_MODE_2` (T2).
    TestMode2 = 1,
    /// `AUTOMATIC_MODE`.
    AutomaticMode = 2,
}

/// `DriveState`, one per joint.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum DriveState {
    /// `OFF`.
    Off = 0,
    /// `TRANSITIONING`.
    Transitioning = 1,
    /// `ACTIVE`.
    Active = 2,
}

/// `ControlMode` of the robot application.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum ControlMode {
    /// `POSITION_CONTROLMODE`.
    PositionControlMode = 0,
    /// `CARTESIAN_IMPEDANCE_CONTROLMODE`.
    CartesianImpedanceControlMode = 1,
    /// `JOINT_IMPEDANCE_CONTROLMODE`.
    JointImpedanceControlMode = 2,
    /// `NO_CONTROLMODE`.
    NoControlMode = 3,
}

/// `ClientCommandMode` (1.x names; 2.x renames `POSITION` to `JOINT_POSITION`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum ClientCommandMode {
    /// `NO_COMMAND_MODE`.
    NoCommandMode = 0,
    /// `POSITION`.
    Position = 1,
    /// `WRENCH`.
    Wrench = 2,
    /// `TORQUE`.
    Torque = 3,
}

/// `OverlayType`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum OverlayType {
    /// `NO_OVERLAY`.
    NoOverlay = 0,
    /// `JOINT`.
    Joint = 1,
    /// `CARTESIAN`.
    Cartesian = 2,
}

/// `FriIOType`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum FriIoType {
    /// `BOOLEAN`.
    Boolean = 0,
    /// `DIGITAL`.
    Digital = 1,
    /// `ANALOG`.
    Analog = 2,
}

/// `FriIODirection`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum FriIoDirection {
    /// `INPUT`.
    Input = 0,
    /// `OUTPUT`.
    Output = 1,
}

/// `JointValues { repeated double value = 1; }` (unpacked on the wire, 7 values for an LBR).
#[derive(Clone, PartialEq, prost::Message)]
pub struct JointValues {
    /// Joint values (rad or Nm).
    #[prost(double, repeated, packed = "false", tag = "1")]
    pub value: Vec<f64>,
}

impl JointValues {
    /// Joint values from a 7-array.
    pub fn from_array(q: &[f64; NUM_JOINTS]) -> Self {
        Self { value: q.to_vec() }
    }
}

/// `TimeStamp` (Unix time of the controller clock). Both fields are proto2 `required`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TimeStamp {
    /// Seconds (required).
    #[prost(uint32, optional, tag = "1")]
    pub sec: Option<u32>,
    /// Nanoseconds (required).
    #[prost(uint32, optional, tag = "2")]
    pub nanosec: Option<u32>,
}

/// `CartesianVector { repeated double element = 1; }` (packed, up to 6 values).
#[derive(Clone, PartialEq, prost::Message)]
pub struct CartesianVector {
    /// Elements.
    #[prost(double, repeated, packed = "true", tag = "1")]
    pub element: Vec<f64>,
}

/// `Checksum`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Checksum {
    /// CRC32 (never set by the SDK).
    #[prost(int32, optional, tag = "1")]
    pub crc32: Option<i32>,
}

/// `Transformation` (1.x): a named 3x4 matrix, translation in mm.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Transformation {
    /// Name (required, ≤ 64 bytes including NUL in the SDK).
    #[prost(string, optional, tag = "1")]
    pub name: Option<String>,
    /// Row-major 3x4 matrix (12 values, packed).
    #[prost(double, repeated, packed = "true", tag = "2")]
    pub matrix: Vec<f64>,
    /// Time stamp.
    #[prost(message, optional, tag = "3")]
    pub timestamp: Option<TimeStamp>,
}

/// `FriIOValue` (not in FRI 1.11).
#[derive(Clone, PartialEq, prost::Message)]
pub struct FriIoValue {
    /// "IOGroupName.IOName" (required).
    #[prost(string, optional, tag = "1")]
    pub name: Option<String>,
    /// Type (required).
    #[prost(enumeration = "FriIoType", optional, tag = "2")]
    pub r#type: Option<i32>,
    /// Direction (required).
    #[prost(enumeration = "FriIoDirection", optional, tag = "3")]
    pub direction: Option<i32>,
    /// Value of a boolean or digital IO.
    #[prost(uint64, optional, tag = "4")]
    pub digital_value: Option<u64>,
    /// Value of an analog IO.
    #[prost(double, optional, tag = "5")]
    pub analog_value: Option<f64>,
}

/// `MessageHeader`: all three fields are proto2 `required`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct MessageHeader {
    /// [`LBR_MONITOR_MESSAGE_ID`] or [`LBR_COMMAND_MESSAGE_ID`].
    #[prost(uint32, optional, tag = "1")]
    pub message_identifier: Option<u32>,
    /// Sender's counter, incremented per message sent.
    #[prost(uint32, optional, tag = "2")]
    pub sequence_counter: Option<u32>,
    /// The last sequence counter received from the other side.
    #[prost(uint32, optional, tag = "3")]
    pub reflected_sequence_counter: Option<u32>,
}

/// `ConnectionInfo`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct ConnectionInfo {
    /// Session state (required).
    #[prost(enumeration = "SessionState", optional, tag = "1")]
    pub session_state: Option<i32>,
    /// Connection quality (required).
    #[prost(enumeration = "ConnectionQuality", optional, tag = "2")]
    pub quality: Option<i32>,
    /// Send period in **milliseconds**.
    #[prost(uint32, optional, tag = "3")]
    pub send_period: Option<u32>,
    /// The client answers every `receiveMultiplier`-th message.
    #[prost(uint32, optional, tag = "4")]
    pub receive_multiplier: Option<u32>,
}

/// `RobotInfo`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct RobotInfo {
    /// Number of joints (7).
    #[prost(int32, optional, tag = "1")]
    pub number_of_joints: Option<i32>,
    /// Safety state.
    #[prost(enumeration = "SafetyState", optional, tag = "2")]
    pub safety_state: Option<i32>,
    /// Drive state per joint (packed, as nanopb writes static arrays).
    #[prost(enumeration = "DriveState", repeated, packed = "true", tag = "5")]
    pub drive_state: Vec<i32>,
    /// Operation mode (T1, T2, AUT).
    #[prost(enumeration = "OperationMode", optional, tag = "6")]
    pub operation_mode: Option<i32>,
    /// Control mode.
    #[prost(enumeration = "ControlMode", optional, tag = "7")]
    pub control_mode: Option<i32>,
}

/// `MessageMonitorData`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct MessageMonitorData {
    /// Measured joint positions (rad).
    #[prost(message, optional, tag = "1")]
    pub measured_joint_position: Option<JointValues>,
    /// Measured torques (Nm).
    #[prost(message, optional, tag = "2")]
    pub measured_torque: Option<JointValues>,
    /// Commanded joint positions (rad). **Removed in FRI 2.x.**
    #[prost(message, optional, tag = "3")]
    pub commanded_joint_position: Option<JointValues>,
    /// Commanded torques (Nm).
    #[prost(message, optional, tag = "4")]
    pub commanded_torque: Option<JointValues>,
    /// Estimated external torques (Nm).
    #[prost(message, optional, tag = "5")]
    pub external_torque: Option<JointValues>,
    /// IO values (max 10).
    #[prost(message, repeated, tag = "8")]
    pub read_io_request: Vec<FriIoValue>,
    /// Controller time stamp of the measurement.
    #[prost(message, optional, tag = "15")]
    pub timestamp: Option<TimeStamp>,
}

/// `MessageIpoData`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct MessageIpoData {
    /// Interpolator joint positions (rad).
    #[prost(message, optional, tag = "1")]
    pub joint_position: Option<JointValues>,
    /// Client command mode of the running overlay.
    #[prost(enumeration = "ClientCommandMode", optional, tag = "10")]
    pub client_command_mode: Option<i32>,
    /// Overlay type.
    #[prost(enumeration = "OverlayType", optional, tag = "11")]
    pub overlay_type: Option<i32>,
    /// Tracking performance 0..1 (0 unless COMMANDING_ACTIVE).
    #[prost(double, optional, tag = "12")]
    pub tracking_performance: Option<f64>,
}

/// `MessageCommandData`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct MessageCommandData {
    /// Commanded joint positions (rad).
    #[prost(message, optional, tag = "1")]
    pub joint_position: Option<JointValues>,
    /// Cartesian wrench feed-forward (6 values).
    #[prost(message, optional, tag = "2")]
    pub cartesian_wrench_feed_forward: Option<CartesianVector>,
    /// Joint torques (Nm).
    #[prost(message, optional, tag = "3")]
    pub joint_torque: Option<JointValues>,
    /// Transformations (max 5).
    #[prost(message, repeated, tag = "4")]
    pub commanded_transformations: Vec<Transformation>,
    /// IO writes (max 10).
    #[prost(message, repeated, tag = "5")]
    pub write_io_request: Vec<FriIoValue>,
}

/// `MessageEndOf` (1.x only; the SDK never sets it).
#[derive(Clone, PartialEq, prost::Message)]
pub struct MessageEndOf {
    /// Message length.
    #[prost(int32, optional, tag = "1")]
    pub message_length: Option<i32>,
    /// Checksum.
    #[prost(message, optional, tag = "2")]
    pub message_checksum: Option<Checksum>,
}

/// `FRIMonitoringMessage` (controller → client).
#[derive(Clone, PartialEq, prost::Message)]
pub struct FriMonitoringMessage {
    /// Header (required).
    #[prost(message, optional, tag = "1")]
    pub header: Option<MessageHeader>,
    /// Robot info.
    #[prost(message, optional, tag = "2")]
    pub robot_info: Option<RobotInfo>,
    /// Monitor data.
    #[prost(message, optional, tag = "3")]
    pub monitor_data: Option<MessageMonitorData>,
    /// Connection info.
    #[prost(message, optional, tag = "4")]
    pub connection_info: Option<ConnectionInfo>,
    /// Interpolator data.
    #[prost(message, optional, tag = "5")]
    pub ipo_data: Option<MessageIpoData>,
    /// Requested transformations (max 5).
    #[prost(message, repeated, tag = "6")]
    pub requested_transformations: Vec<Transformation>,
    /// End-of-message data (1.x only).
    #[prost(message, optional, tag = "15")]
    pub end_of_message_data: Option<MessageEndOf>,
}

/// `FRICommandMessage` (client → controller).
#[derive(Clone, PartialEq, prost::Message)]
pub struct FriCommandMessage {
    /// Header (required).
    #[prost(message, optional, tag = "1")]
    pub header: Option<MessageHeader>,
    /// Command data.
    #[prost(message, optional, tag = "2")]
    pub command_data: Option<MessageCommandData>,
    /// End-of-message data (1.x only).
    #[prost(message, optional, tag = "15")]
    pub end_of_message_data: Option<MessageEndOf>,
}
