//! TLS certificates for a farm on a LAN. `coordinator cert` makes a CA and
//! a server certificate signed by it (rcgen); `serve` and a one-shot render
//! check the certificate they are given before anything starts: a CA
//! certificate (CA:TRUE) is refused as a server's by every TLS client, the
//! workers included, and the refusal (`CaUsedAsEndEntity`) would reach only
//! a worker's log.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use crate::farm::{FarmError, read_pem};

/// The names every server certificate made here carries: local workers
/// dial `localhost`, and clients on the machine may use either address.
const LOCAL_NAMES: [&str; 3] = ["localhost", "127.0.0.1", "::1"];

/// How long the certificates made here are valid.
const VALIDITY: Duration = Duration::from_secs(10 * 365 * 24 * 3600);

/// The files `coordinator cert` writes into its directory.
pub const FILES: [&str; 4] = ["ca.pem", "ca.key", "server.pem", "server.key"];

/// Why `coordinator cert` failed.
#[derive(Debug, thiserror::Error)]
pub enum CertError {
    /// A file or the directory could not be written.
    #[error("{path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What the OS said.
        source: std::io::Error,
    },
    /// A file is there already: certificates and keys are never replaced.
    #[error("{0}: exists already (remove it, or choose another --out)")]
    Exists(PathBuf),
    /// A --name is not a host name or an IP address.
    #[error("--name {name:?}: {message}")]
    Name {
        /// The name given.
        name: String,
        /// What is wrong with it.
        message: String,
    },
    /// rcgen could not make a key or a certificate.
    #[error("cannot make the certificate: {0}")]
    Generate(#[from] rcgen::Error),
}

/// `coordinator cert --out DIR --name HOST…`: writes a CA (`ca.pem`,
/// `ca.key`) and a server certificate signed by it for `names` and the local
/// names (`server.pem`, the server's certificate followed by the CA's, and
/// `server.key`). Keys are 0600, and so is DIR when it is created here.
/// Returns the files written.
pub fn make(dir: &Path, names: &[String]) -> Result<Vec<PathBuf>, CertError> {
    let mut sans: Vec<String> = Vec::new();
    for name in names.iter().map(String::as_str).chain(LOCAL_NAMES) {
        check_name(name)?;
        if !sans.iter().any(|s| s.eq_ignore_ascii_case(name)) {
            sans.push(name.to_string());
        }
    }
    let paths: Vec<PathBuf> = FILES.iter().map(|f| dir.join(f)).collect();
    if let Some(existing) = paths.iter().find(|p| p.symlink_metadata().is_ok()) {
        return Err(CertError::Exists(existing.clone()));
    }
    let now = SystemTime::now();
    let (not_before, not_after) = (now - Duration::from_secs(3600), now + VALIDITY);

    let ca_key = rcgen::KeyPair::generate()?;
    let mut ca = rcgen::CertificateParams::default();
    ca.distinguished_name
        .push(rcgen::DnType::CommonName, "hypertexture farm CA");
    ca.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Constrained(0));
    ca.key_usages = vec![
        rcgen::KeyUsagePurpose::KeyCertSign,
        rcgen::KeyUsagePurpose::CrlSign,
        rcgen::KeyUsagePurpose::DigitalSignature,
    ];
    (ca.not_before, ca.not_after) = (not_before.into(), not_after.into());
    let ca = rcgen::CertifiedIssuer::self_signed(ca, ca_key)?;

    let server_key = rcgen::KeyPair::generate()?;
    let mut server = rcgen::CertificateParams::new(sans.clone())?;
    server
        .distinguished_name
        .push(rcgen::DnType::CommonName, sans[0].as_str());
    server.is_ca = rcgen::IsCa::ExplicitNoCa;
    server.key_usages = vec![rcgen::KeyUsagePurpose::DigitalSignature];
    server.extended_key_usages = vec![rcgen::ExtendedKeyUsagePurpose::ServerAuth];
    (server.not_before, server.not_after) = (not_before.into(), not_after.into());
    let server_cert = server.signed_by(&server_key, &ca)?;

    create_private_dir(dir)?;
    let contents = [
        (ca.pem(), 0o644),
        (ca.key().serialize_pem(), 0o600),
        (format!("{}{}", server_cert.pem(), ca.pem()), 0o644),
        (server_key.serialize_pem(), 0o600),
    ];
    for (path, (text, mode)) in paths.iter().zip(contents) {
        write_new(path, text.as_bytes(), mode)?;
    }
    Ok(paths)
}

/// A host name or an IP address, as a certificate can name it.
fn check_name(name: &str) -> Result<(), CertError> {
    let bad = |message: &str| CertError::Name {
        name: name.to_string(),
        message: message.to_string(),
    };
    if name.parse::<std::net::IpAddr>().is_ok() {
        return Ok(());
    }
    if name.is_empty() || name.len() > 253 {
        return Err(bad(
            "expected a host name of 1 to 253 characters, or an IP address",
        ));
    }
    let label_ok = |l: &str| {
        (1..=63).contains(&l.len())
            && l.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-')
            && !l.starts_with('-')
            && !l.ends_with('-')
    };
    let wildcard = name.strip_prefix("*.");
    if !wildcard.unwrap_or(name).split('.').all(label_ok) {
        return Err(bad(
            "expected a host name (letters, digits and '-' between dots) or an IP address",
        ));
    }
    Ok(())
}

/// Creates `dir` (and its parents) readable by its owner only when it does
/// not exist; an existing directory is used as it is.
fn create_private_dir(dir: &Path) -> Result<(), CertError> {
    let mut builder = std::fs::DirBuilder::new();
    builder.recursive(true);
    #[cfg(unix)]
    std::os::unix::fs::DirBuilderExt::mode(&mut builder, 0o700);
    builder.create(dir).map_err(|source| CertError::Io {
        path: dir.to_path_buf(),
        source,
    })
}

