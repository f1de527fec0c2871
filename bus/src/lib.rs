//! The bus between agents and the coordinator: a small trait, zenoh behind it,
//! and messages on and off the wire.
//!
//! The agent and coordinator loops talk to a [`Bus`]: put, subscribe, query,
//! answer queries, announce liveliness. [`ZenohBus`] is the one the services
//! run on, between processes. [`MemoryBus`] delivers within one process, so the
//! loops' logic can be tested without processes or sockets.
//!
//! zenoh sessions are peers. Without `--zenoh CONFIG` the coordinator listens on
//! [`DEFAULT_ENDPOINT`] (loopback) and agents connect to it, with multicast
//! scouting off, so nothing leaves the machine unless a configuration says so. A
//! configuration file is passed to zenoh as it is: peers or routers, TLS (zenoh
//! is built with its TLS transport) and access control are zenoh's own JSON5
//! keys. zenoh is built without `auth_usrpwd` and `auth_pubkey`: a
//! user/password section in a configuration authenticates nothing.
//!
//! A secured configuration (mutual TLS, every endpoint TLS: what `coordinator
//! pki init` writes) also signs every put and reply with the process's
//! certificate key and accepts only messages signed by the certificate of the
//! sender their key names ([`crate::signing`]); [`Received::signer`] says who.
//! On an open bus, the coordinator's journal is the defence: a capture that
//! contradicts one held is a conflict and used by neither version
//! (`b2b_services::store::Arrival`), and a status neither stalls nor completes a run
//! beyond the captures that arrived and the agent's history holds. On either,
//! a message of another run's session is dropped (`b2b_services::coordinator`).
//!
//! A port another process listens on is named as such ([`BusError::PortInUse`])
//! before zenoh tries it; a side that hears nobody can ask
//! [`Bus::unreached`] why.
//!
//! Payloads are JSON [`Envelope`]s, results included. [`encode`] refuses what
//! does not serialise instead of sending an empty payload; [`decode`] checks
//! every message before anyone trusts it and names the key and the problem when
//! it does not.

pub mod pki;
pub mod signing;

mod log;
pub use log::{ACCESS_CONTROL_TARGET, AccessRefusals, LogLimiter, warn_limited};

use std::path::Path;
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use b2b_protocol::messages::{COORDINATOR, Envelope, KEY_ROOT, Validate};

use crate::signing::Signing;
use serde::Serialize;
use serde::de::DeserializeOwned;
use zenoh::Wait;
use zenoh::query::{ConsolidationMode, QueryTarget};

/// Where the coordinator listens by default.
pub const DEFAULT_ENDPOINT: &str = "tcp/127.0.0.1:7447";

/// What went wrong on the bus. Each names the key or the configuration.
#[derive(Debug, thiserror::Error)]
pub enum BusError {
    #[error("{path}: not a usable zenoh configuration: {reason}")]
    Config { path: String, reason: String },
    #[error("cannot open the zenoh session: {reason}")]
    Open { reason: String },
    #[error("cannot publish on {key}: {reason}")]
    Publish { key: String, reason: String },
    #[error("cannot serialise the message for {key}: {reason}")]
    Encode { key: String, reason: String },
    #[error("cannot subscribe to {key}: {reason}")]
    Subscribe { key: String, reason: String },
    #[error("the subscription to {key} closed")]
    Closed { key: String },
    #[error("query {key}: {reason}")]
    Query { key: String, reason: String },
    #[error("cannot declare {key}: {reason}")]
    Declare { key: String, reason: String },
    /// Another process listens where this session must.
    #[error("port {port} already in use: is another {who} running?")]
    PortInUse { port: u16, who: &'static str },
}

/// One message as it arrived: its key and its bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Received {
    pub key: String,
    pub payload: Vec<u8>,
    /// On a secured bus, the common name of the certificate whose key signed
    /// the message (always the sender its key names: anything else is dropped,
    /// [`crate::signing`]); `None` on a bus without signatures.
    pub signer: Option<String>,
}

