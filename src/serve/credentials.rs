//! The TLS certificate, its key and the token file, re-read while serving: on SIGHUP and when
//! their contents change. Contents are compared, not modification times: kubelet updates a
//! mounted Secret by swapping its `..data` symlink, which leaves the named paths untouched.
//! New connections get the new certificate while open ones keep theirs; a token removed from the
//! file is refused from its next call. A bad new file (unreadable, garbage, a key that does not
//! match, no tokens, an expired certificate) keeps what was served, said in the log and counted
//! in `prac_credential_reloads_total{result="error"}`; sessions are never touched.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, RwLock};
use std::time::Duration;

use anyhow::Context;
use sha2::{Digest, Sha256};
use tokio_rustls::TlsAcceptor;
use tokio_rustls::rustls;
use tokio_rustls::rustls::pki_types::pem::PemObject;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tokio_rustls::rustls::server::{ClientHello, ResolvesServerCert};
use tokio_rustls::rustls::sign::CertifiedKey;
use tokio_util::sync::CancellationToken;

use super::auth::Tokens;
use super::metrics::Metrics;

/// How often the files are compared with what is served: kubelet itself takes up to a minute
/// to show a renewed Secret, so a few seconds add little.
pub(super) const POLL: Duration = Duration::from_secs(2);

/// What a file held when last looked at: its digest, or why it could not be read. A file is
/// loaded (or its failure reported) once per change, not once per poll.
#[derive(Clone, PartialEq, Eq)]
enum Seen {
    Contents([u8; 32]),
    Unreadable(String),
}

/// The certificate served to new connections, swapped whole on a good reload.
#[derive(Debug)]
struct CertResolver {
    current: RwLock<Arc<CertifiedKey>>,
}

impl ResolvesServerCert for CertResolver {
    fn resolve(&self, _hello: ClientHello<'_>) -> Option<Arc<CertifiedKey>> {
        Some(
            self.current
                .read()
                .unwrap_or_else(|p| p.into_inner())
                .clone(),
        )
    }
}

/// A certificate chain and key that make a pair, with the leaf's expiry.
struct Certificate {
    key: Arc<CertifiedKey>,
    /// The leaf's notAfter, in seconds since the Unix epoch.
    not_after: i64,
}

fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

impl Certificate {
    fn parse(cert_pem: &[u8], key_pem: &[u8]) -> anyhow::Result<Certificate> {
        let certs = CertificateDer::pem_slice_iter(cert_pem)
            .collect::<Result<Vec<_>, _>>()
            .context("the TLS certificate is not valid PEM")?;
        let leaf = certs
            .first()
            .context("the TLS certificate file holds no certificate")?;
        let (_, parsed) = x509_parser::parse_x509_certificate(leaf)
            .map_err(|e| anyhow::anyhow!("the TLS certificate is not valid X.509: {e}"))?;
        let not_after = parsed.validity().not_after.timestamp();
        let key = PrivateKeyDer::from_pem_slice(key_pem)
            .context("the TLS key is not a valid PEM private key")?;
        let key = CertifiedKey::from_der(certs, key, &provider())
            .context("the TLS certificate and key do not make a valid pair")?;
        Ok(Certificate {
            key: Arc::new(key),
            not_after,
        })
    }

    fn expired(&self) -> bool {
        self.not_after <= unix_now()
    }
}

fn unix_now() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_secs()).unwrap_or(i64::MAX))
}

struct TlsFiles {
    cert: PathBuf,
    key: PathBuf,
    resolver: Arc<CertResolver>,
    seen: Mutex<Seen>,
}

struct TokenFile {
    path: PathBuf,
    tokens: Arc<Tokens>,
    seen: Mutex<Seen>,
}

/// The server's certificate and tokens, as files and as served.
pub(super) struct Credentials {
    tls: Option<TlsFiles>,
    tokens: Option<TokenFile>,
    metrics: Arc<Metrics>,
}

/// Reads `paths` and digests their contents together.
fn look(paths: &[&Path]) -> (Seen, Vec<Vec<u8>>) {
    let mut digest = Sha256::new();
    let mut contents = Vec::new();
    for path in paths {
        match std::fs::read(path) {
            Ok(bytes) => {
                digest.update((bytes.len() as u64).to_le_bytes());
                digest.update(&bytes);
                contents.push(bytes);
            }
            Err(e) => {
                return (
                    Seen::Unreadable(format!("cannot read {}: {e}", path.display())),
                    Vec::new(),
                );
            }
        }
    }
    (Seen::Contents(digest.finalize().into()), contents)
}

