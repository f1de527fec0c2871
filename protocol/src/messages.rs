//! Messages between agents and the coordinator (zenoh payloads, JSON).
//!
//! Every message travels in an [`Envelope`]: the schema version, the sending
//! robot's id and a per-agent sequence number that survives agent restarts. A
//! receiver runs [`Envelope::validate`] before trusting anything: an unknown
//! version, a robot id that disagrees with the key expression, or a non-finite
//! number rejects the message (and the receiver counts it).
//!
//! Key expressions (all under [`KEY_ROOT`]):
//!
//! | key | payload | who |
//! |---|---|---|
//! | `b2b/agent/{robot}/capture` | [`Capture`]: flange pose, board observation, `base_from_target` | agent, per capture |
//! | `b2b/agent/{robot}/hand_eye` | [`HandEyeUpdate`] | agent, when its captures allow it |
//! | `b2b/agent/{robot}/status` | [`AgentStatus`] | agent, on every change |
//! | `b2b/agent/{robot}/history` | queryable: every capture so far, for a (re)started coordinator | agent |
//! | `b2b/coordinator/result` | [`crate::CalibrationResult`], sender [`COORDINATOR`] | coordinator |
//! | `b2b/coordinator/failure` | [`RunFailure`]: the run's solve failed, and why | coordinator |
//! | `b2b/coordinator/session` | [`SessionAnnouncement`] | coordinator, twice a second |
//! | `b2b/coordinator/alive` | liveliness token | coordinator |
//!
//! Every message of an agent carries the session it heard announced; the
//! coordinator uses only captures, hand-eyes and statuses of its own session,
//! so an earlier run's messages replayed into a new run are dropped (signed
//! ones cannot be re-stamped: the session is inside what is signed).

use serde::{Deserialize, Serialize};

use crate::{Covariance6, Pose, ProtocolError};

/// The version of the message schema; a receiver rejects any other.
pub const SCHEMA_VERSION: u32 = 1;
/// The root of every key expression of the service.
pub const KEY_ROOT: &str = "b2b";

/// `b2b/agent/{robot}/{topic}`.
pub fn agent_key(robot: &str, topic: &str) -> String {
    format!("{KEY_ROOT}/agent/{robot}/{topic}")
}

/// The sender id in the envelopes the coordinator publishes (not a robot id a
/// cart can take: agents' keys live under `b2b/agent/`).
pub const COORDINATOR: &str = "coordinator";

/// What the drift watch's alarms name as the reference when a robot is
/// watched through the scene's features instead of another robot (not a
/// robot id a cart can take).
pub const SCENE: &str = "scene";

/// The key the coordinator publishes results on.
pub fn result_key() -> String {
    format!("{KEY_ROOT}/coordinator/result")
}

/// The key the coordinator's drift watch raises alarms on.
pub fn alarm_key() -> String {
    format!("{KEY_ROOT}/coordinator/alarm")
}

/// The key the coordinator publishes a failed solve on ([`RunFailure`]).
pub fn failure_key() -> String {
    format!("{KEY_ROOT}/coordinator/failure")
}

/// The coordinator's liveliness token.
pub fn coordinator_alive_key() -> String {
    format!("{KEY_ROOT}/coordinator/alive")
}

/// The key the coordinator announces its run's session on ([`SessionAnnouncement`]).
pub fn session_key() -> String {
    format!("{KEY_ROOT}/coordinator/session")
}

/// Length of a session id: 128 random bits in lowercase hex.
pub const SESSION_ID_LEN: usize = 32;

/// A session id is [`SESSION_ID_LEN`] lowercase hex digits.
pub fn validate_session_id(id: &str) -> Result<(), ProtocolError> {
    if id.len() != SESSION_ID_LEN
        || !id
            .chars()
            .all(|c| c.is_ascii_digit() || ('a'..='f').contains(&c))
    {
        return Err(ProtocolError::BadField {
            field: "session".into(),
            reason: format!(
                "'{}' is not a session id ({SESSION_ID_LEN} lowercase hex digits)",
                b2b_errors::excerpt(id)
            ),
        });
    }
    Ok(())
}

