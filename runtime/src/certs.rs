//! The cluster's certificates: a cluster CA made with rcgen issues one
//! certificate per node (its name as DNS subject alternative name, usable as
//! both TLS server and client); every connection is mutual TLS against that
//! CA only.
//!
//! On disk (`dray certs init DIR`, see [`init_cluster`]): `DIR/ca.pem` (the
//! CA certificate) and, per node, `DIR/NODE.pem` and `DIR/NODE.key`; the CA
//! key lives apart, in `DIR/ca/ca.key` or a folder of its own (`--ca-dir`),
//! and is needed only to issue certificates ([`add_nodes`]), never at run
//! time. [`bundle`] copies what one node needs (`ca.pem`, `NODE.pem`,
//! `NODE.key`) to a folder for its host. Each CA's subject name carries an
//! id of its key, so a certificate of another CA is refused as from an
//! unknown issuer. Private keys are written with mode 0600 on Unix, the CA
//! key's folder 0700.

use dray_protocol::{Name, NameError, ALPN};
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, KeyPair,
    KeyUsagePurpose,
};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};
use rustls::server::WebPkiClientVerifier;
use rustls::RootCertStore;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Why certificates could not be made, read or used.
#[derive(Debug, thiserror::Error)]
pub enum CertError {
    /// rcgen failed.
    #[error("cannot generate a certificate: {0}")]
    Generate(#[from] rcgen::Error),
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What happened.
        source: std::io::Error,
    },
    /// A PEM file holds no usable certificate or key.
    #[error("{path}: {reason}")]
    Pem {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// `init` would overwrite an existing CA.
    #[error("{0} already exists; refusing to replace the cluster CA (remove the directory to start over, or add nodes with `dray certs add`)")]
    Exists(PathBuf),
    /// A node's certificate exists already.
    #[error("{0} already exists; a node keeps its certificate (remove it to issue a new one)")]
    NodeExists(PathBuf),
    /// The CA key is not where it should be.
    #[error("{path}: the CA key is missing{hint}")]
    NoCaKey {
        /// Where it was looked for.
        path: PathBuf,
        /// Where it may be instead.
        hint: String,
    },
    /// The CA key is not the key of the CA certificate.
    #[error("{key} is not the key of the CA certificate {cert}")]
    CaMismatch {
        /// The key file.
        key: PathBuf,
        /// The certificate file.
        cert: PathBuf,
    },
    /// A node name is not valid.
    #[error("invalid node name: {0}")]
    Name(#[from] NameError),
    /// rustls refused the configuration.
    #[error("TLS configuration: {0}")]
    Tls(#[from] rustls::Error),
    /// The client certificate verifier could not be built.
    #[error("TLS client verifier: {0}")]
    Verifier(#[from] rustls::server::VerifierBuilderError),
}

/// A cluster certificate authority held in memory.
pub struct ClusterCa {
    cert: rcgen::Certificate,
    key: KeyPair,
}

/// FNV-1a, 64 bits: a hash that stays the same across builds, so a CA's
/// subject name can be derived again from its key.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// The CA's subject name: unique per CA (an id of its random key), so that
/// a certificate of another CA never matches this one's name and is
/// refused as from an unknown issuer rather than for a bad signature.
fn ca_common_name(key: &KeyPair) -> String {
    format!("dray cluster CA {:016x}", fnv1a(key.public_key_raw()))
}

impl ClusterCa {
    /// Generates a new CA (ECDSA P-256).
    pub fn generate() -> Result<ClusterCa, CertError> {
        ClusterCa::with_key(KeyPair::generate()?)
    }

    /// The CA certificate of `key`. Its subject name and key identifier
    /// follow from the key, so certificates issued by a CA rebuilt from
    /// its key verify against the CA certificate first written.
    fn with_key(key: KeyPair) -> Result<ClusterCa, CertError> {
        let mut params = CertificateParams::new(Vec::<String>::new())?;
        params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
        params
            .distinguished_name
            .push(DnType::CommonName, ca_common_name(&key));
        params.key_usages = vec![
            KeyUsagePurpose::KeyCertSign,
            KeyUsagePurpose::CrlSign,
            KeyUsagePurpose::DigitalSignature,
        ];
        let cert = params.self_signed(&key)?;
        Ok(ClusterCa { cert, key })
    }

    /// Loads the CA of certificate directory `dir` from its key in
    /// `ca_dir` (`DIR/ca` by default), checking that the key is the one of
    /// `dir/ca.pem`.
    pub fn load(dir: &Path, ca_dir: Option<&Path>) -> Result<ClusterCa, CertError> {
        let key_path = ca_key_path(dir, ca_dir);
        if !key_path.exists() {
            let legacy = dir.join(CA_KEY);
            let hint = if legacy.exists() {
                format!(
                    " ({} is a CA key next to the node keys: move it to {})",
                    legacy.display(),
                    key_path.display()
                )
            } else {
                " (only the folder that `dray certs init` wrote it to has it; name that folder with --ca-dir)".into()
            };
            return Err(CertError::NoCaKey {
                path: key_path,
                hint,
            });
        }
        let pem = String::from_utf8(read(&key_path)?).map_err(|_| CertError::Pem {
            path: key_path.clone(),
            reason: "not a PEM file".into(),
        })?;
        let key = KeyPair::from_pem(&pem).map_err(|e| CertError::Pem {
            path: key_path.clone(),
            reason: format!("no usable private key: {e}"),
        })?;
        let cert_path = dir.join(CA_CERT);
        let on_disk = pem_cert(&cert_path)?;
        let ca = ClusterCa::with_key(key)?;
        let contains = |needle: &[u8]| on_disk.windows(needle.len()).any(|w| w == needle);
        if !contains(ca.key.public_key_raw()) || !contains(ca_common_name(&ca.key).as_bytes()) {
            return Err(CertError::CaMismatch {
                key: key_path,
                cert: cert_path,
            });
        }
        Ok(ca)
    }

    /// The CA certificate, DER.
    pub fn cert_der(&self) -> CertificateDer<'static> {
        self.cert.der().clone()
    }

    /// Issues the certificate of node `node`, returning it with its key.
    pub fn issue(&self, node: &Name) -> Result<NodeIdentity, CertError> {
        let (cert, key) = self.issue_raw(node)?;
        Ok(NodeIdentity {
            node: node.clone(),
            trust: self.cert_der(),
            cert: cert.der().clone(),
            key: key.serialize_der(),
        })
    }

    fn issue_raw(&self, node: &Name) -> Result<(rcgen::Certificate, KeyPair), CertError> {
        let mut params = CertificateParams::new(vec![node.to_string()])?;
        params
            .distinguished_name
            .push(DnType::CommonName, node.as_str());
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        params.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        params.use_authority_key_identifier_extension = true;
        let key = KeyPair::generate()?;
        let cert = params.signed_by(&key, &self.cert, &self.key)?;
        Ok((cert, key))
    }
}

/// What a node needs to speak mutual TLS: its certificate and key, and the
/// CA it trusts.
#[derive(Clone)]
pub struct NodeIdentity {
    node: Name,
    trust: CertificateDer<'static>,
    cert: CertificateDer<'static>,
    key: Vec<u8>,
}

impl std::fmt::Debug for NodeIdentity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NodeIdentity")
            .field("node", &self.node)
            .finish_non_exhaustive()
    }
}

fn read(path: &Path) -> Result<Vec<u8>, CertError> {
    std::fs::read(path).map_err(|source| CertError::Io {
        path: path.to_owned(),
        source,
    })
}

/// The CA certificate's file name in a certificate directory.
pub const CA_CERT: &str = "ca.pem";
/// The CA key's file name in its folder.
pub const CA_KEY: &str = "ca.key";

/// Where the CA key of certificate directory `dir` lives: in `ca_dir`, by
/// default `dir/ca`.
pub fn ca_key_path(dir: &Path, ca_dir: Option<&Path>) -> PathBuf {
    ca_dir
        .map_or_else(|| dir.join("ca"), Path::to_path_buf)
        .join(CA_KEY)
}

fn pem_cert(path: &Path) -> Result<CertificateDer<'static>, CertError> {
    let bytes = read(path)?;
    CertificateDer::from_pem_slice(&bytes).map_err(|e| CertError::Pem {
        path: path.to_owned(),
        reason: format!("no certificate: {e}"),
    })
}

