//! The platform's own certificate authority and the secured bus:
//! `coordinator pki init --dir DIR --robots robot1,robot2`, then `pki add` for
//! a further cart and `pki revoke` to replace a lost or stolen key.
//!
//! One authority (`ca.pem`, `ca.key`) issues a certificate to the coordinator
//! and to each cart; a certificate's common name is its holder's id (the robot
//! id, or [`COORDINATOR`]). Keys are written readable by their owner only.
//! Beside them go ready zenoh configurations, `coordinator.json5` and
//! `<robot>.json5`:
//!
//! - **Mutual TLS on every link.** The coordinator listens on one TLS endpoint
//!   and nothing else; a cart connects to it and listens on nothing. Both sides
//!   present their certificate and accept only certificates of this authority
//!   (`enable_mtls`), so a peer without one cannot connect. A cart also checks
//!   that the coordinator's certificate names the host it connected to (the
//!   coordinator's certificate names `localhost`, `127.0.0.1` and the host of
//!   `--connect`).
//! - **Access control, default deny.** Each process filters what it receives
//!   by the certificate name of the link it came on: the coordinator takes
//!   puts and replies under `b2b/agent/<id>/**` only from the certificate named
//!   `<id>`, and a cart takes puts and replies under `b2b/coordinator/**` only
//!   from the certificate named `coordinator`. A certificate of this authority
//!   whose name is not in a configuration (a cart removed from the platform)
//!   can say nothing to it.
//!
//! Behind that, every message is signed with its sender's certificate key, and
//! a receiver takes it only if the signing certificate is this authority's and
//! names the sender its key names ([`crate::signing`]); the coordinator also
//! checks that each envelope names the robot of its key
//! ([`b2b_protocol::messages::Envelope::validate`]). So a wrong access-control
//! rule does not let one cart speak for another.

use std::io::Write;
use std::path::{Path, PathBuf};

use b2b_protocol::ProtocolError;
use b2b_protocol::messages::{COORDINATOR, KEY_ROOT, validate_cart_id};
use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa,
    Issuer, KeyPair, KeyUsagePurpose, SanType,
};
use serde_json::{Value, json};

use crate::signing::SigningError;

/// The authority's certificate, which every process trusts.
pub const CA_CERT: &str = "ca.pem";
/// The authority's key: needed only to issue certificates; keep it off the carts.
pub const CA_KEY: &str = "ca.key";
/// The common name of the authority's certificate.
pub const CA_NAME: &str = "b2b calibration platform authority";
/// The coordinator's TLS endpoint when `--listen` is not given.
pub const DEFAULT_TLS_ENDPOINT: &str = "tls/127.0.0.1:7447";