/// Writes a file that must not exist yet (never through a symbolic link),
/// created with `mode`.
fn write_new(path: &Path, bytes: &[u8], mode: u32) -> Result<(), CertError> {
    let io = |source| CertError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, mode);
    #[cfg(not(unix))]
    let _ = mode;
    let mut file = options.open(path).map_err(|e| {
        if e.kind() == std::io::ErrorKind::AlreadyExists {
            CertError::Exists(path.to_path_buf())
        } else {
            io(e)
        }
    })?;
    file.write_all(bytes).map_err(io)?;
    file.sync_all().map_err(io)
}

/// Reads the server's certificate and key for TLS, and refuses a CA
/// certificate as the server's ([`check_server_cert`]).
pub fn read_server_tls(cert: &Path, key: &Path) -> Result<(Vec<u8>, Vec<u8>), FarmError> {
    let pem = read_pem(cert)?;
    check_server_cert(cert, &pem).map_err(FarmError::Tls)?;
    Ok((pem, read_pem(key)?))
}

/// Refuses a server certificate (the first in the file; the rest is its
/// chain) that is a CA's (basicConstraints CA:TRUE): TLS clients refuse it
/// as the end of a chain, and say only `CaUsedAsEndEntity`. The check is
/// rustls's own (webpki), which the workers run: a certificate's own
/// properties (validity, basic constraints) are checked before its issuer
/// is looked for, so with no trust anchor the chain fails, and only this
/// failure is reported here. A file that is not PEM is left to the TLS
/// library to report.
pub fn check_server_cert(path: &Path, pem: &[u8]) -> Result<(), String> {
    use rustls_pki_types::pem::PemObject as _;
    let Some(Ok(first)) = rustls_pki_types::CertificateDer::pem_slice_iter(pem).next() else {
        return Ok(());
    };
    let Ok(cert) = webpki::EndEntityCert::try_from(&first) else {
        return Ok(());
    };
    let verified = cert.verify_for_usage(
        &[],
        &[],
        &[],
        unix_now(),
        webpki::KeyUsage::server_auth(),
        None,
        None,
    );
    if !matches!(verified, Err(webpki::Error::CaUsedAsEndEntity)) {
        return Ok(());
    }
    Err(format!(
        "{}: this is a CA certificate (basicConstraints CA:TRUE, what `openssl req -x509` \
         makes by default), which TLS clients, the workers included, refuse as a server's \
         (CaUsedAsEndEntity). Make a CA and a server certificate signed by it with \
         `coordinator cert --out DIR --name HOST`, then serve with --tls-cert DIR/server.pem \
         --tls-key DIR/server.key and give the workers --ca DIR/ca.pem (or, with openssl, \
         add -addext basicConstraints=critical,CA:FALSE)",
        path.display()
    ))
}

/// The time now, as webpki takes it.
fn unix_now() -> rustls_pki_types::UnixTime {
    rustls_pki_types::UnixTime::since_unix_epoch(
        SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .unwrap_or_default(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("hypertexture-cert-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn the_files_are_a_ca_and_a_leaf_signed_by_it_with_private_keys() {
        use std::os::unix::fs::PermissionsExt as _;
        let dir = scratch("make");
        let out = dir.join("tls");
        let files = make(&out, &["render.lan".into(), "10.0.0.5".into()]).unwrap();
        assert_eq!(files.len(), 4);
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&out), 0o700);
        assert_eq!(mode(&out.join("ca.key")), 0o600);
        assert_eq!(mode(&out.join("server.key")), 0o600);
        let server = std::fs::read(out.join("server.pem")).unwrap();
        check_server_cert(&out.join("server.pem"), &server).unwrap();
        // server.pem is the leaf and then ca.pem; the leaf verifies against
        // the CA for every name, as a worker's TLS checks it.
        use rustls_pki_types::pem::PemObject as _;
        let chain: Vec<_> = rustls_pki_types::CertificateDer::pem_slice_iter(&server)
            .collect::<Result<_, _>>()
            .unwrap();
        let ca_pem = std::fs::read(out.join("ca.pem")).unwrap();
        let ca = rustls_pki_types::CertificateDer::from_pem_slice(&ca_pem).unwrap();
        assert_eq!(chain.len(), 2);
        assert_eq!(chain[1], ca);
        let anchor = webpki::anchor_from_trusted_cert(&ca).unwrap();
        let leaf = webpki::EndEntityCert::try_from(&chain[0]).unwrap();
        leaf.verify_for_usage(
            webpki::ALL_VERIFICATION_ALGS,
            &[anchor],
            &[],
            unix_now(),
            webpki::KeyUsage::server_auth(),
            None,
            None,
        )
        .unwrap();
        for name in ["render.lan", "10.0.0.5", "localhost", "127.0.0.1", "::1"] {
            let name = rustls_pki_types::ServerName::try_from(name).unwrap();
            leaf.verify_is_valid_for_subject_name(&name).unwrap();
        }
        let other = rustls_pki_types::ServerName::try_from("other.lan").unwrap();
        assert!(leaf.verify_is_valid_for_subject_name(&other).is_err());
        let ca_path = out.join("ca.pem");
        assert!(
            check_server_cert(&ca_path, &ca_pem).is_err(),
            "a CA is refused"
        );
        // Never replaced.
        let again = make(&out, &[]).unwrap_err().to_string();
        assert!(again.contains("exists already"), "{again}");
        assert!(make(&dir.join("x"), &["bad name!".into()]).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
