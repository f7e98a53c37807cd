//! The connections the server accepts, held to limits so that no client, silent or hostile, can
//! hold the server's sockets, memory or accept loop:
//! - at most `max_connections` at once; at the cap a new connection is admitted by shedding the
//!   oldest one that has not yet completed its handshake and first request (as proxies shed
//!   slowloris clients), and closed at once if every connection has;
//! - a connection must complete TLS (if on) and send its first request within
//!   `handshake_timeout`, or it is closed;
//! - a connection with no call in flight for `idle_timeout` is sent GOAWAY (clients reconnect);
//! - HTTP/2 keepalive pings close connections whose peer stopped answering;
//! - at most `max_streams_per_connection` concurrent streams per connection, and a small
//!   per-stream receive window, so one stream that is not read holds at most that window;
//! - accept errors (out of file descriptors) back off instead of spinning;
//! - requests pass through [`super::intake`] (tokens from HEADERS, message sizes, buffered bytes,
//!   request timeouts) before tonic reads them.
//!
//! The gRPC service itself is tonic's; this module is the accept loop and hyper's HTTP/2
//! settings around it. Deadlines are the handlers' own (see [`super::deadline`]), so a deadline
//! is answered DEADLINE_EXCEEDED.

use std::collections::BTreeMap;
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

use super::intake::{ConnectionIntake, Intake};
use super::memory::{Charge, costs as memory_costs};

/// Limits on the connections of one listener.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Limits {
    pub(crate) max_connections: usize,
    pub(crate) max_streams_per_connection: u32,
    /// From accept to the first request (TLS handshake and HTTP/2 preface included).
    pub(crate) handshake_timeout: Duration,
    /// A connection with no call in flight this long is closed; None keeps it.
    pub(crate) idle_timeout: Option<Duration>,
    /// HTTP/2 PING interval; None sends none.
    pub(crate) keepalive_interval: Option<Duration>,
    /// A PING unanswered this long closes the connection.
    pub(crate) keepalive_timeout: Duration,
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
    pub(crate) open: AtomicU64,
    pub(crate) refused_at_cap: AtomicU64,
    pub(crate) handshake_timeouts: AtomicU64,
    pub(crate) tls_failures: AtomicU64,
    pub(crate) idle_closed: AtomicU64,
    pub(crate) accept_errors: AtomicU64,
    /// Connections closed to admit a newer one at the cap.
    pub(crate) shed: AtomicU64,
    /// Calls in flight over all connections, and the most since the memory keeper last looked.
    pub(crate) calls_in_flight: AtomicU64,
    pub(crate) calls_in_flight_peak: AtomicU64,
}

/// How long the accept loop waits for a shed connection to give back its slot.
const SHED_WAIT: Duration = Duration::from_millis(200);

/// The connections that have not yet completed their handshake and first request, oldest first:
/// at the connection cap the oldest is shed to admit a new one, so connections that send nothing
/// (or too little) cannot lock real clients out.
#[derive(Default)]
pub(super) struct Newcomers {
    waiting: Mutex<BTreeMap<u64, CancellationToken>>,
    next: AtomicU64,
}

impl Newcomers {
    fn enter(self: &Arc<Self>) -> Probation {
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let shed = CancellationToken::new();
        self.lock().insert(id, shed.clone());
        Probation {
            id,
            shed,
            newcomers: self.clone(),
        }
    }