/// What went wrong issuing or revoking: the flag, file or holder, and the
/// cause as the source.
#[derive(Debug, thiserror::Error)]
pub enum PkiError {
    #[error("{flag} {endpoint}: the secured bus takes a TLS endpoint, tls/HOST:PORT")]
    NotTls {
        flag: &'static str,
        endpoint: String,
    },
    #[error("--connect {endpoint}: expected tls/HOST:PORT")]
    NoHost { endpoint: String },
    #[error("--connect {endpoint}: carts cannot connect to {host}; give the coordinator's address")]
    Unreachable { endpoint: String, host: String },
    #[error("--robots: name at least one robot")]
    NoRobots,
    #[error("{flag} '{id}'")]
    RobotId {
        flag: &'static str,
        id: String,
        #[source]
        source: ProtocolError,
    },
    #[error("--robots: robot id '{id}' is given twice")]
    GivenTwice { id: String },
    #[error(
        "{} already holds an authority ({CA_KEY}); its certificates may be in use. \
         Choose another folder, or remove this one to start the platform's trust over",
        dir.display()
    )]
    AuthorityExists { dir: PathBuf },
    #[error(
        "'{robot}' already has a certificate from this authority; to replace it, \
         `coordinator pki revoke --dir {} --robot {robot}`",
        dir.display()
    )]
    AlreadyIssued { robot: String, dir: PathBuf },
    #[error(
        "--robot '{holder}': no certificate of that name in {} (it has {COORDINATOR}, {})",
        dir.display(),
        robots.join(", ")
    )]
    NoSuchHolder {
        holder: String,
        dir: PathBuf,
        robots: Vec<String>,
    },
    #[error("cannot {what} {}", path.display())]
    Io {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: not a private key", path.display())]
    NotAKey {
        path: PathBuf,
        #[source]
        source: rcgen::Error,
    },
    #[error("{}: not a configuration `pki init` wrote", path.display())]
    NotAConfiguration {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("{}: no {what}", path.display())]
    ConfigurationLacks { path: PathBuf, what: &'static str },
    #[error("{what}")]
    Certificate {
        what: String,
        #[source]
        source: rcgen::Error,
    },
    #[error("the certificate to revoke")]
    Revoking {
        #[source]
        source: SigningError,
    },
}

fn io<'a>(what: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> PkiError + 'a {
    move |source| PkiError::Io {
        what,
        path: path.to_owned(),
        source,
    }
}

fn certificate(what: impl Into<String>) -> impl FnOnce(rcgen::Error) -> PkiError {
    let what = what.into();
    move |source| PkiError::Certificate { what, source }
}

/// A configuration as pretty JSON (of values built here: it cannot fail).
fn pretty(config: &Value) -> String {
    serde_json::to_string_pretty(config).unwrap_or_else(|_| config.to_string())
}

/// What `pki init` wrote.
#[derive(Debug, Clone)]
pub struct Issued {
    /// Every file written, in order.
    pub files: Vec<PathBuf>,
    /// The zenoh configuration of each holder (the coordinator first).
    pub configs: Vec<(String, PathBuf)>,
}

/// Where the coordinator listens and where carts connect.
#[derive(Debug, Clone)]
pub struct Endpoints {
    /// The coordinator's listening endpoint (`tls/HOST:PORT`).
    pub listen: String,
    /// What carts connect to; `listen` when the coordinator is reached at the
    /// address it binds (not behind `0.0.0.0`).
    pub connect: String,
    /// The host of `connect`, which the coordinator's certificate names.
    pub connect_host: String,
}

impl Endpoints {
    /// Listens and connects on `endpoint` (a `tls/` locator).
    pub fn at(endpoint: &str) -> Result<Endpoints, PkiError> {
        Endpoints::new(endpoint, endpoint)
    }

    pub fn new(listen: &str, connect: &str) -> Result<Endpoints, PkiError> {
        for (flag, e) in [("--listen", listen), ("--connect", connect)] {
            if !(e.starts_with("tls/") && e.len() > 4) {
                return Err(PkiError::NotTls {
                    flag,
                    endpoint: e.to_owned(),
                });
            }
        }
        let host = connect["tls/".len()..]
            .rsplit_once(':')
            .map(|(host, _)| host.trim_start_matches('[').trim_end_matches(']'))
            .filter(|h| !h.is_empty())
            .ok_or_else(|| PkiError::NoHost {
                endpoint: connect.to_owned(),
            })?;
        if host == "0.0.0.0" || host == "::" {
            return Err(PkiError::Unreachable {
                endpoint: connect.to_owned(),
                host: host.to_owned(),
            });
        }
        Ok(Endpoints {
            listen: listen.to_owned(),
            connect: connect.to_owned(),
            connect_host: host.to_owned(),
        })
    }
}

/// Creates the authority and every holder's key, certificate and zenoh
/// configuration in `dir` (created if needed). Refuses a folder that already
/// holds an authority: its certificates are in use.
pub fn init(dir: &Path, robots: &[String], endpoints: &Endpoints) -> Result<Issued, PkiError> {
    if robots.is_empty() {
        return Err(PkiError::NoRobots);
    }
    for (i, r) in robots.iter().enumerate() {
        validate_cart_id(r).map_err(|source| PkiError::RobotId {
            flag: "--robots: robot id",
            id: r.clone(),
            source,
        })?;
        if robots[..i].contains(r) {
            return Err(PkiError::GivenTwice { id: r.clone() });
        }
    }
    create_folder(dir)?;
    let dir = std::path::absolute(dir).unwrap_or_else(|_| dir.to_owned());
    if dir.join(CA_KEY).exists() {
        return Err(PkiError::AuthorityExists { dir });
    }
    let mut files = Vec::new();

    let ca_key = KeyPair::generate().map_err(certificate("generating the authority's key"))?;
    let ca_cert = ca_params()?
        .self_signed(&ca_key)
        .map_err(certificate("signing the authority's certificate"))?;
    files.push(write_public(&dir.join(CA_CERT), &ca_cert.pem())?);
    files.push(write_secret(&dir.join(CA_KEY), &ca_key.serialize_pem())?);
    let issuer = Issuer::new(ca_params()?, ca_key);

    let mut configs = Vec::new();
    for holder in std::iter::once(COORDINATOR).chain(robots.iter().map(String::as_str)) {
        configs.push(issue(&dir, &issuer, holder, robots, endpoints, &mut files)?);
    }
    Ok(Issued { files, configs })
}

/// What `add` and `revoke` need of an authority `init` made: the folder,
/// the authority's key, the robots the coordinator's configuration names, and
/// the endpoints `init` wrote.
struct Authority {
    dir: PathBuf,
    ca_key: KeyPair,
    robots: Vec<String>,
    endpoints: Endpoints,
}

fn open_authority(dir: &Path) -> Result<Authority, PkiError> {
    let dir = std::path::absolute(dir).unwrap_or_else(|_| dir.to_owned());
    let key_file = dir.join(CA_KEY);
    let ca_key =
        std::fs::read_to_string(&key_file).map_err(io("read the authority's key", &key_file))?;
    let ca_key = KeyPair::from_pem(&ca_key).map_err(|source| PkiError::NotAKey {
        path: key_file.clone(),
        source,
    })?;
    let read_config = |file: &Path| -> Result<Value, PkiError> {
        let text = std::fs::read_to_string(file).map_err(io("read", file))?;
        serde_json::from_str(&text).map_err(|source| PkiError::NotAConfiguration {
            path: file.to_owned(),
            source,
        })
    };
    let lacks = |path: &Path, what: &'static str| PkiError::ConfigurationLacks {
        path: path.to_owned(),
        what,
    };
    let coordinator_file = dir.join(format!("{COORDINATOR}.json5"));
    let config = read_config(&coordinator_file)?;
    let robots: Vec<String> = config["access_control"]["subjects"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|s| s["id"].as_str().map(str::to_owned))
        .collect();
    let listen = config["listen"]["endpoints"][0]
        .as_str()
        .ok_or_else(|| lacks(&coordinator_file, "listen endpoint"))?;
    let first = robots
        .first()
        .ok_or_else(|| lacks(&coordinator_file, "robots"))?;
    let cart_file = dir.join(format!("{first}.json5"));
    let cart = read_config(&cart_file)?;
    let connect = cart["connect"]["endpoints"][0]
        .as_str()
        .ok_or_else(|| lacks(&cart_file, "connect endpoint"))?;
    let endpoints = Endpoints::new(listen, connect)?;
    Ok(Authority {
        dir,
        ca_key,
        robots,
        endpoints,
    })
}

