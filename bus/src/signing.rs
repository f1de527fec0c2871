//! Signed messages on the secured bus: who sent a message is proved by the
//! message itself, not only by the link it came on.
//!
//! zenoh's mutual TLS authenticates each link and its access control decides,
//! by the certificate name of the link, what may be said where. zenoh does not
//! hand that name to the application, so the access control alone decides that
//! `b2b/agent/robot1/capture` came from robot1; a wrong rule would let another
//! cart speak for it unseen. So on a secured bus every put and every reply also
//! carries, in its zenoh attachment, the sender's certificate and an ECDSA
//! signature, with its certificate's key, over the key expression and the
//! payload. A receiver accepts a message only if:
//!
//! - the certificate chains to the platform's authority (the configuration's
//!   `root_ca_certificate`) and is valid now;
//! - the signature verifies with the certificate's key;
//! - the certificate's common name is the sender the key names (the robot of
//!   `b2b/agent/<robot>/…`, `coordinator` under `b2b/coordinator/…`).
//!
//! - the certificate is not revoked: its SHA-256 fingerprint is not listed in
//!   [`REVOKED`] beside the authority's certificate (`coordinator pki revoke`
//!   writes it; read when the session opens).
//!
//! Anything else is dropped and logged with the reason. The accepted message's
//! [`crate::Received::signer`] is that common name, and the coordinator's
//! journal records it with each sample.
//!
//! The attachment: one version byte (1), the certificate's DER length as two
//! bytes big-endian, the certificate's DER, then the signature (ASN.1 DER). The
//! signed bytes are [`DOMAIN`], the key, one zero byte, and the payload, so a
//! signature made for one key does not verify under another.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use rcgen::{KeyPair, SigningKey};
use rustls_pki_types::pem::PemObject;
use rustls_pki_types::{CertificateDer, TrustAnchor, UnixTime};

use crate::sender_of;

/// The revocation list beside the authority's certificate: one SHA-256
/// fingerprint (hex) of a certificate's DER per line, `#` starting a comment.
pub const REVOKED: &str = "revoked.txt";

/// Prefixes the signed bytes (domain separation).
pub const DOMAIN: &[u8] = b"b2b-calibration signed message v1\0";
const VERSION: u8 = 1;

/// Why a signed message was not accepted, or why signing is not set up.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SigningError {
    #[error("{path}: {reason}")]
    File { path: String, reason: String },
    #[error("unsigned (the secured bus takes only signed messages)")]
    Unsigned,
    #[error("malformed signature attachment: {0}")]
    Malformed(String),
    #[error("the sender's certificate is not the platform authority's: {0}")]
    Untrusted(String),
    #[error("the signature does not verify with the certificate of '{0}'")]
    BadSignature(String),
    #[error("the certificate of '{0}' that signed it is revoked ({REVOKED})")]
    Revoked(String),
    #[error("signed with the certificate of '{signer}', but the key is {expected}'s")]
    WrongSender { signer: String, expected: String },
    #[error("cannot sign: {0}")]
    Sign(String),
}

/// The certificate and key one process signs with.
pub struct Identity {
    name: String,
    certificate: Vec<u8>,
    key: KeyPair,
}

impl std::fmt::Debug for Identity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Identity")
            .field("name", &self.name)
            .finish()
    }
}

/// What a receiver checks against: the authority, and the certificates it has
/// already checked (by their DER bytes) with their common names.
pub struct Verifier {
    authority: Vec<u8>,
    revoked: std::collections::HashSet<String>,
    checked: Mutex<HashMap<Vec<u8>, String>>,
}

impl std::fmt::Debug for Verifier {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Verifier").finish_non_exhaustive()
    }
}

/// Signing and checking, for one secured session.
#[derive(Debug)]
pub struct Signing {
    pub identity: Identity,
    pub verifier: Verifier,
}

fn file_error(path: &Path, reason: impl std::fmt::Display) -> SigningError {
    SigningError::File {
        path: path.display().to_string(),
        reason: reason.to_string(),
    }
}

/// A PEM certificate file's DER.
pub(crate) fn read_certificate(path: &Path) -> Result<Vec<u8>, SigningError> {
    CertificateDer::from_pem_file(path)
        .map(|c| c.as_ref().to_vec())
        .map_err(|e| file_error(path, format!("not a PEM certificate: {e}")))
}

/// The common name of a certificate (DER).
pub fn common_name(der: &[u8]) -> Result<String, String> {
    name_and_key(der).map(|(name, _)| name)
}

