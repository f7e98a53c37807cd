//! The connections the server accepts, held to limits so that no client, silent or hostile, can
//! hold the server's sockets, memory or accept loop:
//! - at most `max_connections` at once; more are closed as soon as they are accepted;
//! - a connection must complete TLS (if on) and send its first request within
//!   `handshake_timeout`, or it is closed;
//! - a connection with no call in flight for `idle_timeout` is sent GOAWAY (clients reconnect);
//! - HTTP/2 keepalive pings close connections whose peer stopped answering;
//! - at most `max_streams_per_connection` concurrent streams per connection, and a small
//!   per-stream receive window, so one stream that is not read holds at most that window;
//! - accept errors (out of file descriptors) back off instead of spinning.
//!
//! The gRPC service itself is tonic's; this module is the accept loop and hyper's HTTP/2
//! settings around it. Deadlines are the handlers' own (see [`super::deadline`]), so a deadline
//! is answered DEADLINE_EXCEEDED.

use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use http_body::{Body as HttpBody, Frame, SizeHint};
use hyper::body::Incoming;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, watch};
use tokio_rustls::TlsAcceptor;
use tokio_util::sync::CancellationToken;
use tonic::body::Body;
use tonic::codegen::Service;
use tonic::service::Routes;

/// Limits on the connections of one listener.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limits {
    pub max_connections: usize,
    pub max_streams_per_connection: u32,
    /// From accept to the first request (TLS handshake and HTTP/2 preface included).
    pub handshake_timeout: Duration,
    /// A connection with no call in flight this long is closed; None keeps it.
    pub idle_timeout: Option<Duration>,
    /// HTTP/2 PING interval; None sends none.
    pub keepalive_interval: Option<Duration>,
    /// A PING unanswered this long closes the connection.
    pub keepalive_timeout: Duration,
}

/// Receive window of one stream. A StepStream whose client stops reading its responses stalls
/// once this much of its requests is buffered: about 300 Hopper steps.
pub(super) const STREAM_WINDOW: u32 = 32 * 1024;

/// The connection's receive window: every stream's window at once, times 8. h2 closes a
/// connection whose buffered small DATA frames cost more framing than half this window; at 8x
/// the streams' data, a stalled stream of requests of 40 bytes or more (every prac request
/// carries a 32-character session id) cannot exhaust it, so it stalls alone.
fn connection_window(limits: &Limits) -> u32 {
    (u64::from(STREAM_WINDOW) * u64::from(limits.max_streams_per_connection) * 8)
        .clamp(1 << 20, (1 << 31) - 1) as u32
}

/// Largest request header block: gRPC metadata is small; this bounds what a client can make the
/// server hold before a call starts.
const MAX_HEADER_LIST_BYTES: u32 = 16 * 1024;

/// Connection counts, for the metrics and logs.
#[derive(Debug, Default)]
pub(super) struct ConnectionStats {
    pub open: AtomicU64,
    pub refused_at_cap: AtomicU64,
    pub handshake_timeouts: AtomicU64,
    pub tls_failures: AtomicU64,
    pub idle_closed: AtomicU64,
    pub accept_errors: AtomicU64,
}

/// The most connections the process's file-descriptor limit allows with room to spare for
/// bundles, logs and the metrics listener; `wanted` if that is lower.
pub(super) fn connection_cap(wanted: usize) -> usize {
    const RESERVE: u64 = 64;
    let mut limit = libc_rlimit_nofile().unwrap_or(u64::MAX);
    limit = limit.saturating_sub(RESERVE).max(1);
    wanted.min(usize::try_from(limit).unwrap_or(usize::MAX))
}

fn libc_rlimit_nofile() -> Option<u64> {
    // /proc/self/limits: "Max open files   1024   1048576   files".
    let text = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = text.lines().find(|l| l.starts_with("Max open files"))?;
    let soft = line.split_whitespace().nth(3)?;
    if soft == "unlimited" {
        return None;
    }
    soft.parse().ok()
}

/// Logs at most once a second, with how many events it stood for.
struct RateLimitedLog {
    last: Option<Instant>,
    suppressed: u64,
}

impl RateLimitedLog {
    fn new() -> RateLimitedLog {
        RateLimitedLog {
            last: None,
            suppressed: 0,
        }
    }

    /// Whether to log now, and how many events went unlogged before this one.
    fn due(&mut self) -> Option<u64> {
        let now = Instant::now();
        if self
            .last
            .is_some_and(|t| now.duration_since(t) < Duration::from_secs(1))
        {
            self.suppressed += 1;
            return None;
        }
        self.last = Some(now);
        Some(std::mem::take(&mut self.suppressed))
    }
}