    /// Sheds the oldest connection on probation; false if there is none.
    fn shed_oldest(&self) -> bool {
        let oldest = self.lock().pop_first();
        oldest.map(|(_, shed)| shed.cancel()).is_some()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, CancellationToken>> {
        self.waiting.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A connection that may still be shed: `shed` is cancelled when it is. Dropped (the connection
/// proved itself, or closed), it leaves the newcomers.
pub(super) struct Probation {
    id: u64,
    shed: CancellationToken,
    newcomers: Arc<Newcomers>,
}

impl Probation {
    /// Resolves if the connection is shed (never, once the probation is dropped).
    pub(super) fn shed_signal(&self) -> CancellationToken {
        self.shed.clone()
    }
}

impl Drop for Probation {
    fn drop(&mut self) {
        self.newcomers.lock().remove(&self.id);
    }
}

/// What the accept loop hands over with a connection: the slot that counts it and its probation.
pub(super) struct Admitted {
    pub(crate) permit: OwnedSemaphorePermit,
    pub(crate) probation: Probation,
}

/// Descriptors kept for bundles, logs, listeners and the metrics endpoint.
const RESERVED_DESCRIPTORS: u64 = 64;

/// Fewer connections than this serve too few clients to be worth starting.
pub(super) const MIN_WORKABLE_CONNECTIONS: usize = 16;

/// Raises the soft open-file limit to the hard limit, as most servers do (Go's runtime, nginx's
/// `worker_rlimit_nofile`, systemd services): the soft limit is often 1024 or lower by default,
/// which caps a server's connections far below what the machine allows. Returns the limits
/// (soft, hard) in force after.
pub(super) fn raise_open_file_limit() -> std::io::Result<(u64, u64)> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes one rlimit through a valid pointer.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
        return Err(std::io::Error::last_os_error());
    }
    if limit.rlim_cur < limit.rlim_max {
        let raised = libc::rlimit {
            // An unlimited hard limit is refused above the kernel's nr_open: 2^20 is its default.
            rlim_cur: if limit.rlim_max == libc::RLIM_INFINITY {
                1 << 20
            } else {
                limit.rlim_max
            },
            rlim_max: limit.rlim_max,
        };
        // SAFETY: setrlimit reads one rlimit through a valid pointer.
        if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
            limit.rlim_cur = raised.rlim_cur;
        }
    }
    Ok((limit.rlim_cur, limit.rlim_max))
}

/// The most connections an open-file limit of `soft` allows with [`RESERVED_DESCRIPTORS`] to
/// spare; `wanted` if that is lower.
pub(super) fn connection_cap(wanted: usize, soft: u64) -> usize {
    let room = soft.saturating_sub(RESERVED_DESCRIPTORS);
    wanted.min(usize::try_from(room).unwrap_or(usize::MAX))
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
/// with its slot and probation. At the cap the oldest connection still on probation is shed to
/// make room; with none, the new one is closed. Accept errors back off from 5 ms to 1 s.
pub(super) async fn accept_loop<F>(
    listener: TcpListener,
    cap: usize,
    stats: Arc<ConnectionStats>,
    shutdown: CancellationToken,
    mut serve: F,
) where
    F: FnMut(TcpStream, SocketAddr, Admitted),
{
    let permits = Arc::new(Semaphore::new(cap));
    let newcomers = Arc::new(Newcomers::default());
    let mut backoff = Duration::ZERO;
    let mut refusals = RateLimitedLog::new();
    let mut sheddings = RateLimitedLog::new();
    let mut errors = RateLimitedLog::new();
    loop {
        let accepted = tokio::select! {
            _ = shutdown.cancelled() => break,
            accepted = listener.accept() => accepted,
        };
        match accepted {
            Ok((tcp, peer)) => {
                backoff = Duration::ZERO;
                let permit = match permits.clone().try_acquire_owned() {
                    Ok(permit) => Some(permit),
                    Err(_) if newcomers.shed_oldest() => {
                        stats.shed.fetch_add(1, Ordering::Relaxed);
                        if let Some(more) = sheddings.due() {
                            tracing::info!(%peer, cap, shed_since_last_log = more, "at the connection cap: closed the oldest connection that had sent no complete request, to admit a new one");
                        }
                        tokio::time::timeout(SHED_WAIT, permits.clone().acquire_owned())
                            .await
                            .ok()
                            .and_then(Result::ok)
                    }
                    Err(_) => None,
                };
                let Some(permit) = permit else {
                    stats.refused_at_cap.fetch_add(1, Ordering::Relaxed);
                    if let Some(more) = refusals.due() {
                        tracing::warn!(%peer, cap, refused_since_last_log = more, "connection refused: the server holds its maximum of connections (--max-connections), all of them past their first request");
                    }
                    drop(tcp);
                    continue;
                };
                let _ = tcp.set_nodelay(true);
                let probation = newcomers.enter();
                serve(tcp, peer, Admitted { permit, probation });
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
    intake: Arc<Intake>,
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
        |tcp, _peer, admitted| {
            let Admitted { permit, probation } = admitted;
            // Charged against the memory budget from accept to close; none left, closed now.
            let memory = match intake.budget() {
                Some(budget) => {
                    let bytes = memory_costs::CONNECTION
                        + if tls.is_some() {
                            memory_costs::TLS_EXTRA
                        } else {
                            0
                        };
                    match budget.admit_connection(bytes) {
                        Some(charge) => Some(charge),
                        None => return drop(tcp),
                    }
                }
                None => None,
            };
            let connection = Connection {
                routes: routes.clone(),
                limits,
                stats: stats.clone(),
                draining: draining.clone(),
                shed: probation.shed_signal(),
                intake: intake.clone(),
                connection_intake: Arc::new(ConnectionIntake::new(Some(probation))),
            };
            let tls = tls.clone();
            tokio::spawn(async move {
                let _permit = permit;
                let _memory = memory;
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
    /// Cancelled if the connection is shed at the cap before its first complete request.
    shed: CancellationToken,
    intake: Arc<Intake>,
    connection_intake: Arc<ConnectionIntake>,
}

impl Connection {
    async fn run(self, tcp: TcpStream, tls: Option<TlsAcceptor>) {
        let accepted = Instant::now();
        let Some(tls) = tls else {
            return self.serve(tcp, accepted).await;
        };
        let handshake = tokio::select! {
            handshake = tokio::time::timeout(self.limits.handshake_timeout, tls.accept(tcp)) => handshake,
            _ = self.shed.cancelled() => return,
        };
        match handshake {
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
        let activity = Arc::new(Activity::new(accepted, self.stats.clone()));
        let service = Tracked {
            routes: self.routes.clone(),
            activity: activity.clone(),
            intake: self.intake.clone(),
            connection_intake: self.connection_intake.clone(),
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
        let goaway = self.connection_intake.share.goaway();
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
                // Shed at the cap before its first complete request: closed at once.
                _ = self.shed.cancelled() => return,
                // Holding many never-started calls while memory is short: GOAWAY, and the
                // calls it has started go on.
                _ = goaway.cancelled(), if !closing => {
                    connection.as_mut().graceful_shutdown();
                    closing = true;
                }
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
    stats: Arc<ConnectionStats>,
}

impl Activity {
    fn new(accepted: Instant, stats: Arc<ConnectionStats>) -> Activity {
        Activity {
            in_flight: AtomicU64::new(0),
            any_request: AtomicBool::new(false),
            since: Mutex::new(accepted),
            changed: tokio::sync::Notify::new(),
            stats,
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
        let calls = self.stats.calls_in_flight.fetch_add(1, Ordering::Relaxed) + 1;
        self.stats
            .calls_in_flight_peak
            .fetch_max(calls, Ordering::Relaxed);
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
        self.0.stats.calls_in_flight.fetch_sub(1, Ordering::Relaxed);
    }
}

/// tonic's routes behind the intake, counting calls in flight on their connection.
#[derive(Clone)]
struct Tracked {
    routes: Routes,
    activity: Arc<Activity>,
    intake: Arc<Intake>,
    connection_intake: Arc<ConnectionIntake>,
}

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

impl hyper::service::Service<http::Request<Incoming>> for Tracked {
    type Response = http::Response<Body>;
    type Error = std::convert::Infallible;
    type Future = BoxFuture<Result<Self::Response, Self::Error>>;

    fn call(&self, request: http::Request<Incoming>) -> Self::Future {
        // Called in the connection's order of streams, before any handler runs.
        let (mut request, memory) = match self.intake.admit(&self.connection_intake, request) {
            Ok(admitted) => admitted,
            // Refused from its headers: answered now, its body never read.
            Err(status) => return Box::pin(std::future::ready(Ok(status.into_http()))),
        };
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
                    _memory: memory,
                })
            }))
        })
    }
}

/// A response body that keeps its call counted until it ends.
struct TrackedBody {
    inner: Body,
    _in_flight: InFlight,
    /// The call's charge against the memory budget.
    _memory: Option<Charge>,
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