/// A certificate's common name and its raw public key, from one parse.
fn name_and_key(der: &[u8]) -> Result<(String, Vec<u8>), String> {
    let (_, cert) =
        x509_parser::parse_x509_certificate(der).map_err(|e| format!("not a certificate: {e}"))?;
    let name = cert
        .subject()
        .iter_common_name()
        .next()
        .and_then(|cn| cn.as_str().ok())
        .map(str::to_owned)
        .ok_or_else(|| "the certificate has no common name".to_owned())?;
    Ok((name, cert.public_key().subject_public_key.data.to_vec()))
}

impl Identity {
    /// Reads a certificate and its private key (PEM files).
    pub fn from_files(certificate: &Path, key: &Path) -> Result<Identity, SigningError> {
        let der = read_certificate(certificate)?;
        let (name, public) = name_and_key(&der).map_err(|e| file_error(certificate, e))?;
        let pem = std::fs::read_to_string(key).map_err(|e| file_error(key, e))?;
        let key_pair = KeyPair::from_pem(&pem)
            .map_err(|e| file_error(key, format!("not a private key: {e}")))?;
        if public != key_pair.public_key_raw() {
            return Err(file_error(
                key,
                format!("not the key of certificate {}", certificate.display()),
            ));
        }
        Ok(Identity {
            name,
            certificate: der,
            key: key_pair,
        })
    }

    /// The certificate's common name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The attachment that proves this identity sent `payload` under `key`.
    pub fn sign(&self, key: &str, payload: &[u8]) -> Result<Vec<u8>, SigningError> {
        let signature = self
            .key
            .sign(&signed_bytes(key, payload))
            .map_err(|e| SigningError::Sign(e.to_string()))?;
        let len = u16::try_from(self.certificate.len())
            .map_err(|_| SigningError::Sign("certificate over 64 KiB".into()))?;
        let mut out = Vec::with_capacity(3 + self.certificate.len() + signature.len());
        out.push(VERSION);
        out.extend_from_slice(&len.to_be_bytes());
        out.extend_from_slice(&self.certificate);
        out.extend_from_slice(&signature);
        Ok(out)
    }
}

