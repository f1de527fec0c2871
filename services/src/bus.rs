//! The zenoh side of the services: sessions, and messages on and off the wire.
//!
//! Sessions are zenoh peers. Without `--zenoh CONFIG` the coordinator listens on
//! [`DEFAULT_ENDPOINT`] (loopback) and agents connect to it, with multicast
//! scouting off, so nothing leaves the machine unless a configuration says so. A
//! configuration file is passed to zenoh as it is: peers or routers, TLS, access
//! control, user/password authentication are all zenoh's own JSON5 keys.
//!
//! Payloads are JSON [`Envelope`]s. [`decode`] checks every message before anyone
//! trusts it and names the key and the problem when it does not.

use std::path::Path;

use anyhow::Context;
use b2b_protocol::messages::{Envelope, KEY_ROOT, Validate};
use serde::Serialize;
use serde::de::DeserializeOwned;
use zenoh::Wait;

/// Where the coordinator listens by default.
pub const DEFAULT_ENDPOINT: &str = "tcp/127.0.0.1:7447";

/// Which side opens the session (decides the default endpoints).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    Agent,
    Coordinator,
}

/// The session configuration: the file when one is given, otherwise loopback
/// peers as described in the module docs.
pub fn config(file: Option<&Path>, role: Role) -> anyhow::Result<zenoh::Config> {
    if let Some(path) = file {
        return zenoh::Config::from_file(path).map_err(|e| {
            anyhow::anyhow!("{}: not a usable zenoh configuration: {e}", path.display())
        });
    }
    let mut c = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, key: &str, value: &str| {
        c.insert_json5(key, value)
            .map_err(|e| anyhow::anyhow!("zenoh config {key}: {e}"))
    };
    set(&mut c, "mode", r#""peer""#)?;
    set(&mut c, "scouting/multicast/enabled", "false")?;
    match role {
        Role::Coordinator => set(
            &mut c,
            "listen/endpoints",
            &format!(r#"["{DEFAULT_ENDPOINT}"]"#),
        )?,
        Role::Agent => {
            set(&mut c, "listen/endpoints", r#"["tcp/127.0.0.1:0"]"#)?;
            set(
                &mut c,
                "connect/endpoints",
                &format!(r#"["{DEFAULT_ENDPOINT}"]"#),
            )?;
        }
    }
    Ok(c)
}

/// Opens a session.
pub fn open(config: zenoh::Config) -> anyhow::Result<zenoh::Session> {
    zenoh::open(config)
        .wait()
        .map_err(|e| anyhow::anyhow!("cannot open the zenoh session: {e}"))
        .context("zenoh")
}

/// Serialises a message.
pub fn encode<T: Serialize>(envelope: &Envelope<T>) -> Vec<u8> {
    // A message of plain numbers and strings always serialises.
    serde_json::to_vec(envelope).unwrap_or_default()
}

/// The robot and topic of an agent key `b2b/agent/{robot}/{topic}`.
pub fn parse_agent_key(key: &str) -> Option<(&str, &str)> {
    let rest = key.strip_prefix(KEY_ROOT)?.strip_prefix("/agent/")?;
    let (robot, topic) = rest.split_once('/')?;
    Some((robot, topic))
}

/// Parses and validates a message received under `key`.
pub fn decode<T: DeserializeOwned + Validate>(
    key: &str,
    bytes: &[u8],
) -> Result<Envelope<T>, String> {
    let (robot, _) = parse_agent_key(key).ok_or_else(|| format!("{key}: not an agent key"))?;
    let envelope: Envelope<T> =
        serde_json::from_slice(bytes).map_err(|e| format!("{key}: not a valid message: {e}"))?;
    envelope
        .validate(robot)
        .map_err(|e| format!("{key}: rejected: {e}"))?;
    Ok(envelope)
}

#[cfg(test)]
mod tests {
    use super::*;
    use b2b_protocol::messages::{AgentState, AgentStatus};

    #[test]
    fn agent_keys_parse() {
        assert_eq!(
            parse_agent_key("b2b/agent/robot1/capture"),
            Some(("robot1", "capture"))
        );
        assert_eq!(parse_agent_key("other/agent/robot1/capture"), None);
        assert_eq!(parse_agent_key("b2b/agent/robot1"), None);
    }

    #[test]
    fn decode_rejects_garbage_and_impostors() {
        let status = AgentStatus {
            state: AgentState::Capturing,
            good: 1,
            rejected: 0,
            published: 1,
            rotation_diversity_deg: 10.0,
            enough_data: false,
            message: String::new(),
        };
        let bytes = encode(&Envelope::new("robot1", 1, status));
        assert!(decode::<AgentStatus>("b2b/agent/robot1/status", &bytes).is_ok());
        let err = decode::<AgentStatus>("b2b/agent/robot2/status", &bytes).unwrap_err();
        assert!(err.contains("robot2"), "{err}");
        let err = decode::<AgentStatus>("b2b/agent/robot1/status", b"{").unwrap_err();
        assert!(err.contains("not a valid message"), "{err}");
    }

    #[test]
    fn config_file_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("zenoh.json5");
        std::fs::write(&f, "{ mode: ").unwrap();
        let err = config(Some(&f), Role::Agent).unwrap_err().to_string();
        assert!(err.contains("zenoh.json5"), "{err}");
    }
}