/// Keeps a declaration (a queryable, a liveliness token) alive; dropping it
/// undeclares.
pub type Declaration = Box<dyn std::any::Any + Send + Sync>;

/// What a queryable answers: the payloads to send at the time of the query.
pub type Replies = Arc<dyn Fn() -> Vec<Vec<u8>> + Send + Sync>;

/// The messages of one subscription, in arrival order.
pub trait Inbox: Send {
    /// The next message; `Ok(None)` when `timeout` passed without one.
    fn recv_timeout(&self, timeout: Duration) -> Result<Option<Received>, BusError>;
}

/// What the agent and the coordinator need of a bus.
pub trait Bus: Send + Sync {
    /// Publishes `payload` under `key`.
    fn put(&self, key: &str, payload: Vec<u8>) -> Result<(), BusError>;
    /// Receives everything published under the key expression (`*` one chunk,
    /// `**` any number).
    fn subscribe(&self, key_expr: &str) -> Result<Box<dyn Inbox>, BusError>;
    /// Asks every queryable matching `selector` and collects the replies that
    /// arrive within `timeout`.
    fn query(&self, selector: &str, timeout: Duration) -> Result<Vec<Received>, BusError>;
    /// Answers queries on `key` with `replies()`, each reply under `key`.
    fn serve(&self, key: &str, replies: Replies) -> Result<Declaration, BusError>;
    /// Declares a liveliness token on `key`, gone when dropped.
    fn announce(&self, key: &str) -> Result<Declaration, BusError>;
    /// Why nobody may be hearing this side (no peer connected, and what the
    /// endpoints it connects to answer), or `None` when it has a peer or
    /// cannot tell. Asked when no coordinator has been heard.
    fn unreached(&self) -> Option<String> {
        None
    }
}

/// Which side opens the session (decides the default endpoints).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    Agent,
    Coordinator,
}