/// Adds a cart to the authority in `dir`: its key, certificate and
/// configuration, and the coordinator's configuration rewritten to let it
/// speak (the coordinator restarts to read it). The endpoints are the ones
/// `init` wrote. A cart already there is refused (`revoke` replaces its
/// certificate).
pub fn add(dir: &Path, robot: &str) -> Result<Issued, PkiError> {
    validate_cart_id(robot).map_err(|source| PkiError::RobotId {
        flag: "--robot",
        id: robot.to_owned(),
        source,
    })?;
    let Authority {
        dir,
        ca_key,
        mut robots,
        endpoints,
    } = open_authority(dir)?;
    if robots.iter().any(|r| r == robot) {
        return Err(PkiError::AlreadyIssued {
            robot: robot.to_owned(),
            dir,
        });
    }
    robots.push(robot.to_owned());
    let issuer = Issuer::new(ca_params()?, ca_key);
    let mut files = Vec::new();
    let configs = vec![issue(
        &dir, &issuer, robot, &robots, &endpoints, &mut files,
    )?];
    let coordinator_file = dir.join(format!("{COORDINATOR}.json5"));
    let text = pretty(&coordinator_config(&dir, &robots, &endpoints));
    files.push(write_public(&coordinator_file, &(text + "\n"))?);
    Ok(Issued { files, configs })
}

