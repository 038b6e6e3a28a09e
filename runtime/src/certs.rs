//! The cluster's certificates: a cluster CA made with rcgen issues one
//! certificate per node (its name as DNS subject alternative name, usable as
//! both TLS server and client); every connection is mutual TLS against that
//! CA only.
//!
//! On disk (`dray certs init DIR`, see [`init_cluster`]): `ca.pem`, `ca.key`
//! and, per node, `NODE.pem` and `NODE.key`. Private keys are written with
//! mode 0600 on Unix.

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
    #[error("{0} already exists; refusing to replace the cluster CA (remove the directory to start over)")]
    Exists(PathBuf),
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

impl ClusterCa {
    /// Generates a new CA (ECDSA P-256).
    pub fn generate() -> Result<ClusterCa, CertError> {
        let mut params = CertificateParams::new(Vec::<String>::new())?;
        params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
        params
            .distinguished_name
            .push(DnType::CommonName, "dray cluster CA");
        params.key_usages = vec![
            KeyUsagePurpose::KeyCertSign,
            KeyUsagePurpose::CrlSign,
            KeyUsagePurpose::DigitalSignature,
        ];
        let key = KeyPair::generate()?;
        let cert = params.self_signed(&key)?;
        Ok(ClusterCa { cert, key })
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
        let trust = pem_cert(&dir.join("ca.pem"))?;
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

    /// rustls server configuration: TLS 1.3, ALPN `dray/6`, client
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

    /// rustls client configuration: TLS 1.3, ALPN `dray/6`, the server
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

/// Creates `dir` with a new cluster CA and a certificate for each node
/// (`dray certs init DIR`). Refuses to replace an existing `ca.key`. Returns
/// the files written.
pub fn init_cluster(dir: &Path, nodes: &[&str]) -> Result<Vec<PathBuf>, CertError> {
    let names = nodes
        .iter()
        .map(|n| Name::new(n))
        .collect::<Result<Vec<_>, _>>()?;
    let ca_key_path = dir.join("ca.key");
    if ca_key_path.exists() {
        return Err(CertError::Exists(ca_key_path));
    }
    std::fs::create_dir_all(dir).map_err(|source| CertError::Io {
        path: dir.to_owned(),
        source,
    })?;
    let ca = ClusterCa::generate()?;
    let mut written = Vec::new();
    let ca_pem = dir.join("ca.pem");
    write(&ca_pem, &ca.cert.pem(), false)?;
    write(&ca_key_path, &ca.key.serialize_pem(), true)?;
    written.push(ca_pem);
    written.push(ca_key_path);
    for name in &names {
        let (cert, key) = ca.issue_raw(name)?;
        let cert_path = dir.join(format!("{name}.pem"));
        let key_path = dir.join(format!("{name}.key"));
        write(&cert_path, &cert.pem(), false)?;
        write(&key_path, &key.serialize_pem(), true)?;
        written.push(cert_path);
        written.push(key_path);
    }
    tracing::info!(dir = %dir.display(), nodes = names.len(), "cluster certificates written");
    Ok(written)
}