impl Credentials {
    /// Reads the files the settings name. Anything unreadable or invalid stops the server: it
    /// must not start without the TLS or the auth it was asked for. An expired certificate is
    /// served, with a warning: a crash loop would not renew it, and the expiry metric alerts.
    pub(super) fn load(
        tls: Option<&(PathBuf, PathBuf)>,
        tokens: Option<&Path>,
        metrics: Arc<Metrics>,
    ) -> anyhow::Result<Credentials> {
        let tls = match tls {
            Some((cert, key)) => {
                let (seen, contents) = look(&[cert, key]);
                if let Seen::Unreadable(why) = seen {
                    anyhow::bail!(why);
                }
                let certificate = Certificate::parse(&contents[0], &contents[1])?;
                if certificate.expired() {
                    tracing::warn!(
                        cert = %cert.display(),
                        not_after = certificate.not_after,
                        "the TLS certificate has expired; serving it until a valid one replaces it"
                    );
                }
                metrics.set_certificate_expiry(cert, certificate.not_after);
                Some(TlsFiles {
                    cert: cert.clone(),
                    key: key.clone(),
                    resolver: Arc::new(CertResolver {
                        current: RwLock::new(certificate.key),
                    }),
                    seen: Mutex::new(seen),
                })
            }
            None => None,
        };
        let tokens = match tokens {
            Some(path) => {
                let (seen, contents) = look(&[path]);
                if let Seen::Unreadable(why) = seen {
                    anyhow::bail!(why);
                }
                Some(TokenFile {
                    path: path.to_path_buf(),
                    tokens: Arc::new(parse_tokens(path, &contents[0])?),
                    seen: Mutex::new(seen),
                })
            }
            None => None,
        };
        Ok(Credentials {
            tls,
            tokens,
            metrics,
        })
    }

    /// The acceptor for HTTP/2 over TLS, serving whatever certificate is current.
    pub(super) fn acceptor(&self) -> anyhow::Result<Option<TlsAcceptor>> {
        let Some(tls) = &self.tls else {
            return Ok(None);
        };
        let mut config = rustls::ServerConfig::builder_with_provider(provider())
            .with_safe_default_protocol_versions()
            .context("TLS protocol versions")?
            .with_no_client_auth()
            .with_cert_resolver(tls.resolver.clone());
        config.alpn_protocols = vec![b"h2".to_vec()];
        Ok(Some(TlsAcceptor::from(Arc::new(config))))
    }

    /// The tokens the intake checks calls against; None when auth is off.
    pub(super) fn tokens(&self) -> Option<Arc<Tokens>> {
        self.tokens.as_ref().map(|t| t.tokens.clone())
    }

    /// Loads whatever changed since last looked at.
    pub(super) fn reload_changed(&self) {
        if let Some(tls) = &self.tls {
            self.reload_certificate(tls);
        }
        if let Some(file) = &self.tokens {
            self.reload_tokens(file);
        }
    }

    fn reload_certificate(&self, tls: &TlsFiles) {
        let (seen, contents) = look(&[&tls.cert, &tls.key]);
        if !changed(&tls.seen, &seen) {
            return;
        }
        let loaded = match seen {
            Seen::Unreadable(why) => Err(anyhow::anyhow!(why)),
            Seen::Contents(_) => Certificate::parse(&contents[0], &contents[1]).and_then(|c| {
                anyhow::ensure!(
                    !c.expired(),
                    "the new TLS certificate expired at {} (Unix seconds)",
                    c.not_after
                );
                Ok(c)
            }),
        };
        match loaded {
            Ok(certificate) => {
                *tls.resolver
                    .current
                    .write()
                    .unwrap_or_else(|p| p.into_inner()) = certificate.key;
                self.metrics
                    .set_certificate_expiry(&tls.cert, certificate.not_after);
                self.metrics.credential_reload("certificate", true);
                tracing::info!(
                    cert = %tls.cert.display(),
                    not_after = certificate.not_after,
                    "TLS certificate reloaded; new connections get it"
                );
            }
            Err(e) => {
                self.metrics.credential_reload("certificate", false);
                tracing::error!(
                    cert = %tls.cert.display(),
                    error = %format!("{e:#}"),
                    "TLS certificate not reloaded; serving the previous one"
                );
            }
        }
    }

    fn reload_tokens(&self, file: &TokenFile) {
        let (seen, contents) = look(&[&file.path]);
        if !changed(&file.seen, &seen) {
            return;
        }
        let loaded = match seen {
            Seen::Unreadable(why) => Err(anyhow::anyhow!(why)),
            Seen::Contents(_) => parse_tokens(&file.path, &contents[0]),
        };
        match loaded {
            Ok(tokens) => {
                let count = tokens.len();
                file.tokens.replace_with(tokens);
                self.metrics.credential_reload("tokens", true);
                tracing::info!(path = %file.path.display(), tokens = count, "auth tokens reloaded");
            }
            Err(e) => {
                self.metrics.credential_reload("tokens", false);
                tracing::error!(
                    path = %file.path.display(),
                    error = %format!("{e:#}"),
                    "auth tokens not reloaded; serving the previous ones"
                );
            }
        }
    }

    /// Whether there is anything to watch.
    pub(super) fn any(&self) -> bool {
        self.tls.is_some() || self.tokens.is_some()
    }
}

fn parse_tokens(path: &Path, bytes: &[u8]) -> anyhow::Result<Tokens> {
    let text = std::str::from_utf8(bytes)
        .with_context(|| format!("auth tokens {}: not UTF-8", path.display()))?;
    Tokens::parse(text).with_context(|| format!("auth tokens {}", path.display()))
}