impl NodeIdentity {
    /// Loads node `node`'s identity from a directory made by [`init_cluster`].
    pub fn load(dir: &Path, node: &Name) -> Result<NodeIdentity, CertError> {
        let legacy = dir.join(CA_KEY);
        if legacy.exists() {
            tracing::warn!(
                ca_key = %legacy.display(),
                "the CA key lies next to the node keys: whoever has this folder can mint any \
                 node's identity; a node needs only ca.pem and its own certificate and key \
                 (`dray certs bundle`), move ca.key to a ca/ folder or off the host"
            );
        }
        let trust = pem_cert(&dir.join(CA_CERT))?;
        let cert = pem_cert(&dir.join(format!("{node}.pem")))?;
        let key_path = dir.join(format!("{node}.key"));
        let key_bytes = read(&key_path)?;
        let key = match PrivateKeyDer::from_pem_slice(&key_bytes) {
            Ok(PrivateKeyDer::Pkcs8(k)) => k.secret_pkcs8_der().to_vec(),
            Ok(_) => {
                return Err(CertError::Pem {
                    path: key_path,
                    reason: "the key is not PKCS#8".into(),
                })
            }
            Err(e) => {
                return Err(CertError::Pem {
                    path: key_path,
                    reason: format!("no private key: {e}"),
                })
            }
        };
        Ok(NodeIdentity {
            node: node.clone(),
            trust,
            cert,
            key,
        })
    }