/// The session configuration: the file when one is given, otherwise loopback
/// peers as described in the module docs.
pub fn config(file: Option<&Path>, role: Role) -> Result<zenoh::Config, BusError> {
    if let Some(path) = file {
        return zenoh::Config::from_file(path).map_err(|e| BusError::Config {
            path: path.display().to_string(),
            reason: e.to_string(),
        });
    }
    let mut c = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, key: &str, value: &str| {
        c.insert_json5(key, value).map_err(|e| BusError::Config {
            path: format!("(built-in) {key}"),
            reason: e.to_string(),
        })
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

/// Why a session with `config` (read from `file`, if any) would not be
/// authenticated, or `None` when it is: mutual TLS on, and every endpoint TLS.
pub fn unauthenticated(file: Option<&Path>, config: &zenoh::Config) -> Option<String> {
    if file.is_none() {
        return Some(
            "no --zenoh configuration, so loopback only; `coordinator pki init` writes secured ones"
                .into(),
        );
    }
    let get = |key: &str| config.get_json(key).unwrap_or_default();
    if get("transport/link/tls/enable_mtls") != "true" {
        return Some(
            "the configuration does not enable mutual TLS (transport/link/tls/enable_mtls)".into(),
        );
    }
    for side in ["listen", "connect"] {
        for e in endpoints(config, side) {
            if !e.starts_with("tls/") {
                return Some(format!("{side} endpoint {e} is not TLS"));
            }
        }
    }
    None
}

/// The `side` (`listen` or `connect`) endpoints of a configuration: a list,
/// or lists by mode (`{"peer": [...], "router": [...]}`).
fn endpoints(config: &zenoh::Config, side: &str) -> Vec<String> {
    let value: serde_json::Value = config
        .get_json(&format!("{side}/endpoints"))
        .ok()
        .and_then(|text| serde_json::from_str(&text).ok())
        .unwrap_or_default();
    let lists: Vec<&serde_json::Value> = match &value {
        serde_json::Value::Object(by_mode) => by_mode.values().collect(),
        other => vec![other],
    };
    lists
        .into_iter()
        .filter_map(serde_json::Value::as_array)
        .flatten()
        .filter_map(serde_json::Value::as_str)
        .map(str::to_owned)
        .collect()
}

/// The socket address of a `tcp/` or `tls/` endpoint with a fixed port
/// (`tcp/127.0.0.1:7447`, `tls/[::1]:7447#...`); `None` for other
/// transports, port 0 and names that do not resolve.
pub fn endpoint_addr(endpoint: &str) -> Option<std::net::SocketAddr> {
    use std::net::ToSocketAddrs;
    let (proto, rest) = endpoint.split_once('/')?;
    if proto != "tcp" && proto != "tls" {
        return None;
    }
    let address = rest.split(['#', '?']).next()?;
    let addr = address.to_socket_addrs().ok()?.next()?;
    (addr.port() != 0).then_some(addr)
}

/// Refuses to open a session whose fixed TCP/TLS listening port another
/// process holds, saying so in one line (zenoh's own error names its source
/// files, not the port).
fn check_listen_ports(config: &zenoh::Config, role: Role) -> Result<(), BusError> {
    for addr in endpoints(config, "listen")
        .iter()
        .filter_map(|e| endpoint_addr(e))
    {
        if let Err(e) = std::net::TcpListener::bind(addr)
            && e.kind() == std::io::ErrorKind::AddrInUse
        {
            return Err(port_in_use(addr.port(), role));
        }
    }
    Ok(())
}

fn port_in_use(port: u16, role: Role) -> BusError {
    BusError::PortInUse {
        port,
        who: match role {
            Role::Coordinator => "coordinator",
            Role::Agent => "agent",
        },
    }
}

/// Opens a zenoh session.
pub fn open(config: zenoh::Config) -> Result<zenoh::Session, BusError> {
    zenoh::open(config).wait().map_err(|e| BusError::Open {
        reason: e.to_string(),
    })
}

/// The bus between processes: one zenoh session; on a secured configuration,
/// every message signed and every message checked ([`crate::signing`]).
#[derive(Debug, Clone)]
pub struct ZenohBus {
    session: zenoh::Session,
    signing: Option<Arc<Signing>>,
    /// The endpoints it connects to (for [`Bus::unreached`]).
    connect: Vec<String>,
}

impl ZenohBus {
    /// Opens a session with [`config`]; says so on stderr when the bus it
    /// joins is not authenticated.
    pub fn open(file: Option<&Path>, role: Role) -> Result<ZenohBus, BusError> {
        let config = config(file, role)?;
        let signing = match (unauthenticated(file, &config), file) {
            (None, Some(path)) => Some(Arc::new(Signing::from_config(&config, path).map_err(
                |e| BusError::Config {
                    path: path.display().to_string(),
                    reason: e.to_string(),
                },
            )?)),
            (Some(why), _) => {
                tracing::warn!("the bus is not authenticated: {why}");
                None
            }
            (None, None) => None,
        };
        check_listen_ports(&config, role)?;
        let connect: Vec<String> = endpoints(&config, "connect");
        let listen_port = endpoints(&config, "listen")
            .iter()
            .find_map(|e| endpoint_addr(e))
            .map_or(0, |a| a.port());
        let session = match open(config) {
            // Taken between the check and the bind.
            Err(BusError::Open { reason }) if reason.contains("Address already in use") => {
                return Err(port_in_use(listen_port, role));
            }
            other => other?,
        };
        Ok(ZenohBus {
            session,
            signing,
            connect,
        })
    }

    /// Whether this session signs and checks every message.
    pub fn signs(&self) -> bool {
        self.signing.is_some()
    }

    /// The session itself, for what the trait does not cover.
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }
}

struct ZenohInbox {
    key: String,
    subscriber:
        zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    signing: Option<Arc<Signing>>,
}

/// A sample as received: checked against its signature on a secured bus, where
/// one that fails is logged (rate-limited per key) and dropped (`None`).
fn received(sample: &zenoh::sample::Sample, signing: Option<&Signing>) -> Option<Received> {
    let key = sample.key_expr().as_str().to_owned();
    let payload = sample.payload().to_bytes().into_owned();
    let signer = match signing {
        None => None,
        Some(s) => {
            let attachment = sample.attachment().map(|a| a.to_bytes());
            match s.verifier.verify(&key, &payload, attachment.as_deref()) {
                Ok(signer) => Some(signer),
                Err(e) => {
                    crate::warn_limited(&key, &format!("{key}: rejected: {e}"));
                    return None;
                }
            }
        }
    };
    Some(Received {
        key,
        payload,
        signer,
    })
}

impl Inbox for ZenohInbox {
    fn recv_timeout(&self, timeout: Duration) -> Result<Option<Received>, BusError> {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match self.subscriber.recv_timeout(left) {
                Ok(Some(sample)) => {
                    if let Some(r) = received(&sample, self.signing.as_deref()) {
                        return Ok(Some(r));
                    }
                    // Dropped (logged): wait on for the rest of the timeout.
                }
                Ok(None) => return Ok(None),
                Err(_) => {
                    return Err(BusError::Closed {
                        key: self.key.clone(),
                    });
                }
            }
        }
    }
}