/// A certificate's SHA-256 fingerprint (of its DER), lower-case hex.
pub fn fingerprint(der: &[u8]) -> String {
    ring::digest::digest(&ring::digest::SHA256, der)
        .as_ref()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The fingerprints a revocation list names; a line that is not one is an
/// error naming the line.
fn read_revoked(text: &str) -> Result<std::collections::HashSet<String>, String> {
    let mut out = std::collections::HashSet::new();
    for (i, line) in text.lines().enumerate() {
        let entry = line.split('#').next().unwrap_or_default().trim();
        if entry.is_empty() {
            continue;
        }
        let hex = entry.to_ascii_lowercase();
        if hex.len() != 64 || !hex.chars().all(|c| c.is_ascii_hexdigit()) {
            return Err(format!(
                "line {}: expected a SHA-256 fingerprint (64 hex digits), found {:?}",
                i + 1,
                entry.chars().take(24).collect::<String>()
            ));
        }
        out.insert(hex);
    }
    Ok(out)
}

fn signed_bytes(key: &str, payload: &[u8]) -> Vec<u8> {
    let mut m = Vec::with_capacity(DOMAIN.len() + key.len() + 1 + payload.len());
    m.extend_from_slice(DOMAIN);
    m.extend_from_slice(key.as_bytes());
    m.push(0);
    m.extend_from_slice(payload);
    m
}

impl Verifier {
    /// Trusts the authority certificate in `path` (PEM), less the
    /// certificates [`REVOKED`] beside it lists.
    pub fn from_file(path: &Path) -> Result<Verifier, SigningError> {
        let authority = read_certificate(path)?;
        let der = CertificateDer::from(authority.as_slice());
        webpki::anchor_from_trusted_cert(&der)
            .map_err(|e| file_error(path, format!("not a usable authority: {e:?}")))?;
        let list = path.with_file_name(REVOKED);
        let revoked = match std::fs::read_to_string(&list) {
            Ok(text) => read_revoked(&text).map_err(|e| file_error(&list, e))?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Default::default(),
            Err(e) => return Err(file_error(&list, e)),
        };
        Ok(Verifier {
            authority,
            revoked,
            checked: Mutex::new(HashMap::new()),
        })
    }

    /// Who sent `payload` under `key`, proved by `attachment`; an error names
    /// why the message is not to be believed.
    pub fn verify(
        &self,
        key: &str,
        payload: &[u8],
        attachment: Option<&[u8]>,
    ) -> Result<String, SigningError> {
        let a = attachment.ok_or(SigningError::Unsigned)?;
        if a.len() < 3 || a[0] != VERSION {
            return Err(SigningError::Malformed(format!(
                "{} bytes, version {:?}",
                a.len(),
                a.first()
            )));
        }
        let len = usize::from(u16::from_be_bytes([a[1], a[2]]));
        if a.len() < 3 + len {
            return Err(SigningError::Malformed(format!(
                "certificate of {len} bytes in {} bytes",
                a.len()
            )));
        }
        let (cert, signature) = a[3..].split_at(len);
        let cert_der = CertificateDer::from(cert);
        let ee = webpki::EndEntityCert::try_from(&cert_der)
            .map_err(|e| SigningError::Untrusted(format!("{e:?}")))?;
        let signer = self.chain(cert, &ee)?;
        ee.verify_signature(
            webpki::ring::ECDSA_P256_SHA256,
            &signed_bytes(key, payload),
            signature,
        )
        .map_err(|_| SigningError::BadSignature(signer.clone()))?;
        if let Some(expected) = sender_of(key)
            && expected != signer
        {
            return Err(SigningError::WrongSender {
                signer,
                expected: expected.to_owned(),
            });
        }
        Ok(signer)
    }

    /// The common name of a certificate that chains to the authority (checked
    /// once per certificate).
    fn chain(&self, cert: &[u8], ee: &webpki::EndEntityCert<'_>) -> Result<String, SigningError> {
        if let Some(name) = self.checked.lock().ok().and_then(|m| m.get(cert).cloned()) {
            return Ok(name);
        }
        let authority = CertificateDer::from(self.authority.as_slice());
        let anchor: TrustAnchor<'_> = webpki::anchor_from_trusted_cert(&authority)
            .map_err(|e| SigningError::Untrusted(format!("{e:?}")))?;
        ee.verify_for_usage(
            webpki::ALL_VERIFICATION_ALGS,
            &[anchor],
            &[],
            UnixTime::now(),
            webpki::KeyUsage::client_auth(),
            None,
            None,
        )
        .map_err(|e| SigningError::Untrusted(format!("{e:?}")))?;
        let name = common_name(cert).map_err(SigningError::Untrusted)?;
        if self.revoked.contains(&fingerprint(cert)) {
            return Err(SigningError::Revoked(name));
        }
        if let Ok(mut m) = self.checked.lock() {
            m.insert(cert.to_vec(), name.clone());
        }
        Ok(name)
    }
}

impl Signing {
    /// The signing set-up of a secured zenoh configuration: this process's
    /// certificate and key (`connect_certificate`/`connect_private_key`, else
    /// the `listen_` ones) and the authority (`root_ca_certificate`).
    pub fn from_config(config: &zenoh::Config, file: &Path) -> Result<Signing, SigningError> {
        let get = |name: &str| -> Option<PathBuf> {
            let v = config
                .get_json(&format!("transport/link/tls/{name}"))
                .ok()?;
            let s: Option<String> = serde_json::from_str(&v).ok()?;
            s.filter(|s| !s.is_empty()).map(PathBuf::from)
        };
        let missing = |what: &str| {
            file_error(
                file,
                format!("a secured configuration needs transport/link/tls/{what}"),
            )
        };
        let certificate = get("connect_certificate")
            .or_else(|| get("listen_certificate"))
            .ok_or_else(|| missing("connect_certificate"))?;
        let key = get("connect_private_key")
            .or_else(|| get("listen_private_key"))
            .ok_or_else(|| missing("connect_private_key"))?;
        let authority = get("root_ca_certificate").ok_or_else(|| missing("root_ca_certificate"))?;
        Ok(Signing {
            identity: Identity::from_files(&certificate, &key)?,
            verifier: Verifier::from_file(&authority)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pki;

    fn authority(dir: &Path) -> pki::Issued {
        pki::init(
            dir,
            &["robot1".to_owned(), "robot2".to_owned()],
            &pki::Endpoints::at(pki::DEFAULT_TLS_ENDPOINT).unwrap(),
        )
        .unwrap()
    }

    fn identity(dir: &Path, who: &str) -> Identity {
        Identity::from_files(
            &dir.join(format!("{who}.pem")),
            &dir.join(format!("{who}.key")),
        )
        .unwrap()
    }

    #[test]
    fn a_signed_message_names_its_sender_and_nothing_else_passes() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        authority(dir);
        let verifier = Verifier::from_file(&dir.join(pki::CA_CERT)).unwrap();
        let robot1 = identity(dir, "robot1");
        let robot2 = identity(dir, "robot2");
        let coordinator = identity(dir, "coordinator");
        let key = "b2b/agent/robot1/capture";
        let payload = br#"{"robot":"robot1"}"#;

        let signed = robot1.sign(key, payload).unwrap();
        assert_eq!(
            verifier.verify(key, payload, Some(&signed)).unwrap(),
            "robot1"
        );
        // Twice: the second time from the checked certificates.
        assert_eq!(
            verifier.verify(key, payload, Some(&signed)).unwrap(),
            "robot1"
        );
        let result = coordinator.sign("b2b/coordinator/result", payload).unwrap();
        assert_eq!(
            verifier
                .verify("b2b/coordinator/result", payload, Some(&result))
                .unwrap(),
            "coordinator"
        );

        // robot2's own, valid signature on robot1's key.
        let by_robot2 = robot2.sign(key, payload).unwrap();
        assert_eq!(
            verifier.verify(key, payload, Some(&by_robot2)),
            Err(SigningError::WrongSender {
                signer: "robot2".into(),
                expected: "robot1".into()
            })
        );
        // A cart's signature on the coordinator's result key.
        let forged = robot1.sign("b2b/coordinator/result", payload).unwrap();
        assert!(matches!(
            verifier.verify("b2b/coordinator/result", payload, Some(&forged)),
            Err(SigningError::WrongSender { .. })
        ));
        // The payload changed after signing; the signature moved to another key.
        let mut changed = payload.to_vec();
        changed[3] ^= 1;
        assert_eq!(
            verifier.verify(key, &changed, Some(&signed)),
            Err(SigningError::BadSignature("robot1".into()))
        );
        let moved = robot1.sign("b2b/agent/robot1/status", payload).unwrap();
        assert_eq!(
            verifier.verify(key, payload, Some(&moved)),
            Err(SigningError::BadSignature("robot1".into()))
        );
        // Unsigned, truncated, another version.
        assert_eq!(
            verifier.verify(key, payload, None),
            Err(SigningError::Unsigned)
        );
        for bad in [&signed[..2], &signed[..100], &[2u8, 0, 0][..]] {
            assert!(
                matches!(
                    verifier.verify(key, payload, Some(bad)),
                    Err(SigningError::Malformed(_) | SigningError::Untrusted(_))
                ),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn another_authoritys_certificate_is_not_believed() {
        let tmp = tempfile::tempdir().unwrap();
        let (ours, theirs) = (tmp.path().join("ours"), tmp.path().join("theirs"));
        authority(&ours);
        authority(&theirs);
        let verifier = Verifier::from_file(&ours.join(pki::CA_CERT)).unwrap();
        // A robot1 certificate, correctly signed, from another authority.
        let impostor = identity(&theirs, "robot1");
        let key = "b2b/agent/robot1/status";
        let signed = impostor.sign(key, b"{}").unwrap();
        assert!(matches!(
            verifier.verify(key, b"{}", Some(&signed)),
            Err(SigningError::Untrusted(_))
        ));
        // And a key that is not the certificate's is refused on reading.
        let err =
            Identity::from_files(&ours.join("robot1.pem"), &theirs.join("robot1.key")).unwrap_err();
        assert!(
            err.to_string().contains("not the key of certificate"),
            "{err}"
        );
    }

    #[test]
    fn the_configuration_names_the_files() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        authority(dir);
        let file = dir.join("robot2.json5");
        let config = zenoh::Config::from_file(&file).unwrap();
        let signing = Signing::from_config(&config, &file).unwrap();
        assert_eq!(signing.identity.name(), "robot2");
        let file = dir.join("coordinator.json5");
        let config = zenoh::Config::from_file(&file).unwrap();
        assert_eq!(
            Signing::from_config(&config, &file)
                .unwrap()
                .identity
                .name(),
            "coordinator"
        );
        let mut bare = zenoh::Config::default();
        bare.insert_json5("transport/link/tls/enable_mtls", "true")
            .unwrap();
        let err = Signing::from_config(&bare, &file).unwrap_err();
        assert!(err.to_string().contains("connect_certificate"), "{err}");
    }
}