/// The session of a `coordinator run` (`b2b/coordinator/session`, announced
/// twice a second): agents echo it in every message's envelope from then on,
/// and accept a result only from the coordinator and with the session they
/// echo, so a result of another run (a stale coordinator, a replay) is never
/// taken for theirs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionAnnouncement {
    pub session: String,
}

impl Validate for SessionAnnouncement {
    fn validate(&self) -> Result<(), ProtocolError> {
        validate_session_id(&self.session)
    }
}

/// The longest [`RunFailure::reason`], in bytes.
pub const FAILURE_REASON_MAX: usize = 4096;

/// A run's solve failed (`b2b/coordinator/failure`, in the run's session):
/// the agents waiting for its result stop waiting and say why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunFailure {
    /// What failed, one line for an operator.
    pub reason: String,
}

impl Validate for RunFailure {
    fn validate(&self) -> Result<(), ProtocolError> {
        let bad = |reason: String| ProtocolError::BadField {
            field: "reason".into(),
            reason,
        };
        if self.reason.trim().is_empty() {
            return Err(bad("empty".into()));
        }
        if self.reason.len() > FAILURE_REASON_MAX {
            return Err(bad(format!(
                "{} bytes, at most {FAILURE_REASON_MAX}",
                self.reason.len()
            )));
        }
        // Printed on the agents' terminals: no escape sequences.
        if let Some(c) = self.reason.chars().find(|c| c.is_control() && *c != '\n') {
            return Err(bad(format!("holds the control character {c:?}")));
        }
        Ok(())
    }
}

/// A cart's robot id: a [`validate_robot_id`] that is not one of the names
/// the service takes for itself ([`COORDINATOR`], the sender of the
/// coordinator's envelopes, and [`SCENE`], the drift watch's scene
/// reference). Checked where a cart is named (its agent, its certificate, a
/// result to watch); envelopes are checked with [`validate_robot_id`], since
/// the coordinator's own carry [`COORDINATOR`].
pub fn validate_cart_id(id: &str) -> Result<(), ProtocolError> {
    validate_robot_id(id)?;
    if id == COORDINATOR || id == SCENE {
        return Err(ProtocolError::BadField {
            field: "robot".into(),
            reason: format!(
                "'{id}' is not a robot id: the name is taken ({COORDINATOR}: the coordinator's envelopes; {SCENE}: the drift watch's scene reference)"
            ),
        });
    }
    Ok(())
}

/// Ids in envelopes and key expressions (robots, and the coordinator as a
/// sender): letters, digits, `-` and `_` only.
pub fn validate_robot_id(id: &str) -> Result<(), ProtocolError> {
    if id.is_empty()
        || id.len() > 64
        || !id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    {
        return Err(ProtocolError::BadField {
            field: "robot".into(),
            reason: format!("'{id}' is not a robot id (1-64 of A-Z a-z 0-9 - _)"),
        });
    }
    Ok(())
}

/// A message with its schema version, sender and sequence number.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Envelope<T> {
    pub schema: u32,
    pub robot: String,
    /// Per agent, strictly increasing across restarts.
    pub seq: u64,
    /// The `coordinator run` session the sender is part of: an agent's echo of
    /// the announced one, the coordinator's own on its result. None before an
    /// agent has heard one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub session: Option<String>,
    pub body: T,
}

/// Checks the numbers of a message body.
pub trait Validate {
    fn validate(&self) -> Result<(), ProtocolError>;
}

impl<T: Validate> Envelope<T> {
    /// Wraps a body.
    pub fn new(robot: &str, seq: u64, body: T) -> Self {
        Envelope {
            schema: SCHEMA_VERSION,
            robot: robot.to_owned(),
            seq,
            session: None,
            body,
        }
    }

    /// The same message in `session`.
    pub fn in_session(mut self, session: Option<&str>) -> Self {
        self.session = session.map(str::to_owned);
        self
    }

    /// Checks the version, that the sender is the robot the key names, and the body.
    pub fn validate(&self, robot_in_key: &str) -> Result<(), ProtocolError> {
        if self.schema != SCHEMA_VERSION {
            return Err(ProtocolError::BadField {
                field: "schema".into(),
                reason: format!(
                    "version {} is not the supported {SCHEMA_VERSION}",
                    self.schema
                ),
            });
        }
        validate_robot_id(&self.robot)?;
        if let Some(s) = &self.session {
            validate_session_id(s)?;
        }
        if self.robot != robot_in_key {
            return Err(ProtocolError::BadField {
                field: "robot".into(),
                reason: format!(
                    "message says '{}' but was published under '{robot_in_key}'",
                    self.robot
                ),
            });
        }
        self.body.validate()
    }
}