/// Accepts connections until `shutdown`, at most `cap` open at once, handing each to `serve`
/// with the permit that counts it. Accept errors back off from 5 ms to 1 s.
pub(super) async fn accept_loop<F>(
    listener: TcpListener,
    cap: usize,
    stats: Arc<ConnectionStats>,
    shutdown: CancellationToken,
    mut serve: F,
) where
    F: FnMut(TcpStream, SocketAddr, OwnedSemaphorePermit),
{
    let permits = Arc::new(Semaphore::new(cap));
    let mut backoff = Duration::ZERO;
    let mut refusals = RateLimitedLog::new();
    let mut errors = RateLimitedLog::new();
    loop {
        let accepted = tokio::select! {
            _ = shutdown.cancelled() => break,
            accepted = listener.accept() => accepted,
        };
        match accepted {
            Ok((tcp, peer)) => {
                backoff = Duration::ZERO;
                let Ok(permit) = permits.clone().try_acquire_owned() else {
                    stats.refused_at_cap.fetch_add(1, Ordering::Relaxed);
                    if let Some(more) = refusals.due() {
                        tracing::warn!(%peer, cap, refused_since_last_log = more, "connection refused: the server holds its maximum of connections (--max-connections)");
                    }
                    drop(tcp);
                    continue;
                };
                let _ = tcp.set_nodelay(true);
                serve(tcp, peer, permit);
            }
            Err(e) => {
                stats.accept_errors.fetch_add(1, Ordering::Relaxed);
                backoff = (backoff * 2).clamp(Duration::from_millis(5), Duration::from_secs(1));
                if let Some(more) = errors.due() {
                    tracing::warn!(error = %e, retry_in = ?backoff, errors_since_last_log = more, "accept failed (out of file descriptors?); backing off");
                }
                tokio::select! {
                    _ = shutdown.cancelled() => break,
                    _ = tokio::time::sleep(backoff) => {}
                }
            }
        }
    }
}

/// Serves gRPC on `listener` until `shutdown`, then closes every connection gracefully (GOAWAY;
/// calls in flight finish) and returns when all are closed.
pub(super) async fn serve_grpc(
    listener: TcpListener,
    tls: Option<TlsAcceptor>,
    routes: Routes,
    limits: Limits,
    stats: Arc<ConnectionStats>,
    shutdown: CancellationToken,
) {
    let (drain, draining) = watch::channel(());
    let routes = routes.prepare();
    let cap = limits.max_connections;
    accept_loop(
        listener,
        cap,
        stats.clone(),
        shutdown,
        |tcp, _peer, permit| {
            let connection = Connection {
                routes: routes.clone(),
                limits,
                stats: stats.clone(),
                draining: draining.clone(),
            };
            let tls = tls.clone();
            tokio::spawn(async move {
                let _permit = permit;
                let stats = connection.stats.clone();
                stats.open.fetch_add(1, Ordering::Relaxed);
                connection.run(tcp, tls).await;
                stats.open.fetch_sub(1, Ordering::Relaxed);
            });
        },
    )
    .await;
    // The listener is closed: connections are told to finish, and are waited for.
    let _ = drain.send(());
    drop(draining);
    drain.closed().await;
}

struct Connection {
    routes: Routes,
    limits: Limits,
    stats: Arc<ConnectionStats>,
    draining: watch::Receiver<()>,
}

impl Connection {
    async fn run(self, tcp: TcpStream, tls: Option<TlsAcceptor>) {
        let accepted = Instant::now();
        let Some(tls) = tls else {
            return self.serve(tcp, accepted).await;
        };
        match tokio::time::timeout(self.limits.handshake_timeout, tls.accept(tcp)).await {
            Ok(Ok(stream)) => self.serve(stream, accepted).await,
            Ok(Err(e)) => {
                self.stats.tls_failures.fetch_add(1, Ordering::Relaxed);
                tracing::debug!(error = %e, "TLS handshake failed");
            }
            Err(_) => {
                self.stats
                    .handshake_timeouts
                    .fetch_add(1, Ordering::Relaxed);
                tracing::debug!("TLS handshake timed out");
            }
        }
    }

    async fn serve<I>(mut self, io: I, accepted: Instant)
    where
        I: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    {
        let activity = Arc::new(Activity::new(accepted));
        let service = Tracked {
            routes: self.routes.clone(),
            activity: activity.clone(),
        };
        let mut builder = hyper::server::conn::http2::Builder::new(TokioExecutor::new());
        builder
            .timer(TokioTimer::new())
            .max_concurrent_streams(self.limits.max_streams_per_connection)
            .initial_stream_window_size(STREAM_WINDOW)
            .initial_connection_window_size(connection_window(&self.limits))
            .max_header_list_size(MAX_HEADER_LIST_BYTES)
            .keep_alive_interval(self.limits.keepalive_interval)
            .keep_alive_timeout(self.limits.keepalive_timeout);
        let connection = builder.serve_connection(TokioIo::new(io), service);
        tokio::pin!(connection);
        let mut closing = false;
        loop {
            let wake = activity.wake_at(&self.limits);
            tokio::select! {
                result = connection.as_mut() => {
                    if let Err(e) = result {
                        tracing::debug!(error = %e, "connection ended with an error");
                    }
                    return;
                }
                _ = activity.changed.notified() => continue,
                changed = self.draining.changed(), if !closing => {
                    // Shutdown (or the server gone): GOAWAY, calls in flight finish.
                    let _ = changed;
                    connection.as_mut().graceful_shutdown();
                    closing = true;
                }
                _ = tokio::time::sleep_until(wake.into()) => {
                    if !activity.idle_past(&self.limits) {
                        continue;
                    }
                    if closing {
                        // Told to go and still holding the socket with nothing in flight.
                        return;
                    }
                    let counter = if activity.any_request() {
                        &self.stats.idle_closed
                    } else {
                        &self.stats.handshake_timeouts
                    };
                    counter.fetch_add(1, Ordering::Relaxed);
                    connection.as_mut().graceful_shutdown();
                    closing = true;
                    activity.touch();
                }
            }
        }
    }
}