/// Records `now` as seen; whether it differs from what was seen before.
fn changed(seen: &Mutex<Seen>, now: &Seen) -> bool {
    let mut last = seen.lock().unwrap_or_else(|p| p.into_inner());
    if *last == *now {
        return false;
    }
    *last = now.clone();
    true
}

/// Compares the files with what is served every [`POLL`] until `cancel`.
pub(super) async fn watch(credentials: Arc<Credentials>, cancel: CancellationToken) {
    if !credentials.any() {
        return;
    }
    let mut poll = tokio::time::interval(POLL);
    poll.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    poll.tick().await;
    loop {
        tokio::select! {
            _ = poll.tick() => {}
            _ = cancel.cancelled() => return,
        }
        let credentials = credentials.clone();
        // Reading files blocks; a slow volume must not hold a runtime thread.
        if tokio::task::spawn_blocking(move || credentials.reload_changed())
            .await
            .is_err()
        {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair(days: i64) -> (String, String) {
        let mut params = rcgen::CertificateParams::new(vec!["localhost".to_string()]).unwrap();
        let now = time::OffsetDateTime::now_utc();
        params.not_before = now - time::Duration::days(2);
        params.not_after = now + time::Duration::days(days);
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = params.self_signed(&key).unwrap();
        (cert.pem(), key.serialize_pem())
    }

    #[test]
    fn garbage_mismatched_and_expired_certificates_are_refused() {
        let (cert, key) = pair(30);
        let parsed = Certificate::parse(cert.as_bytes(), key.as_bytes()).unwrap();
        assert!(!parsed.expired());
        assert!((parsed.not_after - unix_now() - 30 * 86_400).abs() < 120);
        let (_, other_key) = pair(30);
        let mismatch = Certificate::parse(cert.as_bytes(), other_key.as_bytes());
        assert!(
            format!("{:#}", mismatch.err().unwrap()).contains("do not make a valid pair"),
            "a key that does not match"
        );
        assert!(Certificate::parse(b"garbage", key.as_bytes()).is_err());
        assert!(Certificate::parse(cert.as_bytes(), b"garbage").is_err());
        let (old, old_key) = pair(-1);
        assert!(
            Certificate::parse(old.as_bytes(), old_key.as_bytes())
                .unwrap()
                .expired()
        );
    }

    #[test]
    fn a_bad_reload_keeps_what_is_served_and_a_good_one_replaces_it() {
        let dir = tempfile::tempdir().unwrap();
        let (cert_path, key_path, tokens_path) = (
            dir.path().join("tls.crt"),
            dir.path().join("tls.key"),
            dir.path().join("tokens"),
        );
        let (cert, key) = pair(30);
        std::fs::write(&cert_path, &cert).unwrap();
        std::fs::write(&key_path, &key).unwrap();
        std::fs::write(&tokens_path, "alpha-0123456789abcdef\n").unwrap();
        let metrics = Arc::new(Metrics::default());
        let credentials = Credentials::load(
            Some(&(cert_path.clone(), key_path.clone())),
            Some(&tokens_path),
            metrics.clone(),
        )
        .unwrap();
        let served = || {
            credentials
                .tls
                .as_ref()
                .unwrap()
                .resolver
                .current
                .read()
                .unwrap()
                .cert[0]
                .clone()
        };
        let first = served();
        let tokens = credentials.tokens().unwrap();
        let errors = |file: &str| metrics.credential_reloads(file, false);

        // An empty token file and a vanished one: the old tokens stay, each counted once.
        std::fs::write(&tokens_path, "").unwrap();
        credentials.reload_changed();
        credentials.reload_changed();
        assert_eq!((tokens.len(), errors("tokens")), (1, 1));
        std::fs::remove_file(&tokens_path).unwrap();
        credentials.reload_changed();
        assert_eq!((tokens.len(), errors("tokens")), (1, 2));
        std::fs::write(
            &tokens_path,
            "beta-0123456789abcdef\ngamma-0123456789abcdef\n",
        )
        .unwrap();
        credentials.reload_changed();
        assert_eq!(
            (tokens.len(), metrics.credential_reloads("tokens", true)),
            (2, 1)
        );

        // Garbage, a key of another certificate, an expired certificate: the first stays.
        std::fs::write(&cert_path, "garbage").unwrap();
        credentials.reload_changed();
        let (_, other_key) = pair(30);
        std::fs::write(&cert_path, &cert).unwrap();
        std::fs::write(&key_path, &other_key).unwrap();
        credentials.reload_changed();
        let (expired, expired_key) = pair(-1);
        std::fs::write(&cert_path, &expired).unwrap();
        std::fs::write(&key_path, &expired_key).unwrap();
        credentials.reload_changed();
        assert_eq!(errors("certificate"), 3);
        assert_eq!(served(), first);

        let (renewed, renewed_key) = pair(90);
        std::fs::write(&cert_path, &renewed).unwrap();
        std::fs::write(&key_path, &renewed_key).unwrap();
        credentials.reload_changed();
        assert_ne!(served(), first);
        assert_eq!(metrics.credential_reloads("certificate", true), 1);
    }
}