/// The signature attachment for `payload` under `key`, on a secured bus.
fn attachment(
    signing: Option<&Signing>,
    key: &str,
    payload: &[u8],
) -> Result<Option<Vec<u8>>, BusError> {
    signing
        .map(|s| s.identity.sign(key, payload))
        .transpose()
        .map_err(|e| BusError::Publish {
            key: key.to_owned(),
            reason: e.to_string(),
        })
}

impl Bus for ZenohBus {
    fn put(&self, key: &str, payload: Vec<u8>) -> Result<(), BusError> {
        let signature = attachment(self.signing.as_deref(), key, &payload)?;
        self.session
            .put(key, payload)
            .attachment(signature)
            .wait()
            .map_err(|e| BusError::Publish {
                key: key.to_owned(),
                reason: e.to_string(),
            })
    }

    fn subscribe(&self, key_expr: &str) -> Result<Box<dyn Inbox>, BusError> {
        let subscriber = self
            .session
            .declare_subscriber(key_expr.to_owned())
            .wait()
            .map_err(|e| BusError::Subscribe {
                key: key_expr.to_owned(),
                reason: e.to_string(),
            })?;
        Ok(Box::new(ZenohInbox {
            key: key_expr.to_owned(),
            subscriber,
            signing: self.signing.clone(),
        }))
    }

    fn query(&self, selector: &str, timeout: Duration) -> Result<Vec<Received>, BusError> {
        let replies = self
            .session
            .get(selector)
            .target(QueryTarget::All)
            .consolidation(ConsolidationMode::None)
            .timeout(timeout)
            .wait()
            .map_err(|e| BusError::Query {
                key: selector.to_owned(),
                reason: e.to_string(),
            })?;
        let mut out = Vec::new();
        while let Ok(reply) = replies.recv() {
            if let Ok(sample) = reply.result()
                && let Some(r) = received(sample, self.signing.as_deref())
            {
                out.push(r);
            }
        }
        Ok(out)
    }

    fn serve(&self, key: &str, replies: Replies) -> Result<Declaration, BusError> {
        let reply_key = key.to_owned();
        let signing = self.signing.clone();
        let queryable = self
            .session
            .declare_queryable(key.to_owned())
            .callback(move |query| {
                for bytes in replies() {
                    let sent =
                        attachment(signing.as_deref(), &reply_key, &bytes).and_then(|signature| {
                            query
                                .reply(&reply_key, bytes)
                                .attachment(signature)
                                .wait()
                                .map_err(|e| BusError::Publish {
                                    key: reply_key.clone(),
                                    reason: e.to_string(),
                                })
                        });
                    if let Err(e) = sent {
                        tracing::warn!("reply on {reply_key} failed: {e}");
                    }
                }
            })
            .wait()
            .map_err(|e| BusError::Declare {
                key: key.to_owned(),
                reason: e.to_string(),
            })?;
        Ok(Box::new(queryable))
    }

    fn announce(&self, key: &str) -> Result<Declaration, BusError> {
        let token = self
            .session
            .liveliness()
            .declare_token(key.to_owned())
            .wait()
            .map_err(|e| BusError::Declare {
                key: key.to_owned(),
                reason: e.to_string(),
            })?;
        Ok(Box::new(token))
    }