fn finite(field: &str, values: &[f64]) -> Result<(), ProtocolError> {
    for (i, v) in values.iter().enumerate() {
        if !v.is_finite() {
            return Err(ProtocolError::NonFinite {
                field: format!("{field}[{i}]"),
                value: *v,
            });
        }
    }
    Ok(())
}

/// Camera intrinsics with OpenCV distortion `k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[,
/// tx, ty]]]]`: the project's one intrinsics type, in every message, in
/// `dataset.json`'s `camera` blocks and in the simulator's scenes. Each place checks
/// what it accepts (a message at most 8 terms, [`Validate`]; a dataset 4, 5, 8, 12 or
/// 14, `b2b_dataset::validate_camera`), and `b2b_dataset::camera_model` builds the math
/// core's projection from it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Missing in a file: none given (a dataset rejects that by name).
    #[serde(default)]
    pub dist: Vec<f64>,
    /// The camera gave no intrinsics: these are the agent's provisional estimate
    /// from its captures so far (a guess before the first fit), used for its own
    /// poses only. The coordinator fits the camera again from every capture's
    /// corners and refines it with the hand-eyes.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub estimated: bool,
}

impl Validate for Intrinsics {
    fn validate(&self) -> Result<(), ProtocolError> {
        finite("camera", &[self.fx, self.fy, self.cx, self.cy])?;
        finite("camera.dist", &self.dist)?;
        if self.fx <= 0.0
            || self.fy <= 0.0
            || self.width == 0
            || self.height == 0
            || self.dist.len() > 8
        {
            return Err(ProtocolError::BadField {
                field: "camera".into(),
                reason: "focal lengths and size must be positive, at most 8 distortion terms"
                    .into(),
            });
        }
        Ok(())
    }
}

/// What the agent saw of the board in one capture.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BoardObservation {
    /// Corner positions in the target frame (m).
    pub target_points: Vec<[f64; 3]>,
    /// The detected corners (px), paired with `target_points`.
    pub pixels: Vec<[f64; 2]>,
    #[serde(rename = "T_camera_target")]
    pub camera_from_target: Pose,
    /// Per-corner reprojection residual of the board pose (px).
    pub residuals_px: Vec<f64>,
    pub rms_px: f64,
    /// The centre of the whole target in its own frame (m): the mean of all its
    /// model points, seen in this capture or not. Every path (offline, live,
    /// replay) predicts touch errors around this one point.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_centre: Option<[f64; 3]>,
    /// Which target this is when a cell has several: its id among the
    /// dataset's further `targets`; `None` (the default): the main target.
    /// Robots that see different targets are placed through robots that see
    /// several; observations of one id are of one physical target.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<String>,
}

/// One capture: the flange pose (with the controller's timestamp), the board
/// observation or the reason it was rejected, and the hand-eye-corrected board
/// pose when the agent has a hand-eye.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Capture {
    /// The capture's index at the agent (stable across agent restarts; the
    /// receiver de-duplicates on it).
    pub index: u64,
    /// Controller time of the flange pose (s since the Unix epoch), when known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub controller_time_s: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<String>,
    #[serde(rename = "T_base_flange")]
    pub base_from_flange: Pose,
    pub camera: Intrinsics,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observation: Option<BoardObservation>,
    /// Why the capture is not usable, when it is not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rejected: Option<String>,
    /// `base_from_flange * flange_from_camera * camera_from_target`, with the
    /// agent's hand-eye at the time of the capture.
    #[serde(
        rename = "T_base_target",
        default,
        skip_serializing_if = "Option::is_none"
    )]
    pub base_from_target: Option<Pose>,
    /// Local image features lifted with the aligned depth, when the agent has depth
    /// (the RGB-D method's input; independent of the board observation).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub features: Option<FeatureSet>,
}

