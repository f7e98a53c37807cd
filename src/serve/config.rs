//! `prac serve` settings: command-line flags over an optional TOML file over defaults.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use serde::Deserialize;

use super::batch::BatchConfig;
use super::intake::{RequestLimits, SMALL_MESSAGE};
use super::transport::Limits;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    Text,
    Json,
}

/// Declares every setting once: its flag, its TOML key (the same name), its parser (shared by
/// both), its default and its help, which shows the default.
macro_rules! settings {
    ($(
        $name:ident: $ty:ty = $default:literal, $parse:expr, $help:literal;
    )*) => {
        /// Flags of `prac serve`; each overrides the same key of the `--config` file.
        #[derive(Clone, Debug, Default, clap::Args)]
        pub struct ServeArgs {
            /// TOML file with any of the keys below (snake_case, e.g. max_sessions = 64).
            #[arg(long)]
            pub(crate) config: Option<PathBuf>,
            /// Refuse to start if any bundle fails to load (default: skip it with an error).
            #[arg(long)]
            pub(crate) strict: bool,
            $(
                #[doc = $help]
                #[arg(long, value_parser = $parse, help = concat!($help, " [default: ", $default, "]"))]
                pub(crate) $name: Option<$ty>,
            )*
        }

        /// Every setting resolved: flag, else file, else default ("none" for no value).
        #[derive(Clone, Debug, PartialEq)]
        struct Settled {
            strict: bool,
            $($name: Option<$ty>,)*
        }

        /// The TOML keys, for the unknown-key error.
        const KEYS: &[&str] = &["strict", $(stringify!($name),)*];

        impl ServeArgs {
            fn settle(&self, file: &toml::Table) -> anyhow::Result<Settled> {
                let strict = match file.get("strict") {
                    None => false,
                    Some(toml::Value::Boolean(b)) => *b,
                    Some(other) => anyhow::bail!("strict = {other} is not true or false"),
                };
                Ok(Settled {
                    strict: self.strict || strict,
                    $($name: match &self.$name {
                        Some(value) => Some(value.clone()),
                        None => match file.get(stringify!($name)) {
                            Some(value) => Some(from_file(stringify!($name), value, $parse)?),
                            None => parse_default($default, $parse),
                        },
                    },)*
                })
            }
        }
    };
}