    /// A node certificate signed by itself, trusting only itself: what a
    /// stranger to the cluster has. For tests of refusal.
    pub fn self_signed(node: &Name) -> Result<NodeIdentity, CertError> {
        let mut params = CertificateParams::new(vec![node.to_string()])?;
        params
            .distinguished_name
            .push(DnType::CommonName, node.as_str());
        let key = KeyPair::generate()?;
        let cert = params.self_signed(&key)?;
        Ok(NodeIdentity {
            node: node.clone(),
            trust: cert.der().clone(),
            cert: cert.der().clone(),
            key: key.serialize_der(),
        })
    }

    /// The same identity trusting another CA (for tests: a stranger who
    /// knows the cluster's public CA certificate).
    pub fn trusting(mut self, ca: CertificateDer<'static>) -> NodeIdentity {
        self.trust = ca;
        self
    }

    /// The node name in the certificate.
    pub fn node(&self) -> &Name {
        &self.node
    }

    fn key(&self) -> PrivateKeyDer<'static> {
        PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(self.key.clone()))
    }

    fn roots(&self) -> Result<Arc<RootCertStore>, CertError> {
        let mut roots = RootCertStore::empty();
        roots.add(self.trust.clone())?;
        Ok(Arc::new(roots))
    }

    /// rustls server configuration: TLS 1.3, ALPN [`ALPN`], client
    /// certificates required and verified against the trusted CA.
    pub fn server_tls(&self) -> Result<rustls::ServerConfig, CertError> {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let verifier =
            WebPkiClientVerifier::builder_with_provider(self.roots()?, provider.clone()).build()?;
        let mut cfg = rustls::ServerConfig::builder_with_provider(provider)
            .with_protocol_versions(&[&rustls::version::TLS13])?
            .with_client_cert_verifier(verifier)
            .with_single_cert(vec![self.cert.clone()], self.key())?;
        cfg.alpn_protocols = vec![ALPN.to_vec()];
        Ok(cfg)
    }

    /// rustls client configuration: TLS 1.3, ALPN [`ALPN`], the server
    /// verified against the trusted CA, our certificate presented.
    pub fn client_tls(&self) -> Result<rustls::ClientConfig, CertError> {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut cfg = rustls::ClientConfig::builder_with_provider(provider)
            .with_protocol_versions(&[&rustls::version::TLS13])?
            .with_root_certificates(self.roots()?)
            .with_client_auth_cert(vec![self.cert.clone()], self.key())?;
        cfg.alpn_protocols = vec![ALPN.to_vec()];
        Ok(cfg)
    }
}

fn write(path: &Path, contents: &str, secret: bool) -> Result<(), CertError> {
    let io = |source| CertError::Io {
        path: path.to_owned(),
        source,
    };
    let mut opts = std::fs::OpenOptions::new();
    opts.write(true).create(true).truncate(true);
    #[cfg(unix)]
    if secret {
        use std::os::unix::fs::OpenOptionsExt;
        opts.mode(0o600);
    }
    #[cfg(not(unix))]
    let _ = secret;
    let mut f = opts.open(path).map_err(io)?;
    std::io::Write::write_all(&mut f, contents.as_bytes()).map_err(io)
}

fn create_dir(dir: &Path, private: bool) -> Result<(), CertError> {
    let io = |source| CertError::Io {
        path: dir.to_owned(),
        source,
    };
    std::fs::create_dir_all(dir).map_err(io)?;
    #[cfg(unix)]
    if private {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o700)).map_err(io)?;
    }
    #[cfg(not(unix))]
    let _ = private;
    Ok(())
}

fn names(nodes: &[&str]) -> Result<Vec<Name>, CertError> {
    nodes
        .iter()
        .map(|n| Name::new(n))
        .collect::<Result<_, _>>()
        .map_err(CertError::from)
}