/// Revokes `holder`'s certificate (a robot's or the coordinator's) and issues
/// it a new key and certificate in its place: the old certificate's
/// fingerprint is appended to [`crate::signing::REVOKED`] beside the
/// authority's certificate, and every process that reads that list refuses
/// every message the old key signs (zenoh's TLS keeps no revocation list, so
/// the old key can still connect, but it can say nothing anyone believes).
/// Copy the list to every host beside its `ca.pem`, and the new files to the
/// holder; restart them to read it.
pub fn revoke(dir: &Path, holder: &str) -> Result<Issued, PkiError> {
    let Authority {
        dir,
        ca_key,
        robots,
        endpoints,
    } = open_authority(dir)?;
    if holder != COORDINATOR && !robots.iter().any(|r| r == holder) {
        return Err(PkiError::NoSuchHolder {
            holder: holder.to_owned(),
            dir,
            robots,
        });
    }
    let cert_file = dir.join(format!("{holder}.pem"));
    let der = crate::signing::read_certificate(&cert_file)
        .map_err(|source| PkiError::Revoking { source })?;
    let fingerprint = crate::signing::fingerprint(&der);
    let list = dir.join(crate::signing::REVOKED);
    let mut out = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&list)
        .map_err(io("open", &list))?;
    set_mode(&list, PUBLIC_MODE)?;
    let when = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    writeln!(
        out,
        "{fingerprint}  # {holder}, revoked at unix time {when}"
    )
    .map_err(io("append to", &list))?;
    // The old certificate is kept for the record; its key goes (keys are
    // written only where none is, so that no key is overwritten by mistake).
    let kept = dir.join(format!("{holder}.revoked-{when}.pem"));
    std::fs::rename(&cert_file, &kept).map_err(io("move aside", &cert_file))?;
    let old_key = dir.join(format!("{holder}.key"));
    match std::fs::remove_file(&old_key) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => {
            return Err(io("remove", &old_key)(e));
        }
    }
    let issuer = Issuer::new(ca_params()?, ca_key);
    let mut files = vec![list, kept];
    let configs = vec![issue(
        &dir, &issuer, holder, &robots, &endpoints, &mut files,
    )?];
    Ok(Issued { files, configs })
}

/// The authority's own certificate parameters (the same for issuing later).
fn ca_params() -> Result<CertificateParams, PkiError> {
    let mut params = CertificateParams::new(Vec::<String>::new())
        .map_err(certificate("the authority's certificate parameters"))?;
    params.distinguished_name = name(CA_NAME);
    params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    Ok(params)
}