    fn unreached(&self) -> Option<String> {
        let info = self.session.info();
        if info.peers_zid().wait().next().is_some() || info.routers_zid().wait().next().is_some() {
            return None;
        }
        if self.connect.is_empty() {
            return Some("this session has no peer and connects to no endpoint".into());
        }
        let each: Vec<String> = self
            .connect
            .iter()
            .map(|e| match endpoint_addr(e) {
                None => format!("{e}: no session"),
                Some(addr) => {
                    match std::net::TcpStream::connect_timeout(&addr, Duration::from_secs(1)) {
                        Ok(_) => format!(
                            "{e} accepts connections but no session comes of them: another program \
                         holds the coordinator's port (is another coordinator running?), or it \
                         refuses this side's TLS certificate"
                        ),
                        Err(why) => {
                            format!("{e} cannot be reached ({why}): is the coordinator running?")
                        }
                    }
                }
            })
            .collect();
        Some(format!("no peer connected; {}", each.join("; ")))
    }
}

/// Whether `key` matches the key expression `expr` (`*`: one chunk; `**`: any
/// number of chunks, none included).
pub fn key_matches(expr: &str, key: &str) -> bool {
    fn go(e: &[&str], k: &[&str]) -> bool {
        match (e.first(), k.first()) {
            (None, None) => true,
            (Some(&"**"), _) => go(&e[1..], k) || (!k.is_empty() && go(e, &k[1..])),
            (Some(&"*"), Some(_)) => go(&e[1..], &k[1..]),
            (Some(a), Some(b)) if a == b => go(&e[1..], &k[1..]),
            _ => false,
        }
    }
    let e: Vec<&str> = expr.split('/').collect();
    let k: Vec<&str> = key.split('/').collect();
    go(&e, &k)
}

type Subscribers = Vec<(String, mpsc::Sender<Received>)>;

/// A bus within one process: what is put reaches every matching subscription
/// of the same `MemoryBus` (clones share it). For tests of the loops; the
/// services themselves run on [`ZenohBus`].
#[derive(Clone, Default)]
pub struct MemoryBus {
    subscribers: Arc<Mutex<Subscribers>>,
    queryables: Arc<Mutex<Vec<(String, Replies)>>>,
}

impl std::fmt::Debug for MemoryBus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MemoryBus").finish_non_exhaustive()
    }
}

impl MemoryBus {
    pub fn new() -> MemoryBus {
        MemoryBus::default()
    }
}

struct MemoryInbox {
    key: String,
    receiver: mpsc::Receiver<Received>,
}

impl Inbox for MemoryInbox {
    fn recv_timeout(&self, timeout: Duration) -> Result<Option<Received>, BusError> {
        match self.receiver.recv_timeout(timeout) {
            Ok(m) => Ok(Some(m)),
            Err(mpsc::RecvTimeoutError::Timeout) => Ok(None),
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(BusError::Closed {
                key: self.key.clone(),
            }),
        }
    }
}

fn poisoned(key: &str) -> BusError {
    BusError::Publish {
        key: key.to_owned(),
        reason: "the in-process bus lock is poisoned".into(),
    }
}

impl Bus for MemoryBus {
    fn put(&self, key: &str, payload: Vec<u8>) -> Result<(), BusError> {
        let mut subs = self.subscribers.lock().map_err(|_| poisoned(key))?;
        // A dropped subscription is forgotten.
        subs.retain(|(expr, tx)| {
            !key_matches(expr, key)
                || tx
                    .send(Received {
                        key: key.to_owned(),
                        payload: payload.clone(),
                        signer: None,
                    })
                    .is_ok()
        });
        Ok(())
    }

    fn subscribe(&self, key_expr: &str) -> Result<Box<dyn Inbox>, BusError> {
        let (tx, rx) = mpsc::channel();
        self.subscribers
            .lock()
            .map_err(|_| poisoned(key_expr))?
            .push((key_expr.to_owned(), tx));
        Ok(Box::new(MemoryInbox {
            key: key_expr.to_owned(),
            receiver: rx,
        }))
    }