/// Calls in flight on one connection and when that last changed.
struct Activity {
    in_flight: AtomicU64,
    any_request: AtomicBool,
    since: Mutex<Instant>,
    /// Wakes the connection's loop to re-arm its timer when a call starts or ends.
    changed: tokio::sync::Notify,
}

impl Activity {
    fn new(accepted: Instant) -> Activity {
        Activity {
            in_flight: AtomicU64::new(0),
            any_request: AtomicBool::new(false),
            since: Mutex::new(accepted),
            changed: tokio::sync::Notify::new(),
        }
    }

    fn touch(&self) {
        *self.since.lock().unwrap_or_else(|p| p.into_inner()) = Instant::now();
        self.changed.notify_one();
    }

    fn any_request(&self) -> bool {
        self.any_request.load(Ordering::SeqCst)
    }

    fn started(self: &Arc<Self>) -> InFlight {
        self.any_request.store(true, Ordering::SeqCst);
        self.in_flight.fetch_add(1, Ordering::SeqCst);
        self.touch();
        InFlight(self.clone())
    }

    /// How long this connection may stay without a call: until its first request, the handshake
    /// timeout; after, the idle timeout (none: a day, re-checked).
    fn allowance(&self, limits: &Limits) -> Duration {
        if self.any_request() {
            limits
                .idle_timeout
                .unwrap_or(Duration::from_secs(24 * 3600))
        } else {
            limits.handshake_timeout
        }
    }

    fn wake_at(&self, limits: &Limits) -> Instant {
        if self.in_flight.load(Ordering::SeqCst) > 0 {
            // A call in flight: look again a whole allowance later.
            return Instant::now() + self.allowance(limits);
        }
        *self.since.lock().unwrap_or_else(|p| p.into_inner()) + self.allowance(limits)
    }

    fn idle_past(&self, limits: &Limits) -> bool {
        if self.in_flight.load(Ordering::SeqCst) > 0 {
            return false;
        }
        if self.any_request() && limits.idle_timeout.is_none() {
            return false;
        }
        let since = *self.since.lock().unwrap_or_else(|p| p.into_inner());
        since.elapsed() >= self.allowance(limits)
    }
}

/// A call in flight, from its request until its response body ends or is dropped.
struct InFlight(Arc<Activity>);

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.touch();
        self.0.in_flight.fetch_sub(1, Ordering::SeqCst);
    }
}

/// tonic's routes, counting calls in flight on their connection.
#[derive(Clone)]
struct Tracked {
    routes: Routes,
    activity: Arc<Activity>,
}

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

impl hyper::service::Service<http::Request<Incoming>> for Tracked {
    type Response = http::Response<Body>;
    type Error = std::convert::Infallible;
    type Future = BoxFuture<Result<Self::Response, Self::Error>>;

    fn call(&self, mut request: http::Request<Incoming>) -> Self::Future {
        // Called in the connection's order of streams, before any handler runs.
        request
            .extensions_mut()
            .insert(super::arrival::Arrival::next());
        let in_flight = self.activity.started();
        let mut routes = self.routes.clone();
        Box::pin(async move {
            let response = routes.call(request.map(Body::new)).await?;
            Ok(response.map(|body| {
                Body::new(TrackedBody {
                    inner: body,
                    _in_flight: in_flight,
                })
            }))
        })
    }
}

/// A response body that keeps its call counted until it ends.
struct TrackedBody {
    inner: Body,
    _in_flight: InFlight,
}

impl HttpBody for TrackedBody {
    type Data = bytes::Bytes;
    type Error = tonic::Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// A TLS acceptor for HTTP/2 from a PEM certificate chain and key (rustls with ring).
pub(super) fn tls_acceptor(cert_pem: &[u8], key_pem: &[u8]) -> anyhow::Result<TlsAcceptor> {
    use anyhow::Context as _;
    use tokio_rustls::rustls;
    use tokio_rustls::rustls::pki_types::pem::PemObject;
    use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let certs = CertificateDer::pem_slice_iter(cert_pem)
        .collect::<Result<Vec<_>, _>>()
        .context("the TLS certificate is not valid PEM")?;
    anyhow::ensure!(
        !certs.is_empty(),
        "the TLS certificate file holds no certificate"
    );
    let key = PrivateKeyDer::from_pem_slice(key_pem)
        .context("the TLS key is not a valid PEM private key")?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .context("TLS protocol versions")?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .context("the TLS certificate and key do not make a valid pair")?;
    config.alpn_protocols = vec![b"h2".to_vec()];
    Ok(TlsAcceptor::from(Arc::new(config)))
}