/// Issues `holder`'s key and certificate and writes its configuration (a
/// coordinator's over `robots`); returns the configuration.
fn issue(
    dir: &Path,
    issuer: &Issuer<'_, KeyPair>,
    holder: &str,
    robots: &[String],
    endpoints: &Endpoints,
    files: &mut Vec<PathBuf>,
) -> Result<(String, PathBuf), PkiError> {
    let key = KeyPair::generate().map_err(certificate(format!("generating {holder}'s key")))?;
    // The names a cart may reach the coordinator by: loopback, for
    // one-machine setups and tests, and the host carts connect to.
    let mut names = vec!["localhost".to_owned(), "127.0.0.1".to_owned()];
    if holder == COORDINATOR && !names.contains(&endpoints.connect_host) {
        names.push(endpoints.connect_host.clone());
    }
    let mut params = CertificateParams::new(names)
        .map_err(certificate(format!("{holder}'s certificate parameters")))?;
    params.subject_alt_names.push(SanType::DnsName(
        format!("{holder}.b2b")
            .try_into()
            .map_err(certificate(format!("{holder}'s name")))?,
    ));
    params.distinguished_name = name(holder);
    params.key_usages = vec![
        KeyUsagePurpose::DigitalSignature,
        KeyUsagePurpose::KeyEncipherment,
    ];
    params.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    let cert = params
        .signed_by(&key, issuer)
        .map_err(certificate(format!("signing {holder}'s certificate")))?;
    files.push(write_public(
        &dir.join(format!("{holder}.pem")),
        &cert.pem(),
    )?);
    files.push(write_secret(
        &dir.join(format!("{holder}.key")),
        &key.serialize_pem(),
    )?);
    let config = if holder == COORDINATOR {
        coordinator_config(dir, robots, endpoints)
    } else {
        cart_config(dir, holder, endpoints)
    };
    let config_file = dir.join(format!("{holder}.json5"));
    let text = pretty(&config);
    files.push(write_public(&config_file, &(text + "\n"))?);
    Ok((holder.to_owned(), config_file))
}

fn name(common_name: &str) -> DistinguishedName {
    let mut dn = DistinguishedName::new();
    dn.push(DnType::CommonName, common_name);
    dn
}

/// The TLS section of `holder`'s configuration.
fn tls(dir: &Path, holder: &str) -> Value {
    let file = |name: String| dir.join(name).display().to_string();
    json!({
        "root_ca_certificate": file(CA_CERT.to_owned()),
        "listen_private_key": file(format!("{holder}.key")),
        "listen_certificate": file(format!("{holder}.pem")),
        "connect_private_key": file(format!("{holder}.key")),
        "connect_certificate": file(format!("{holder}.pem")),
        "enable_mtls": true,
        "verify_name_on_connect": true,
    })
}

/// Every declaration (subscribers, queryables, queries, liveliness) under the
/// service's keys, both ways: who may *say* what is decided by puts and replies.
fn declarations_rule() -> Value {
    json!({
        "id": "declarations",
        "permission": "allow",
        "flows": ["ingress", "egress"],
        "messages": [
            "declare_subscriber", "declare_queryable", "query",
            "liveliness_token", "liveliness_query", "declare_liveliness_subscriber",
        ],
        "key_exprs": [format!("{KEY_ROOT}/**")],
    })
}

fn says(id: &str, flow: &str, key: String) -> Value {
    json!({
        "id": id,
        "permission": "allow",
        "flows": [flow],
        "messages": ["put", "delete", "reply"],
        "key_exprs": [key],
    })
}

fn subject(id: &str) -> Value {
    json!({ "id": id, "cert_common_names": [id] })
}