    fn query(&self, selector: &str, _timeout: Duration) -> Result<Vec<Received>, BusError> {
        let served: Vec<(String, Replies)> = self
            .queryables
            .lock()
            .map_err(|_| poisoned(selector))?
            .iter()
            .filter(|(key, _)| key_matches(selector, key))
            .map(|(k, r)| (k.clone(), Arc::clone(r)))
            .collect();
        Ok(served
            .into_iter()
            .flat_map(|(key, replies)| {
                replies().into_iter().map(move |payload| Received {
                    key: key.clone(),
                    payload,
                    signer: None,
                })
            })
            .collect())
    }

    fn serve(&self, key: &str, replies: Replies) -> Result<Declaration, BusError> {
        self.queryables
            .lock()
            .map_err(|_| poisoned(key))?
            .push((key.to_owned(), replies));
        // Queryables of the in-process bus last as long as the bus.
        Ok(Box::new(()))
    }

    fn announce(&self, _key: &str) -> Result<Declaration, BusError> {
        Ok(Box::new(()))
    }
}

/// Serialises a message for `key`.
pub fn encode<T: Serialize>(key: &str, envelope: &Envelope<T>) -> Result<Vec<u8>, BusError> {
    serde_json::to_vec(envelope).map_err(|e| BusError::Encode {
        key: key.to_owned(),
        reason: e.to_string(),
    })
}

/// Serialises and publishes a message.
pub fn publish<T: Serialize>(
    bus: &dyn Bus,
    key: &str,
    envelope: &Envelope<T>,
) -> Result<(), BusError> {
    bus.put(key, encode(key, envelope)?)
}

/// The robot and topic of an agent key `b2b/agent/{robot}/{topic}`.
pub fn parse_agent_key(key: &str) -> Option<(&str, &str)> {
    let rest = key.strip_prefix(KEY_ROOT)?.strip_prefix("/agent/")?;
    let (robot, topic) = rest.split_once('/')?;
    Some((robot, topic))
}

/// Who may send under `key`: the robot of an agent key, [`COORDINATOR`] under
/// `b2b/coordinator/`.
pub fn sender_of(key: &str) -> Option<&str> {
    if let Some((robot, _)) = parse_agent_key(key) {
        return Some(robot);
    }
    key.strip_prefix(KEY_ROOT)?
        .strip_prefix("/coordinator/")
        .map(|_| COORDINATOR)
}