/// Local image features of one capture for the RGB-D method: keypoints, each one
/// lifted to 3-D with the aligned depth where the depth there is valid, and their
/// descriptors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureSet {
    /// `sift`, `akaze` or `orb`.
    pub kind: String,
    /// Keypoint positions (px, OpenCV convention).
    pub pixels: Vec<[f64; 2]>,
    /// Detector responses, paired with `pixels`.
    pub responses: Vec<f64>,
    /// Each keypoint in the camera frame (m); `null` where it has no valid depth.
    pub points_camera: Vec<Option<[f64; 3]>>,
    /// Bytes per descriptor.
    pub descriptor_len: usize,
    /// The descriptors, row after row (base64 on the wire).
    #[serde(with = "base64_bytes")]
    pub descriptors: Vec<u8>,
}

mod base64_bytes {
    use base64::Engine;
    use base64::engine::general_purpose::STANDARD;
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(bytes: &[u8], s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&STANDARD.encode(bytes))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
        let text = String::deserialize(d)?;
        STANDARD
            .decode(text.as_bytes())
            .map_err(|e| serde::de::Error::custom(format!("descriptors: not base64: {e}")))
    }
}

impl Validate for FeatureSet {
    fn validate(&self) -> Result<(), ProtocolError> {
        let bad = |reason: String| ProtocolError::BadField {
            field: "features".into(),
            reason,
        };
        if !matches!(self.kind.as_str(), "sift" | "akaze" | "orb") {
            return Err(bad(format!(
                "kind '{}': expected sift, akaze or orb",
                self.kind
            )));
        }
        let n = self.pixels.len();
        if self.responses.len() != n || self.points_camera.len() != n {
            return Err(bad(format!(
                "{n} pixels, {} responses and {} points (need equal counts)",
                self.responses.len(),
                self.points_camera.len()
            )));
        }
        if self.descriptors.len() != n * self.descriptor_len || (n > 0 && self.descriptor_len == 0)
        {
            return Err(bad(format!(
                "{n} descriptors of {} bytes need {} bytes, got {}",
                self.descriptor_len,
                n * self.descriptor_len,
                self.descriptors.len()
            )));
        }
        finite("features.pixels", &self.pixels.concat())?;
        finite("features.responses", &self.responses)?;
        for (i, p) in self.points_camera.iter().enumerate() {
            if let Some(p) = p {
                finite(&format!("features.points_camera[{i}]"), p)?;
                if p[2] <= 0.0 {
                    return Err(bad(format!(
                        "points_camera[{i}] has depth {} m: must be in front of the camera",
                        p[2]
                    )));
                }
            }
        }
        Ok(())
    }
}

impl Validate for Capture {
    fn validate(&self) -> Result<(), ProtocolError> {
        self.base_from_flange.to_isometry("T_base_flange")?;
        self.camera.validate()?;
        if let Some(f) = &self.features {
            f.validate()?;
        }
        if let Some(t) = self.controller_time_s {
            finite("controller_time_s", &[t])?;
        }
        if let Some(p) = &self.base_from_target {
            p.to_isometry("T_base_target")?;
        }
        match (&self.observation, &self.rejected) {
            (Some(o), None) => {
                o.camera_from_target
                    .to_isometry("observation.T_camera_target")?;
                if o.target_points.len() != o.pixels.len() || o.target_points.len() < 4 {
                    return Err(ProtocolError::BadField {
                        field: "observation".into(),
                        reason: format!(
                            "{} target points and {} pixels (need equal counts, at least 4)",
                            o.target_points.len(),
                            o.pixels.len()
                        ),
                    });
                }
                finite("observation.target_points", &o.target_points.concat())?;
                if let Some(c) = &o.target_centre {
                    finite("observation.target_centre", c)?;
                }
                if let Some(id) = &o.target
                    && (id.is_empty() || id.len() > 64 || id.chars().any(char::is_control))
                {
                    return Err(ProtocolError::BadField {
                        field: "observation.target".into(),
                        reason: format!("{id:?} is not a target id (1-64 printable characters)"),
                    });
                }
                finite("observation.pixels", &o.pixels.concat())?;
                finite("observation.residuals_px", &o.residuals_px)?;
                finite("observation.rms_px", &[o.rms_px])
            }
            (None, Some(_)) => Ok(()),
            _ => Err(ProtocolError::BadField {
                field: "observation".into(),
                reason: "a capture has exactly one of an observation and a rejection reason".into(),
            }),
        }
    }
}

