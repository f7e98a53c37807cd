//! `prac serve` settings: command-line flags over an optional TOML file over defaults.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use serde::Deserialize;

use super::batch::BatchConfig;
use super::transport::Limits;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    Text,
    Json,
}

/// Flags of `prac serve`; each overrides the same key of the `--config` file.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct ServeArgs {
    /// TOML file with any of the keys below (snake_case, e.g. max_sessions = 64).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Address to listen on, e.g. 127.0.0.1:50051, [::1]:50051 or localhost:50051
    /// [default: 127.0.0.1:50051]; port 0 picks a free port.
    #[arg(long, value_parser = socket_address)]
    pub listen: Option<SocketAddr>,
    /// Directory of NAME.safetensors bundles [default: bundles/ in the repository].
    #[arg(long)]
    pub bundles: Option<PathBuf>,
    /// Most sessions open at once [default: 1024].
    #[arg(long)]
    pub max_sessions: Option<usize>,
    /// A session unused for this long is evicted, e.g. "5m" [default: 5m].
    #[arg(long, value_parser = humantime::parse_duration)]
    pub session_ttl: Option<Duration>,
    /// Largest gRPC message accepted or sent, in bytes [default: 4194304].
    #[arg(long)]
    pub max_message_bytes: Option<usize>,
    /// On SIGINT/SIGTERM, how long to wait for in-flight work before exiting [default: 10s].
    #[arg(long, value_parser = humantime::parse_duration)]
    pub drain_timeout: Option<Duration>,
    /// Log format on stderr [default: text].
    #[arg(long, value_enum)]
    pub log_format: Option<LogFormat>,
    /// Refuse to start if any bundle fails to load (default: skip it with an error).
    #[arg(long)]
    pub strict: bool,
    /// Largest max_horizon, grow k or fixed n a session may ask for [default: 256].
    #[arg(long)]
    pub max_horizon_limit: Option<usize>,
    /// Most steps replanned together across sessions; 0 turns batching off (each step is
    /// replanned in its request handler) [default: 64].
    #[arg(long)]
    pub batch_max: Option<usize>,
    /// How long a batch worker waits for more steps after the first, e.g. "200us"; 0 takes only
    /// what is already queued, adding no delay [default: 0s].
    #[arg(long, value_parser = humantime::parse_duration)]
    pub batch_window: Option<Duration>,
    /// Steps that may wait for a batch worker; more are refused with RESOURCE_EXHAUSTED
    /// [default: 4096].
    #[arg(long)]
    pub batch_queue: Option<usize>,
    /// Batch worker threads [default: 2].
    #[arg(long)]
    pub batch_workers: Option<usize>,
    /// File of bearer tokens, one per line: every prac.v1 call must carry
    /// `authorization: Bearer TOKEN`, and a session belongs to the token that opened it
    /// [default: no auth].
    #[arg(long)]
    pub auth_tokens: Option<PathBuf>,
    /// PEM certificate chain: serve TLS (with --tls-key) [default: plaintext].
    #[arg(long, requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Serve Prometheus metrics over HTTP at ADDR/metrics, e.g. 127.0.0.1:9090; port 0 picks a
    /// free port (printed as `metrics on ADDR`) [default: off].
    #[arg(long, value_parser = socket_address)]
    pub metrics_listen: Option<SocketAddr>,
    /// Most client connections open at once; more are closed when accepted (lowered to fit the
    /// open-file limit) [default: 1024].
    #[arg(long)]
    pub max_connections: Option<usize>,
    /// Most concurrent streams (calls) on one connection (HTTP/2 SETTINGS_MAX_CONCURRENT_STREAMS)
    /// [default: 256].
    #[arg(long)]
    pub max_streams_per_connection: Option<u32>,
    /// A connection must finish its TLS handshake and send its first request within this, or it
    /// is closed [default: 10s].
    #[arg(long, value_parser = humantime::parse_duration)]
    pub handshake_timeout: Option<Duration>,
    /// A connection with no call in flight for this long is closed with GOAWAY (clients
    /// reconnect by themselves); 0s keeps idle connections [default: 10m].
    #[arg(long, value_parser = humantime::parse_duration)]
    pub idle_timeout: Option<Duration>,
    /// Interval of HTTP/2 PINGs to each client; 0s sends none [default: 30s].
    #[arg(long, value_parser = humantime::parse_duration)]
    pub keepalive_interval: Option<Duration>,
    /// A PING unanswered for this long closes the connection [default: 20s].
    #[arg(long, value_parser = humantime::parse_duration)]
    pub keepalive_timeout: Option<Duration>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileConfig {
    listen: Option<SocketAddr>,
    bundles: Option<PathBuf>,
    max_sessions: Option<usize>,
    session_ttl: Option<String>,
    max_message_bytes: Option<usize>,
    drain_timeout: Option<String>,
    log_format: Option<LogFormat>,
    strict: Option<bool>,
    max_horizon_limit: Option<usize>,
    batch_max: Option<usize>,
    batch_window: Option<String>,
    batch_queue: Option<usize>,
    batch_workers: Option<usize>,
    auth_tokens: Option<PathBuf>,
    tls_cert: Option<PathBuf>,
    tls_key: Option<PathBuf>,
    metrics_listen: Option<SocketAddr>,
    max_connections: Option<usize>,
    max_streams_per_connection: Option<u32>,
    handshake_timeout: Option<String>,
    idle_timeout: Option<String>,
    keepalive_interval: Option<String>,
    keepalive_timeout: Option<String>,
}