/// Parses and validates a message received under `key`: the schema version,
/// that its sender is the one the key names, and its numbers.
pub fn decode<T: DeserializeOwned + Validate>(
    key: &str,
    bytes: &[u8],
) -> Result<Envelope<T>, String> {
    let sender = sender_of(key).ok_or_else(|| format!("{key}: not a key of the service"))?;
    let envelope: Envelope<T> =
        serde_json::from_slice(bytes).map_err(|e| format!("{key}: not a valid message: {e}"))?;
    envelope
        .validate(sender)
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
        assert_eq!(sender_of("b2b/coordinator/result"), Some(COORDINATOR));
        assert_eq!(sender_of("b2b/elsewhere/result"), None);
    }

    fn status() -> AgentStatus {
        AgentStatus {
            state: AgentState::Capturing,
            good: 1,
            rejected: 0,
            published: 1,
            rotation_diversity_deg: 10.0,
            enough_data: false,
            message: String::new(),
        }
    }

    #[test]
    fn decode_rejects_garbage_and_impostors() {
        let key = "b2b/agent/robot1/status";
        let bytes = encode(key, &Envelope::new("robot1", 1, status())).unwrap();
        assert!(decode::<AgentStatus>(key, &bytes).is_ok());
        let err = decode::<AgentStatus>("b2b/agent/robot2/status", &bytes).unwrap_err();
        assert!(err.contains("robot2"), "{err}");
        let err = decode::<AgentStatus>(key, b"{").unwrap_err();
        assert!(err.contains("not a valid message"), "{err}");
        // An agent cannot speak for the coordinator.
        let err = decode::<AgentStatus>("b2b/coordinator/result", &bytes).unwrap_err();
        assert!(err.contains("coordinator"), "{err}");
    }

    #[test]
    fn encode_refuses_what_does_not_serialise() {
        // JSON object keys must be strings: a map keyed by pairs does not serialise.
        let mut body = std::collections::BTreeMap::new();
        body.insert((1, 2), 3);
        let envelope = Envelope {
            schema: 1,
            robot: "robot1".into(),
            seq: 1,
            session: None,
            body,
        };
        let err = encode("b2b/agent/robot1/x", &envelope).unwrap_err();
        assert!(
            matches!(&err, BusError::Encode { key, .. } if key == "b2b/agent/robot1/x"),
            "{err}"
        );
    }

    #[test]
    fn key_expressions_match_like_zenoh() {
        assert!(key_matches("b2b/agent/**", "b2b/agent/robot1/capture"));
        assert!(key_matches(
            "b2b/agent/*/history",
            "b2b/agent/robot1/history"
        ));
        assert!(!key_matches(
            "b2b/agent/*/history",
            "b2b/agent/robot1/capture"
        ));
        assert!(!key_matches("b2b/agent/*", "b2b/agent/robot1/capture"));
        assert!(key_matches("b2b/**", "b2b"));
        assert!(key_matches(
            "b2b/coordinator/result",
            "b2b/coordinator/result"
        ));
        assert!(!key_matches(
            "b2b/coordinator/result",
            "b2b/coordinator/results"
        ));
    }

    #[test]
    fn the_memory_bus_delivers_to_matching_subscriptions_and_serves_queries() {
        let bus = MemoryBus::new();
        let all = bus.subscribe("b2b/agent/**").unwrap();
        let other = bus.subscribe("b2b/coordinator/*").unwrap();
        bus.put("b2b/agent/robot1/status", b"a".to_vec()).unwrap();
        let got = all
            .recv_timeout(Duration::from_millis(10))
            .unwrap()
            .unwrap();
        assert_eq!(got.key, "b2b/agent/robot1/status");
        assert_eq!(got.payload, b"a");
        assert_eq!(other.recv_timeout(Duration::from_millis(10)).unwrap(), None);
        let _q = bus
            .serve(
                "b2b/agent/robot1/history",
                Arc::new(|| vec![b"x".to_vec(), b"y".to_vec()]),
            )
            .unwrap();
        let replies = bus
            .query("b2b/agent/*/history", Duration::from_millis(10))
            .unwrap();
        assert_eq!(replies.len(), 2);
        assert!(
            bus.query("b2b/agent/robot2/history", Duration::from_millis(10))
                .unwrap()
                .is_empty()
        );
    }

    #[test]
    fn endpoints_resolve_to_fixed_tcp_ports_only() {
        let a = endpoint_addr("tcp/127.0.0.1:7447").unwrap();
        assert_eq!(a.port(), 7447);
        assert_eq!(
            endpoint_addr("tls/[::1]:7448#iface=lo").unwrap().port(),
            7448
        );
        for none in ["tcp/127.0.0.1:0", "udp/127.0.0.1:7447", "tcp/nohost", "x"] {
            assert_eq!(endpoint_addr(none), None, "{none}");
        }
    }

    /// A process listening on the port: one line naming the port and the
    /// likely cause, no zenoh source path; a free port opens.
    #[test]
    fn a_listening_port_taken_by_another_process_is_named() {
        let squatter = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = squatter.local_addr().unwrap().port();
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("coordinator.json5");
        std::fs::write(
            &f,
            format!(
                r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#
            ),
        )
        .unwrap();
        let e = ZenohBus::open(Some(&f), Role::Coordinator)
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            format!("port {port} already in use: is another coordinator running?")
        );
        drop(squatter);
        let bus = ZenohBus::open(Some(&f), Role::Coordinator).unwrap();
        // Nobody connects to it, and it connects to nobody: it says so.
        let why = bus.unreached().unwrap();
        assert!(why.contains("connects to no endpoint"), "{why}");
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