/// The agent's current hand-eye.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HandEyeUpdate {
    #[serde(rename = "T_flange_camera")]
    pub flange_from_camera: Pose,
    pub covariance: Covariance6,
    pub captures_used: usize,
    pub reprojection_rms_px: f64,
}

impl Validate for HandEyeUpdate {
    fn validate(&self) -> Result<(), ProtocolError> {
        self.flange_from_camera.to_isometry("T_flange_camera")?;
        crate::validate_covariance("covariance", &self.covariance)?;
        finite("reprojection_rms_px", &[self.reprojection_rms_px])
    }
}

/// Where an agent is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AgentState {
    Starting,
    Capturing,
    /// Every capture it will take has been published.
    Finished,
    Failed,
}

/// An agent's status line.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AgentStatus {
    pub state: AgentState,
    pub good: usize,
    pub rejected: usize,
    /// Total number of captures published; with `Finished`, the receiver can
    /// tell whether it has them all.
    pub published: u64,
    /// Largest angle between rotation axes of the motions so far (deg).
    pub rotation_diversity_deg: f64,
    pub enough_data: bool,
    pub message: String,
}

impl Validate for AgentStatus {
    fn validate(&self) -> Result<(), ProtocolError> {
        finite("rotation_diversity_deg", &[self.rotation_diversity_deg])
    }
}

/// A drift alarm (`b2b/coordinator/alarm`): a cart's base has moved against
/// the result it was calibrated with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DriftAlarm {
    /// The robot whose base moved against the reference's.
    pub robot: String,
    /// The reference robot (the result's first), or `scene` when the robot
    /// was watched through the scene's depth features (no target in view).
    pub reference: String,
    /// How far the target moved in the reference base, seen through this
    /// robot's observations (m); watched through the scene, how far the
    /// scene's centre moved in the robot's base.
    pub shift_m: f64,
    /// How far it turned (rad).
    pub turn_rad: f64,
    /// The alarm came from the first observations against the result (the cart
    /// moved before the watch began, or the result is off), not from a change
    /// during the watch.
    pub against_result: bool,
    /// The test statistic that crossed its threshold, and the threshold.
    pub statistic: f64,
    pub threshold: f64,
    /// One line for an operator.
    pub message: String,
}

impl Validate for DriftAlarm {
    fn validate(&self) -> Result<(), ProtocolError> {
        finite(
            "drift alarm",
            &[self.shift_m, self.turn_rad, self.statistic, self.threshold],
        )
    }
}