/// The settings in force.
#[derive(Clone, Debug, PartialEq)]
pub struct ServeConfig {
    pub listen: SocketAddr,
    pub bundles: PathBuf,
    pub max_sessions: usize,
    pub session_ttl: Duration,
    pub max_message_bytes: usize,
    pub drain_timeout: Duration,
    pub log_format: LogFormat,
    pub strict: bool,
    pub max_horizon_limit: usize,
    /// Cross-session batching; None when off.
    pub batch: Option<BatchConfig>,
    pub auth_tokens: Option<PathBuf>,
    /// Certificate chain and key (PEM) when serving TLS.
    pub tls: Option<(PathBuf, PathBuf)>,
    /// Where to serve Prometheus metrics; None when off.
    pub metrics_listen: Option<SocketAddr>,
    /// Limits on client connections (the metrics endpoint's too).
    pub connections: Limits,
}

/// The repository's bundle directory, which holds the shipped bundles.
pub fn default_bundle_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("bundles")
}

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig {
            listen: SocketAddr::from(([127, 0, 0, 1], 50051)),
            bundles: default_bundle_dir(),
            max_sessions: 1024,
            session_ttl: Duration::from_secs(300),
            max_message_bytes: 4 << 20,
            drain_timeout: Duration::from_secs(10),
            log_format: LogFormat::Text,
            strict: false,
            max_horizon_limit: 256,
            batch: Some(BatchConfig {
                max_batch: 64,
                window: Duration::ZERO,
                queue: 4096,
                workers: 2,
            }),
            auth_tokens: None,
            tls: None,
            metrics_listen: None,
            connections: Limits {
                max_connections: 1024,
                max_streams_per_connection: 256,
                handshake_timeout: Duration::from_secs(10),
                idle_timeout: Some(Duration::from_secs(600)),
                keepalive_interval: Some(Duration::from_secs(30)),
                keepalive_timeout: Duration::from_secs(20),
            },
        }
    }
}

/// An address to listen on: IP:PORT, [IPv6]:PORT, or HOST:PORT resolved now (its first address).
fn socket_address(text: &str) -> Result<SocketAddr, String> {
    use std::net::ToSocketAddrs;
    if let Ok(addr) = text.parse() {
        return Ok(addr);
    }
    let Some((_, port)) = text.rsplit_once(':') else {
        return Err(format!(
            "{text:?} has no port; expected HOST:PORT such as 127.0.0.1:50051 or localhost:50051"
        ));
    };
    if port.parse::<u16>().is_err() {
        return Err(format!(
            "{text:?}: the port {port:?} is not a number from 0 to 65535"
        ));
    }
    text.to_socket_addrs()
        .map_err(|e| format!("cannot resolve {text:?}: {e}"))?
        .next()
        .ok_or_else(|| format!("{text:?} resolves to no address"))
}

/// A duration where 0 means "never".
fn nonzero(d: Duration) -> Option<Duration> {
    (!d.is_zero()).then_some(d)
}

fn duration(key: &str, text: Option<String>) -> anyhow::Result<Option<Duration>> {
    text.map(|t| {
        humantime::parse_duration(&t)
            .with_context(|| format!("{key} = {t:?} is not a duration such as \"30s\" or \"5m\""))
    })
    .transpose()
}