settings! {
    listen: SocketAddr = "127.0.0.1:50051", socket_address,
        "Address to listen on, e.g. 127.0.0.1:50051, [::1]:50051 or localhost:50051; port \
        0 picks a free port.";
    bundles: PathBuf = "bundles", path,
        "Directory of NAME.safetensors bundles, relative to the working directory.";
    max_sessions: usize = "1024", number::<usize>,
        "Most sessions open at once.";
    session_ttl: Duration = "5m", duration,
        "A session unused for this long is evicted, e.g. \"5m\".";
    max_message_bytes: usize = "none", number::<usize>,
        "Largest gRPC message accepted or sent, in bytes; none (the default) accepts the \
        largest request the loaded bundles allow (an OpenSession resuming a plan of \
        --max-horizon-limit actions, at least 16 KiB; it follows reloads) and sends up to \
        4 MiB.";
    request_timeout: Duration = "10s", duration,
        "A unary request must arrive whole, and each message of a streamed one must \
        complete once begun, within this (or the call's deadline if sooner); past it the \
        call is answered DEADLINE_EXCEEDED.";
    max_request_bytes_per_connection: usize = "1048576", number::<usize>,
        "Declared bytes of unfinished request messages one connection may hold; a call \
        past it is answered RESOURCE_EXHAUSTED.";
    max_request_bytes_total: usize = "67108864", number::<usize>,
        "Declared bytes of unfinished request messages all connections together may hold; \
        past it new calls are answered RESOURCE_EXHAUSTED.";
    drain_timeout: Duration = "10s", duration,
        "On SIGINT/SIGTERM, how long to wait for in-flight work before exiting.";
    log_format: LogFormat = "text", log_format,
        "Log format on stderr: text or json.";
    max_horizon_limit: usize = "256", number::<usize>,
        "Largest max_horizon, grow k or fixed n a session may ask for.";
    batch_max: usize = "64", number::<usize>,
        "Most steps replanned together across sessions; 0 turns batching off (each step \
        is replanned in its request handler).";
    batch_window: Duration = "0s", duration,
        "How long a batch worker waits for more steps after the first, e.g. \"200us\"; 0 \
        takes only what is already queued, adding no delay.";
    batch_queue: usize = "4096", number::<usize>,
        "Steps that may wait for a batch worker; more are refused with \
        RESOURCE_EXHAUSTED.";
    batch_workers: usize = "none", number::<usize>,
        "Batch worker threads; none (the default) runs one per core the server may use (its \
        CPU affinity, e.g. taskset or a cpuset, and its cgroup CPU quota).";
    auth_tokens: PathBuf = "none", path,
        "File of bearer tokens, one per line: every prac.v1 call must carry \
        `authorization: Bearer TOKEN`, and a session belongs to the token that opened \
        it; none turns auth off.";
    tls_cert: PathBuf = "none", path,
        "PEM certificate chain: serve TLS (with --tls-key); none serves plaintext.";
    tls_key: PathBuf = "none", path,
        "PEM private key of --tls-cert.";
    metrics_listen: SocketAddr = "none", socket_address,
        "Serve Prometheus metrics over HTTP at ADDR/metrics, e.g. 127.0.0.1:9090; port 0 \
        picks a free port (printed as `metrics on ADDR`); none serves no metrics.";
    health_listen: SocketAddr = "none", socket_address,
        "A second, plaintext port at ADDR that answers only grpc.health.v1 (no token, no \
        other service), for probes that speak neither TLS nor tokens, such as the \
        kubelet's; e.g. 0.0.0.0:8081 (printed as `health on ADDR`); none serves none.";
    max_connections: usize = "1024", number::<usize>,
        "Most client connections open at once; more are closed when accepted (lowered to \
        fit the open-file limit).";
    max_streams_per_connection: u32 = "256", number::<u32>,
        "Most concurrent streams (calls) on one connection (HTTP/2 \
        SETTINGS_MAX_CONCURRENT_STREAMS).";
    handshake_timeout: Duration = "10s", duration,
        "A connection must finish its TLS handshake and send its first request within \
        this, or it is closed.";
    idle_timeout: Duration = "10m", duration,
        "A connection with no call in flight for this long is closed with GOAWAY (clients \
        reconnect by themselves); 0s keeps idle connections.";
    keepalive_interval: Duration = "30s", duration,
        "Interval of HTTP/2 PINGs to each client; 0s sends none.";
    keepalive_timeout: Duration = "20s", duration,
        "A PING unanswered for this long closes the connection.";
    max_memory: u64 = "none", memory_size,
        "Memory the server may use in all, e.g. 256Mi (binary units; KB, MB, GB are \
        decimal); none (the default) takes the cgroup's limit (a container's memory limit), \
        else the machine's memory. Connections, calls, watchers, sessions and request bytes \
        are held within it (docs/operations.md, \"Memory budget\").";
}

/// A setting's default: "none" for no value; the others parse (a unit test checks them all).
fn parse_default<T>(text: &str, parse: impl Fn(&str) -> Result<T, String>) -> Option<T> {
    (text != "none").then(|| parse(text).unwrap_or_else(|e| panic!("default {text:?}: {e}")))
}

/// A file value, read as the flag would read its text.
fn from_file<T>(
    key: &str,
    value: &toml::Value,
    parse: impl Fn(&str) -> Result<T, String>,
) -> anyhow::Result<T> {
    let text = match value {
        toml::Value::String(s) => s.clone(),
        toml::Value::Integer(n) => n.to_string(),
        toml::Value::Float(x) => x.to_string(),
        toml::Value::Boolean(b) => b.to_string(),
        other => anyhow::bail!("{key} = {other} is not a single value"),
    };
    parse(&text).map_err(|e| anyhow::anyhow!("{key} = {value}: {e}"))
}

fn number<T: std::str::FromStr>(text: &str) -> Result<T, String>
where
    T::Err: std::fmt::Display,
{
    text.parse()
        .map_err(|e| format!("{text:?} is not a whole number: {e}"))
}

/// A duration such as "30s" or "5m", as flags and the config file write it.
pub fn duration(text: &str) -> Result<Duration, String> {
    humantime::parse_duration(text)
        .map_err(|e| format!("{text:?} is not a duration such as \"30s\" or \"5m\": {e}"))
}

fn memory_size(text: &str) -> Result<u64, String> {
    super::memory::parse_size(text)
}

fn path(text: &str) -> Result<PathBuf, String> {
    Ok(PathBuf::from(text))
}

fn log_format(text: &str) -> Result<LogFormat, String> {
    <LogFormat as clap::ValueEnum>::from_str(text, true)
        .map_err(|_| format!("{text:?} is not a log format; expected text or json"))
}