impl Validate for crate::CalibrationResult {
    fn validate(&self) -> Result<(), ProtocolError> {
        crate::CalibrationResult::validate(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn capture() -> Capture {
        Capture {
            index: 3,
            controller_time_s: Some(1.7e9),
            image: Some("images/003.png".into()),
            base_from_flange: Pose::IDENTITY,
            camera: Intrinsics {
                width: 640,
                height: 480,
                fx: 600.0,
                fy: 600.0,
                cx: 320.0,
                cy: 240.0,
                dist: vec![0.0; 5],
                estimated: false,
            },
            observation: Some(BoardObservation {
                target_points: vec![[0.0; 3]; 4],
                pixels: vec![[1.0, 2.0]; 4],
                camera_from_target: Pose::IDENTITY,
                residuals_px: vec![0.1; 4],
                rms_px: 0.1,
                target_centre: Some([0.1, 0.05, 0.0]),
                target: None,
            }),
            rejected: None,
            base_from_target: None,
            features: None,
        }
    }

    #[test]
    fn valid_capture_round_trips() {
        let env = Envelope::new("robot1", 7, capture());
        let json = serde_json::to_string(&env).unwrap();
        let back: Envelope<Capture> = serde_json::from_str(&json).unwrap();
        assert_eq!(back, env);
        back.validate("robot1").unwrap();
    }

    #[test]
    fn wrong_version_robot_and_numbers_are_rejected() {
        let mut env = Envelope::new("robot1", 1, capture());
        env.schema = 99;
        assert!(
            env.validate("robot1")
                .unwrap_err()
                .to_string()
                .contains("version 99")
        );
        let env = Envelope::new("robot1", 1, capture());
        assert!(
            env.validate("robot2")
                .unwrap_err()
                .to_string()
                .contains("robot2")
        );
        let mut c = capture();
        if let Some(o) = c.observation.as_mut() {
            o.pixels[2][0] = f64::NAN;
        }
        assert!(Envelope::new("robot1", 1, c).validate("robot1").is_err());
        let mut c = capture();
        c.rejected = Some("blur".into());
        assert!(Envelope::new("robot1", 1, c).validate("robot1").is_err());
        // A further target is named by a printable id.
        for (id, ok) in [("side", true), ("", false), ("a\nb", false)] {
            let mut c = capture();
            if let Some(o) = c.observation.as_mut() {
                o.target = Some(id.into());
            }
            let checked = Envelope::new("robot1", 1, c).validate("robot1");
            assert_eq!(checked.is_ok(), ok, "{id:?}: {checked:?}");
            if let Err(e) = checked {
                assert!(e.to_string().contains("observation.target"), "{e}");
            }
        }
    }

    fn features() -> FeatureSet {
        FeatureSet {
            kind: "sift".into(),
            pixels: vec![[10.5, 20.25], [30.0, 40.0]],
            responses: vec![0.02, 0.03],
            points_camera: vec![Some([0.01, -0.02, 0.5]), None],
            descriptor_len: 3,
            descriptors: vec![0, 255, 7, 1, 2, 3],
        }
    }

    #[test]
    fn features_round_trip_as_base64_and_bad_ones_are_named() {
        let mut c = capture();
        c.features = Some(features());
        let env = Envelope::new("robot1", 2, c);
        let json = serde_json::to_string(&env).unwrap();
        assert!(json.contains(r#""descriptors":"AP8HAQID""#), "{json}");
        let back: Envelope<Capture> = serde_json::from_str(&json).unwrap();
        assert_eq!(back, env);
        back.validate("robot1").unwrap();
        let broken = json.replace("AP8HAQID", "AP8H!QID");
        let err = serde_json::from_str::<Envelope<Capture>>(&broken)
            .unwrap_err()
            .to_string();
        assert!(err.contains("not base64"), "{err}");
        let check = |f: FeatureSet, what: &str| {
            let mut c = capture();
            c.features = Some(f);
            let err = c.validate().unwrap_err().to_string();
            assert!(err.contains(what), "{err} lacks {what}");
        };
        let mut f = features();
        f.kind = "surf".into();
        check(f, "surf");
        let mut f = features();
        f.descriptors.pop();
        check(f, "need 6 bytes, got 5");
        let mut f = features();
        f.points_camera.pop();
        check(f, "1 points");
        let mut f = features();
        f.points_camera[0] = Some([0.0, 0.0, -0.1]);
        check(f, "points_camera[0]");
        let mut f = features();
        f.pixels[1][0] = f64::INFINITY;
        check(f, "features.pixels");
    }

    #[test]
    fn a_run_failure_is_one_bounded_printable_reason() {
        let ok = RunFailure {
            reason: "need two robots, heard from 1".into(),
        };
        Envelope::new(COORDINATOR, 1, ok.clone())
            .validate(COORDINATOR)
            .unwrap();
        for (reason, what) in [
            ("  ".to_owned(), "empty"),
            ("x".repeat(FAILURE_REASON_MAX + 1), "at most 4096"),
            ("red \u{1b}[31m".to_owned(), "control character"),
        ] {
            let e = RunFailure { reason }.validate().unwrap_err().to_string();
            assert!(e.contains(what) && e.contains("reason"), "{e}");
        }
    }

    #[test]
    fn robot_ids_must_be_key_safe() {
        assert!(validate_robot_id("robot-1_a").is_ok());
        for bad in ["", "a/b", "a*", "a b", "é"] {
            assert!(validate_robot_id(bad).is_err(), "{bad}");
            assert!(validate_cart_id(bad).is_err(), "{bad}");
        }
        // The coordinator signs its envelopes with its name; no cart takes it.
        assert!(validate_robot_id(COORDINATOR).is_ok());
        for taken in [COORDINATOR, SCENE] {
            assert!(validate_cart_id(taken).is_err(), "{taken}");
        }
        assert!(validate_cart_id("robot-1_a").is_ok());
    }
}