/// The coordinator: listens on the TLS endpoint only; takes what a cart says
/// only under that cart's own keys; says things only under its own.
fn coordinator_config(dir: &Path, robots: &[String], endpoints: &Endpoints) -> Value {
    let mut rules = vec![
        declarations_rule(),
        says(
            "coordinator says",
            "egress",
            format!("{KEY_ROOT}/coordinator/**"),
        ),
    ];
    let mut policies = vec![json!({
        "rules": ["declarations", "coordinator says"],
        "subjects": robots,
    })];
    for r in robots {
        let rule = format!("{r} says");
        rules.push(says(&rule, "ingress", format!("{KEY_ROOT}/agent/{r}/**")));
        policies.push(json!({ "rules": [rule], "subjects": [r] }));
    }
    json!({
        "mode": "peer",
        "listen": { "endpoints": [endpoints.listen] },
        "connect": { "endpoints": [] },
        "scouting": { "multicast": { "enabled": false } },
        "transport": { "link": { "tls": tls(dir, COORDINATOR) } },
        "access_control": {
            "enabled": true,
            "default_permission": "deny",
            "rules": rules,
            "subjects": robots.iter().map(|r| subject(r)).collect::<Vec<_>>(),
            "policies": policies,
        },
    })
}

/// A cart: connects to the coordinator and listens on nothing; takes what is
/// said under the coordinator's keys only from the coordinator; says things
/// only under its own keys.
fn cart_config(dir: &Path, robot: &str, endpoints: &Endpoints) -> Value {
    json!({
        "mode": "peer",
        "listen": { "endpoints": [] },
        "connect": { "endpoints": [endpoints.connect] },
        "scouting": { "multicast": { "enabled": false } },
        "transport": { "link": { "tls": tls(dir, robot) } },
        "access_control": {
            "enabled": true,
            "default_permission": "deny",
            "rules": [
                declarations_rule(),
                says("coordinator says", "ingress", format!("{KEY_ROOT}/coordinator/**")),
                says(&format!("{robot} says"), "egress", format!("{KEY_ROOT}/agent/{robot}/**")),
            ],
            "subjects": [subject(COORDINATOR)],
            "policies": [{
                "rules": ["declarations", "coordinator says", format!("{robot} says")],
                "subjects": [COORDINATOR],
            }],
        },
    })
}

/// Certificates, configurations and the revocation list: readable by all,
/// writable by the owner only, whatever the umask (a trust anchor or an
/// access rule anyone may rewrite is neither).
const PUBLIC_MODE: u32 = 0o644;
/// Private keys: the owner only.
const SECRET_MODE: u32 = 0o600;
/// The authority's folder when `pki init` creates it: no one but the owner
/// may add, remove or rename files in it.
const FOLDER_MODE: u32 = 0o755;

/// Sets `path`'s permission bits to exactly `mode` (the umask never widens
/// nor narrows what is written).
fn set_mode(path: &Path, mode: u32) -> Result<(), PkiError> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode))
            .map_err(io("set the permissions of", path))?;
    }
    #[cfg(not(unix))]
    let _ = (path, mode);
    Ok(())
}

/// Creates `dir` and its missing parents as [`FOLDER_MODE`] (less what the
/// umask takes away); a folder that is there already loses group and other
/// write permission, if it had them.
fn create_folder(dir: &Path) -> Result<(), PkiError> {
    let mut builder = std::fs::DirBuilder::new();
    builder.recursive(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::DirBuilderExt;
        builder.mode(FOLDER_MODE);
    }
    builder.create(dir).map_err(io("create folder", dir))?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(dir)
            .map_err(io("read", dir))?
            .permissions()
            .mode()
            & 0o7777;
        if mode & 0o022 != 0 {
            set_mode(dir, mode & !0o022)?;
        }
    }
    Ok(())
}

/// Writes (or replaces) a public file with [`PUBLIC_MODE`].
fn write_public(path: &Path, text: &str) -> Result<PathBuf, PkiError> {
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(PUBLIC_MODE);
    }
    let mut file = options.open(path).map_err(io("create", path))?;
    // Created with the mode less the umask, or there before with its own:
    // set it outright.
    set_mode(path, PUBLIC_MODE)?;
    file.write_all(text.as_bytes())
        .and_then(|_| file.sync_all())
        .map_err(io("write", path))?;
    Ok(path.to_owned())
}