impl ServeConfig {
    pub fn resolve(args: &ServeArgs) -> anyhow::Result<ServeConfig> {
        let file = match &args.config {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("cannot read config {}", path.display()))?;
                toml::from_str::<FileConfig>(&text)
                    .with_context(|| format!("invalid config {}", path.display()))?
            }
            None => FileConfig::default(),
        };
        let d = ServeConfig::default();
        let config = ServeConfig {
            listen: args.listen.or(file.listen).unwrap_or(d.listen),
            bundles: args.bundles.clone().or(file.bundles).unwrap_or(d.bundles),
            max_sessions: args
                .max_sessions
                .or(file.max_sessions)
                .unwrap_or(d.max_sessions),
            session_ttl: args
                .session_ttl
                .or(duration("session_ttl", file.session_ttl)?)
                .unwrap_or(d.session_ttl),
            max_message_bytes: args
                .max_message_bytes
                .or(file.max_message_bytes)
                .unwrap_or(d.max_message_bytes),
            drain_timeout: args
                .drain_timeout
                .or(duration("drain_timeout", file.drain_timeout)?)
                .unwrap_or(d.drain_timeout),
            log_format: args.log_format.or(file.log_format).unwrap_or(d.log_format),
            strict: args.strict || file.strict.unwrap_or(false),
            max_horizon_limit: args
                .max_horizon_limit
                .or(file.max_horizon_limit)
                .unwrap_or(d.max_horizon_limit),
            batch: None,
            auth_tokens: args.auth_tokens.clone().or(file.auth_tokens),
            tls: match (
                args.tls_cert.clone().or(file.tls_cert),
                args.tls_key.clone().or(file.tls_key),
            ) {
                (Some(cert), Some(key)) => Some((cert, key)),
                (None, None) => None,
                _ => anyhow::bail!("tls_cert and tls_key go together"),
            },
            metrics_listen: args.metrics_listen.or(file.metrics_listen),
            connections: {
                let dc = d.connections;
                Limits {
                    max_connections: args
                        .max_connections
                        .or(file.max_connections)
                        .unwrap_or(dc.max_connections),
                    max_streams_per_connection: args
                        .max_streams_per_connection
                        .or(file.max_streams_per_connection)
                        .unwrap_or(dc.max_streams_per_connection),
                    handshake_timeout: args
                        .handshake_timeout
                        .or(duration("handshake_timeout", file.handshake_timeout)?)
                        .unwrap_or(dc.handshake_timeout),
                    idle_timeout: match args
                        .idle_timeout
                        .or(duration("idle_timeout", file.idle_timeout)?)
                    {
                        Some(d) => nonzero(d),
                        None => dc.idle_timeout,
                    },
                    keepalive_interval: match args
                        .keepalive_interval
                        .or(duration("keepalive_interval", file.keepalive_interval)?)
                    {
                        Some(d) => nonzero(d),
                        None => dc.keepalive_interval,
                    },
                    keepalive_timeout: args
                        .keepalive_timeout
                        .or(duration("keepalive_timeout", file.keepalive_timeout)?)
                        .unwrap_or(dc.keepalive_timeout),
                }
            },
        };
        let db = d.batch.expect("batching is on by default");
        let max_batch = args.batch_max.or(file.batch_max).unwrap_or(db.max_batch);
        let config = ServeConfig {
            batch: (max_batch > 0).then_some(BatchConfig {
                max_batch,
                window: args
                    .batch_window
                    .or(duration("batch_window", file.batch_window)?)
                    .unwrap_or(db.window),
                queue: args.batch_queue.or(file.batch_queue).unwrap_or(db.queue),
                workers: args
                    .batch_workers
                    .or(file.batch_workers)
                    .unwrap_or(db.workers),
            }),
            ..config
        };
        anyhow::ensure!(config.max_sessions > 0, "max_sessions must be at least 1");
        anyhow::ensure!(
            config.max_horizon_limit > 0,
            "max_horizon_limit must be at least 1"
        );
        anyhow::ensure!(
            config.max_message_bytes >= 1024,
            "max_message_bytes must be at least 1024"
        );
        anyhow::ensure!(
            !config.session_ttl.is_zero(),
            "session_ttl must be positive"
        );
        let limits = &config.connections;
        anyhow::ensure!(
            limits.max_connections > 0,
            "max_connections must be at least 1"
        );
        anyhow::ensure!(
            limits.max_streams_per_connection > 0,
            "max_streams_per_connection must be at least 1"
        );
        anyhow::ensure!(
            !limits.handshake_timeout.is_zero(),
            "handshake_timeout must be positive"
        );
        anyhow::ensure!(
            !limits.keepalive_timeout.is_zero(),
            "keepalive_timeout must be positive"
        );
        Ok(config)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn listen_addresses_may_name_a_host() {
        assert_eq!(
            socket_address("127.0.0.1:50051").unwrap(),
            "127.0.0.1:50051".parse::<SocketAddr>().unwrap()
        );
        assert!(
            socket_address("localhost:50072")
                .unwrap()
                .ip()
                .is_loopback()
        );
        assert!(socket_address("localhost").unwrap_err().contains("no port"));
        assert!(
            socket_address("localhost:http")
                .unwrap_err()
                .contains("not a number")
        );
    }

    #[test]
    fn flags_override_the_file_which_overrides_defaults() {
        let dir = std::env::temp_dir().join(format!("prac-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("prac.toml");
        std::fs::write(
            &file,
            "max_sessions = 7\nsession_ttl = \"2m\"\nlog_format = \"json\"\nlisten = \"0.0.0.0:9000\"\n",
        )
        .unwrap();
        let args = ServeArgs {
            config: Some(file.clone()),
            max_sessions: Some(9),
            ..Default::default()
        };
        let c = ServeConfig::resolve(&args).unwrap();
        assert_eq!(c.max_sessions, 9);
        assert_eq!(c.session_ttl, Duration::from_secs(120));
        assert_eq!(c.log_format, LogFormat::Json);
        assert_eq!(c.listen, "0.0.0.0:9000".parse().unwrap());
        assert_eq!(c.drain_timeout, Duration::from_secs(10));

        std::fs::write(&file, "max_sesions = 7\n").unwrap();
        let err = ServeConfig::resolve(&args).unwrap_err();
        assert!(format!("{err:#}").contains("max_sesions"), "{err:#}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