/// Writes node `name`'s certificate and key into `dir`, refusing to replace
/// them.
fn write_node(ca: &ClusterCa, dir: &Path, name: &Name) -> Result<[PathBuf; 2], CertError> {
    let cert_path = dir.join(format!("{name}.pem"));
    let key_path = dir.join(format!("{name}.key"));
    for p in [&cert_path, &key_path] {
        if p.exists() {
            return Err(CertError::NodeExists(p.clone()));
        }
    }
    let (cert, key) = ca.issue_raw(name)?;
    write(&cert_path, &cert.pem(), false)?;
    write(&key_path, &key.serialize_pem(), true)?;
    Ok([cert_path, key_path])
}

/// Creates `dir` with a new cluster CA and a certificate for each node
/// (`dray certs init DIR`), the CA key in `dir/ca/`. Returns the files
/// written.
pub fn init_cluster(dir: &Path, nodes: &[&str]) -> Result<Vec<PathBuf>, CertError> {
    init_cluster_in(dir, None, nodes)
}

/// [`init_cluster`] with the CA key in `ca_dir` (`dir/ca` when `None`).
/// Refuses to replace an existing CA certificate or key.
pub fn init_cluster_in(
    dir: &Path,
    ca_dir: Option<&Path>,
    nodes: &[&str],
) -> Result<Vec<PathBuf>, CertError> {
    let names = names(nodes)?;
    let ca_key_path = ca_key_path(dir, ca_dir);
    for p in [dir.join(CA_CERT), dir.join(CA_KEY), ca_key_path.clone()] {
        if p.exists() {
            return Err(CertError::Exists(p));
        }
    }
    create_dir(dir, false)?;
    if let Some(parent) = ca_key_path.parent() {
        create_dir(parent, true)?;
    }
    let ca = ClusterCa::generate()?;
    let ca_pem = dir.join(CA_CERT);
    write(&ca_key_path, &ca.key.serialize_pem(), true)?;
    write(&ca_pem, &ca.cert.pem(), false)?;
    let mut written = vec![ca_pem, ca_key_path];
    for name in &names {
        written.extend(write_node(&ca, dir, name)?);
    }
    tracing::info!(dir = %dir.display(), nodes = names.len(), "cluster certificates written");
    Ok(written)
}

/// Issues certificates for more nodes from the existing CA of `dir` (its
/// key in `ca_dir`, `dir/ca` when `None`), leaving every other
/// certificate as it is (`dray certs add`). Refuses to replace a node's
/// certificate. Returns the files written.
pub fn add_nodes(
    dir: &Path,
    ca_dir: Option<&Path>,
    nodes: &[&str],
) -> Result<Vec<PathBuf>, CertError> {
    let names = names(nodes)?;
    let ca = ClusterCa::load(dir, ca_dir)?;
    for name in &names {
        for p in [
            dir.join(format!("{name}.pem")),
            dir.join(format!("{name}.key")),
        ] {
            if p.exists() {
                return Err(CertError::NodeExists(p));
            }
        }
    }
    let mut written = Vec::new();
    for name in &names {
        written.extend(write_node(&ca, dir, name)?);
    }
    tracing::info!(dir = %dir.display(), nodes = names.len(), "node certificates added");
    Ok(written)
}

/// Copies what node `node` needs at run time, and nothing else (no CA
/// key, no other node's key), from `dir` to `out` (`dray certs bundle`):
/// `ca.pem`, `NODE.pem` and `NODE.key`. `out` then serves as that node's
/// `certs.dir`. Refuses to replace files in `out`. Returns the files
/// written.
pub fn bundle(dir: &Path, node: &str, out: &Path) -> Result<Vec<PathBuf>, CertError> {
    let node = Name::new(node)?;
    // Loading checks that the three files are there and usable.
    NodeIdentity::load(dir, &node)?;
    let files = [
        (CA_CERT.to_string(), false),
        (format!("{node}.pem"), false),
        (format!("{node}.key"), true),
    ];
    for (f, _) in &files {
        if out.join(f).exists() {
            return Err(CertError::NodeExists(out.join(f)));
        }
    }
    create_dir(out, true)?;
    let mut written = Vec::new();
    for (f, secret) in files {
        let bytes = read(&dir.join(&f))?;
        let text = String::from_utf8(bytes).map_err(|_| CertError::Pem {
            path: dir.join(&f),
            reason: "not a PEM file".into(),
        })?;
        let to = out.join(&f);
        write(&to, &text, secret)?;
        written.push(to);
    }
    Ok(written)
}