/// The settings in force.
#[derive(Clone, Debug, PartialEq)]
pub struct ServeConfig {
    pub(crate) listen: SocketAddr,
    pub(crate) bundles: PathBuf,
    pub(crate) max_sessions: usize,
    pub(crate) session_ttl: Duration,
    pub(crate) drain_timeout: Duration,
    pub log_format: LogFormat,
    pub(crate) strict: bool,
    pub(crate) max_horizon_limit: usize,
    /// Cross-session batching; None when off.
    pub(crate) batch: Option<BatchConfig>,
    pub(crate) auth_tokens: Option<PathBuf>,
    /// Certificate chain and key (PEM) when serving TLS.
    pub(crate) tls: Option<(PathBuf, PathBuf)>,
    /// Where to serve Prometheus metrics; None when off.
    pub(crate) metrics_listen: Option<SocketAddr>,
    /// Where to serve plaintext grpc.health.v1 alone; None when off.
    pub(crate) health_listen: Option<SocketAddr>,
    /// Limits on client connections (the metrics endpoint's too).
    pub(crate) connections: Limits,
    /// Limits on requests in transit.
    pub(crate) requests: RequestLimits,
    /// `--max-memory`; None follows the cgroup's limit, else the machine's memory.
    pub(crate) max_memory: Option<u64>,
}

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig::resolve(&ServeArgs::default()).expect("the defaults are valid")
    }
}