/// Writes a private key readable and writable by its owner only (created so,
/// never widened afterwards).
fn write_secret(path: &Path, text: &str) -> Result<PathBuf, PkiError> {
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(SECRET_MODE);
    }
    let mut file = options.open(path).map_err(io("create", path))?;
    set_mode(path, SECRET_MODE)?;
    file.write_all(text.as_bytes())
        .and_then(|_| file.sync_all())
        .map_err(io("write", path))?;
    Ok(path.to_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn robots() -> Vec<String> {
        vec!["robot1".into(), "robot2".into()]
    }

    #[test]
    fn init_writes_an_authority_owner_only_keys_and_configs_zenoh_reads() {
        let dir = tempfile::tempdir().unwrap();
        let issued = init(
            dir.path(),
            &robots(),
            &Endpoints::at(DEFAULT_TLS_ENDPOINT).unwrap(),
        )
        .unwrap();
        assert_eq!(issued.configs.len(), 3);
        for f in &issued.files {
            let mode = {
                use std::os::unix::fs::PermissionsExt;
                std::fs::metadata(f).unwrap().permissions().mode() & 0o777
            };
            if f.extension().is_some_and(|e| e == "key") {
                assert_eq!(mode, 0o600, "{}", f.display());
            }
        }
        for (_, config) in &issued.configs {
            zenoh::Config::from_file(config)
                .unwrap_or_else(|e| panic!("{}: {e}", config.display()));
        }
        // A second authority over the first is refused.
        let e = init(
            dir.path(),
            &robots(),
            &Endpoints::at(DEFAULT_TLS_ENDPOINT).unwrap(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("already holds an authority"), "{e}");
    }

    #[test]
    fn add_issues_a_cart_and_lets_it_speak_to_the_coordinator() {
        let dir = tempfile::tempdir().unwrap();
        let at = Endpoints::new("tls/0.0.0.0:7447", "tls/10.0.0.5:7447").unwrap();
        init(dir.path(), &robots(), &at).unwrap();
        let added = add(dir.path(), "robot3").unwrap();
        assert_eq!(added.configs[0].0, "robot3");
        let read = |f: &str| -> Value {
            serde_json::from_str(&std::fs::read_to_string(dir.path().join(f)).unwrap()).unwrap()
        };
        let c = read("coordinator.json5");
        let subjects: Vec<&str> = c["access_control"]["subjects"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["id"].as_str().unwrap())
            .collect();
        assert_eq!(subjects, ["robot1", "robot2", "robot3"]);
        assert_eq!(c["listen"]["endpoints"][0], "tls/0.0.0.0:7447");
        assert_eq!(
            read("robot3.json5")["connect"]["endpoints"][0],
            "tls/10.0.0.5:7447"
        );
        let e = add(dir.path(), "robot3").unwrap_err().to_string();
        assert!(
            e.contains("already has a certificate") && e.contains("pki revoke"),
            "{e}"
        );
        let e = b2b_errors::chain(&add(&dir.path().join("none"), "robot4").unwrap_err());
        assert!(e.contains("cannot read the authority's key"), "{e}");
    }

    #[test]
    fn revoke_lists_the_old_certificate_and_issues_a_new_one() {
        use crate::signing::{Identity, REVOKED, SigningError, Verifier};
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        init(d, &robots(), &Endpoints::at(DEFAULT_TLS_ENDPOINT).unwrap()).unwrap();
        let identity = |who: &str| {
            Identity::from_files(&d.join(format!("{who}.pem")), &d.join(format!("{who}.key")))
                .unwrap()
        };
        let old = identity("robot1");
        let key = "b2b/agent/robot1/status";
        let signed_by_old = old.sign(key, b"{}").unwrap();
        let before = Verifier::from_file(&d.join(CA_CERT)).unwrap();
        assert_eq!(
            before.verify(key, b"{}", Some(&signed_by_old)).unwrap(),
            "robot1"
        );

        let revoked = revoke(d, "robot1").unwrap();
        assert!(revoked.files.contains(&d.join(REVOKED)));
        let list = std::fs::read_to_string(d.join(REVOKED)).unwrap();
        assert!(list.contains("# robot1, revoked"), "{list}");
        // The list, read by a new session: the old key's messages are refused,
        // the new key's taken.
        let after = Verifier::from_file(&d.join(CA_CERT)).unwrap();
        assert_eq!(
            after.verify(key, b"{}", Some(&signed_by_old)),
            Err(SigningError::Revoked("robot1".into()))
        );
        let new = identity("robot1");
        let signed_by_new = new.sign(key, b"{}").unwrap();
        assert_eq!(
            after.verify(key, b"{}", Some(&signed_by_new)).unwrap(),
            "robot1"
        );
        // robot2 and the coordinator are untouched; the coordinator can be
        // revoked too, and both stay listed.
        let r2 = identity("robot2")
            .sign("b2b/agent/robot2/status", b"{}")
            .unwrap();
        assert!(
            after
                .verify("b2b/agent/robot2/status", b"{}", Some(&r2))
                .is_ok()
        );
        revoke(d, COORDINATOR).unwrap();
        let list = std::fs::read_to_string(d.join(REVOKED)).unwrap();
        assert_eq!(list.lines().count(), 2, "{list}");
        // Unknown holders and broken lists are named.
        let e = b2b_errors::chain(&revoke(d, "robot9").unwrap_err());
        assert!(e.contains("robot9") && e.contains("robot1, robot2"), "{e}");
        std::fs::write(d.join(REVOKED), format!("{list}not-a-fingerprint\n")).unwrap();
        let e = Verifier::from_file(&d.join(CA_CERT))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(REVOKED) && e.contains("line 3") && e.contains("not-a-fingerprint"),
            "{e}"
        );
    }

    /// Each wrapping error names what it was doing and prints its cause once.
    #[test]
    fn wrapped_errors_print_their_cause_once() {
        let dir = tempfile::tempdir().unwrap();
        let at = Endpoints::at(DEFAULT_TLS_ENDPOINT).unwrap();
        let bad_id = init(dir.path(), &["a/b".to_owned()], &at).unwrap_err();
        assert!(matches!(bad_id, PkiError::RobotId { .. }), "{bad_id:?}");
        b2b_errors::assert_cause_once(&bad_id);
        let no_authority = add(&dir.path().join("none"), "robot4").unwrap_err();
        assert!(
            matches!(no_authority, PkiError::Io { .. }),
            "{no_authority:?}"
        );
        b2b_errors::assert_cause_once(&no_authority);
    }

    #[test]
    fn bad_robot_lists_and_endpoints_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let at = Endpoints::at(DEFAULT_TLS_ENDPOINT).unwrap();
        for (robots, what) in [
            (vec![], "at least one"),
            (vec!["robot1", "robot1"], "twice"),
            (vec!["coordinator"], "the coordinator's envelopes"),
            (vec!["scene"], "the drift watch's scene reference"),
            (vec!["a/b"], "robot id 'a/b'"),
        ] {
            let robots: Vec<String> = robots.into_iter().map(String::from).collect();
            let e = b2b_errors::chain(&init(dir.path(), &robots, &at).unwrap_err());
            assert!(e.contains(what), "{robots:?}: {e}");
        }
        let e = Endpoints::at("tcp/127.0.0.1:7447").unwrap_err().to_string();
        assert!(e.contains("TLS endpoint"), "{e}");
        let e = Endpoints::at("tls/0.0.0.0:7447").unwrap_err().to_string();
        assert!(e.contains("give the coordinator's address"), "{e}");
        let e = Endpoints::at("tls/nohost").unwrap_err().to_string();
        assert!(e.contains("tls/HOST:PORT"), "{e}");
        let ok = Endpoints::new("tls/0.0.0.0:7447", "tls/[fd00::2]:7447").unwrap();
        assert_eq!(ok.connect_host, "fd00::2");
    }
}