/// An address to listen on: IP:PORT, [IPv6]:PORT, or HOST:PORT resolved now (its first address).
pub fn socket_address(text: &str) -> Result<SocketAddr, String> {
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

/// Cores this process may run on: one batch worker each, so that a server pinned to one core
/// replans its sessions in one batch instead of splitting them between workers that take turns.
fn usable_cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// A duration where 0 means "never".
fn nonzero(d: Duration) -> Option<Duration> {
    (!d.is_zero()).then_some(d)
}

impl ServeConfig {
    /// Flags over the `--config` file over defaults, validated.
    pub fn resolve(args: &ServeArgs) -> anyhow::Result<ServeConfig> {
        let file = match &args.config {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("cannot read config {}", path.display()))?;
                let table = toml::from_str::<toml::Table>(&text)
                    .with_context(|| format!("invalid config {}", path.display()))?;
                if let Some(unknown) = table.keys().find(|k| !KEYS.contains(&k.as_str())) {
                    anyhow::bail!(
                        "invalid config {}: unknown key {unknown}; known keys: {}",
                        path.display(),
                        KEYS.join(", ")
                    );
                }
                table
            }
            None => toml::Table::new(),
        };
        let s = args.settle(&file).with_context(|| match &args.config {
            Some(path) => format!("invalid config {}", path.display()),
            None => "invalid settings".to_string(),
        })?;
        let has = "every setting but the optional ones has a default";
        let max_batch = s.batch_max.expect(has);
        let config = ServeConfig {
            listen: s.listen.expect(has),
            bundles: s.bundles.expect(has),
            max_sessions: s.max_sessions.expect(has),
            session_ttl: s.session_ttl.expect(has),
            drain_timeout: s.drain_timeout.expect(has),
            log_format: s.log_format.expect(has),
            strict: s.strict,
            max_horizon_limit: s.max_horizon_limit.expect(has),
            batch: (max_batch > 0).then_some(BatchConfig {
                max_batch,
                window: s.batch_window.expect(has),
                queue: s.batch_queue.expect(has),
                workers: s.batch_workers.unwrap_or_else(usable_cores),
            }),
            auth_tokens: s.auth_tokens,
            tls: match (s.tls_cert, s.tls_key) {
                (Some(cert), Some(key)) => Some((cert, key)),
                (None, None) => None,
                _ => anyhow::bail!("tls_cert and tls_key go together"),
            },
            metrics_listen: s.metrics_listen,
            health_listen: s.health_listen,
            connections: Limits {
                max_connections: s.max_connections.expect(has),
                max_streams_per_connection: s.max_streams_per_connection.expect(has),
                handshake_timeout: s.handshake_timeout.expect(has),
                idle_timeout: s.idle_timeout.and_then(nonzero),
                keepalive_interval: s.keepalive_interval.and_then(nonzero),
                keepalive_timeout: s.keepalive_timeout.expect(has),
            },
            requests: RequestLimits {
                request_timeout: s.request_timeout.expect(has),
                bytes_per_connection: s.max_request_bytes_per_connection.expect(has),
                bytes_total: s.max_request_bytes_total.expect(has),
                max_message_bytes: s.max_message_bytes,
            },
            max_memory: s.max_memory,
        };
        anyhow::ensure!(config.max_sessions > 0, "max_sessions must be at least 1");
        anyhow::ensure!(
            config.max_horizon_limit > 0,
            "max_horizon_limit must be at least 1"
        );
        if let Some(health) = config.health_listen {
            anyhow::ensure!(
                health.port() == 0 || health.port() != config.listen.port(),
                "health_listen {health} is the gRPC port of listen {}: the health port must be \
                 its own (probes reach it in plaintext without a token)",
                config.listen
            );
        }
        let requests = &config.requests;
        anyhow::ensure!(
            requests.max_message_bytes.is_none_or(|n| n >= 1024),
            "max_message_bytes must be at least 1024"
        );
        anyhow::ensure!(
            requests
                .max_message_bytes
                .is_none_or(|n| n + 5 <= requests.bytes_per_connection),
            "max_message_bytes must fit in max_request_bytes_per_connection (with its 5-byte \
             prefix), or no message that large could be taken in; raise the budget too"
        );
        anyhow::ensure!(
            !requests.request_timeout.is_zero(),
            "request_timeout must be positive"
        );
        anyhow::ensure!(
            requests.bytes_per_connection >= SMALL_MESSAGE
                && requests.bytes_total >= requests.bytes_per_connection,
            "max_request_bytes_per_connection must be at least {SMALL_MESSAGE}, and \
             max_request_bytes_total at least max_request_bytes_per_connection"
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
    fn the_help_shows_every_default() {
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            args: ServeArgs,
        }
        let help = <Cli as clap::CommandFactory>::command()
            .render_long_help()
            .to_string();
        for shown in [
            "[default: 127.0.0.1:50051]",
            "[default: bundles]",
            "[default: 5m]",
            "[default: none]",
            "[default: 1048576]",
        ] {
            assert!(help.contains(shown), "{shown} missing from:\n{help}");
        }
    }

    /// The defaults declared with the settings, and so shown by --help, are the documented ones.
    #[test]
    fn the_declared_defaults_are_the_documented_ones() {
        let c = ServeConfig::default();
        assert_eq!(c.listen, "127.0.0.1:50051".parse().unwrap());
        assert_eq!(c.bundles, PathBuf::from("bundles"));
        assert_eq!(c.max_sessions, 1024);
        assert_eq!(c.session_ttl, Duration::from_secs(300));
        assert_eq!(c.requests.max_message_bytes, None);
        assert_eq!(c.requests.request_timeout, Duration::from_secs(10));
        assert_eq!(c.requests.bytes_per_connection, 1 << 20);
        assert_eq!(c.requests.bytes_total, 64 << 20);
        assert_eq!(c.drain_timeout, Duration::from_secs(10));
        assert_eq!(c.log_format, LogFormat::Text);
        assert!(!c.strict);
        assert_eq!(c.max_horizon_limit, 256);
        assert_eq!(
            c.batch,
            Some(BatchConfig {
                max_batch: 64,
                window: Duration::ZERO,
                queue: 4096,
                workers: usable_cores(),
            })
        );
        assert_eq!((c.auth_tokens, c.tls, c.metrics_listen), (None, None, None));
        assert_eq!((c.health_listen, c.max_memory), (None, None));
        assert_eq!(
            c.connections,
            Limits {
                max_connections: 1024,
                max_streams_per_connection: 256,
                handshake_timeout: Duration::from_secs(10),
                idle_timeout: Some(Duration::from_secs(600)),
                keepalive_interval: Some(Duration::from_secs(30)),
                keepalive_timeout: Duration::from_secs(20),
            }
        );
    }

    #[test]
    fn file_values_are_read_as_their_flags_and_bad_ones_named() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("prac.toml");
        let resolve = |text: &str| {
            std::fs::write(&file, text).unwrap();
            ServeConfig::resolve(&ServeArgs {
                config: Some(file.clone()),
                ..Default::default()
            })
        };
        let c =
            resolve("batch_max = 0\nidle_timeout = \"0s\"\nstrict = true\nmax_memory = \"96Mi\"\n")
                .unwrap();
        assert_eq!(c.max_memory, Some(96 << 20));
        assert_eq!(c.batch, None, "batch_max = 0 turns batching off");
        assert_eq!(
            c.connections.idle_timeout, None,
            "0s keeps idle connections"
        );
        assert!(c.strict);
        for (text, named) in [
            ("session_ttl = \"soon\"", "session_ttl"),
            ("max_sessions = \"many\"", "max_sessions"),
            ("log_format = \"xml\"", "log_format"),
            ("strict = 1", "strict"),
            ("max_memory = 0", "0 bytes"),
            ("max_memory = \"-5Mi\"", "not a memory size"),
            ("max_memory = \"lots\"", "max_memory"),
            ("tls_cert = \"cert.pem\"", "tls_key go together"),
            (
                "listen = \"0.0.0.0:50051\"\nhealth_listen = \"0.0.0.0:50051\"",
                "health_listen 0.0.0.0:50051 is the gRPC port",
            ),
        ] {
            let err = format!("{:#}", resolve(text).unwrap_err());
            assert!(err.contains(named), "{text}: {err}");
        }
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
