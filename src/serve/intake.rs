//! Requests as they come in, before tonic reads them. tonic reads a unary request whole before its
//! handler runs, and reserves a message's declared length as soon as its 5-byte prefix arrives,
//! so without this layer a client that declares large messages and never finishes them makes the
//! server hold them (and re-open the HTTP/2 windows) for as long as the connection lives. Here:
//! - the bearer token of a prac.v1 call is checked from its HEADERS; a call without a valid one is
//!   answered UNAUTHENTICATED before any of its body is read;
//! - a message may declare at most the size the loaded bundles can need (the largest valid
//!   request is an OpenSession resuming a plan of `--max-horizon-limit` actions), or
//!   `--max-message-bytes` when set; health and reflection requests at most [`SMALL_MESSAGE`];
//!   a larger one is answered OUT_OF_RANGE, as tonic answers a message over its limit;
//! - the declared bytes of unfinished messages are held to a budget per connection and one for
//!   the whole server (Envoy's per-connection buffer limit and overload manager do the same): a
//!   call that would pass either is answered RESOURCE_EXHAUSTED, and so is a new call while either
//!   is spent, so the windows of what is refused are never re-opened;
//! - a unary request must arrive whole, and each message of a streamed request must complete once
//!   begun, within `--request-timeout` or the call's own deadline, whichever is shorter; past it
//!   the call is answered DEADLINE_EXCEEDED and what it held is let go (nginx's
//!   `client_body_timeout`, Envoy's `request_timeout`).

use std::future::Future as _;
use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use bytes::Bytes;
use http_body::{Body as HttpBody, Frame, SizeHint};
use hyper::body::Incoming;
use tonic::Status;

use super::auth::Caller;
use super::auth::Tokens;
use super::memory::{Admission, Charge, ConnectionShare, Item, MemoryBudget, PendingCall};
use super::metrics::Metrics;
use super::transport::Probation;

/// The largest health or reflection request: a service or symbol name.
pub(super) const SMALL_MESSAGE: usize = 4 * 1024;

/// The smallest limit derived from the bundles: room for ids, names and options.
const MIN_DERIVED_MESSAGE: usize = 16 * 1024;

/// The path prefix of the calls that carry a token.
const PRAC_PATH: &str = "/prac.v1.Prac/";

/// The one call whose request may carry a plan.
const OPEN_SESSION_PATH: &str = "/prac.v1.Prac/OpenSession";

/// Calls whose requests are streams: only each message, not the whole body, must complete in time.
const STREAMED_REQUESTS: [&str; 3] = [
    "/prac.v1.Prac/StepStream",
    "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
    "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
];

/// The limits on requests in transit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct RequestLimits {
    /// A request (unary) or a message of it (streamed) must complete this soon.
    pub(crate) request_timeout: Duration,
    /// Declared bytes of unfinished messages one connection may hold.
    pub(crate) bytes_per_connection: usize,
    /// The same over all connections.
    pub(crate) bytes_total: usize,
    /// `--max-message-bytes`; None follows the loaded bundles.
    pub(crate) max_message_bytes: Option<usize>,
}

/// The largest requests the loaded bundles allow: an OpenSession's, and every other prac.v1 call's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct RequestSizes {
    pub(crate) open_session: usize,
    pub(crate) other: usize,
}

impl Default for RequestSizes {
    /// With no bundle loaded: room for ids, names and options.
    fn default() -> Self {
        RequestSizes {
            open_session: MIN_DERIVED_MESSAGE,
            other: SMALL_MESSAGE,
        }
    }
}

/// The largest Step (or StepStream message) a policy observing `obs_dim` floats allows, and every
/// other call but OpenSession: a session id and an observation, generously.
pub(super) fn largest_step_bytes(obs_dim: usize) -> usize {
    (8 * obs_dim + 1024).max(SMALL_MESSAGE)
}

/// The largest encoded prac.v1 request a policy of these dimensions allows: an OpenSession
/// resuming a plan of `max_horizon` actions, each with its predicted observation, as the client's
/// last StepResponse carries them; packed floats plus every tag, length and varint, generously.
pub(super) fn largest_request_bytes(max_horizon: usize, obs_dim: usize, act_dim: usize) -> usize {
    let entry = 4 * (obs_dim + act_dim) + 32;
    let ids_names_and_options = 1024;
    ((max_horizon + 1) * entry + ids_names_and_options).max(MIN_DERIVED_MESSAGE)
}

/// What every connection of the gRPC listener shares.
pub(super) struct Intake {
    limits: RequestLimits,
    tokens: Option<Arc<Tokens>>,
    /// Largest OpenSession request message now, and largest of every other prac.v1 call.
    max_open_session: AtomicUsize,
    max_other: AtomicUsize,
    held: AtomicUsize,
    metrics: Arc<Metrics>,
    /// The server's memory budget; None for the probes' port, which must answer whatever the
    /// clients hold.
    budget: Option<Arc<MemoryBudget>>,
}

impl Intake {
    pub(super) fn new(
        limits: RequestLimits,
        tokens: Option<Arc<Tokens>>,
        metrics: Arc<Metrics>,
        budget: Option<Arc<MemoryBudget>>,
    ) -> Intake {
        Intake {
            limits,
            tokens,
            budget,
            max_open_session: AtomicUsize::new(
                limits.max_message_bytes.unwrap_or(MIN_DERIVED_MESSAGE),
            ),
            max_other: AtomicUsize::new(limits.max_message_bytes.unwrap_or(SMALL_MESSAGE)),
            held: AtomicUsize::new(0),
            metrics,
        }
    }

    /// The loaded bundles' largest valid requests: the message limits unless one is set.
    pub(super) fn bundles_need(&self, sizes: RequestSizes) {
        let (open_session, other) = match self.limits.max_message_bytes {
            Some(limit) => (limit, limit),
            None => (sizes.open_session, sizes.other),
        };
        let before = self.max_open_session.swap(open_session, Ordering::Relaxed);
        self.max_other.store(other, Ordering::Relaxed);
        if before != open_session {
            tracing::info!(
                open_session_bytes = open_session,
                other_calls_bytes = other,
                "request message limits"
            );
        }
        if open_session + 5 > self.limits.bytes_per_connection {
            tracing::warn!(
                open_session_bytes = open_session,
                per_connection = self.limits.bytes_per_connection,
                "the largest OpenSession request is over --max-request-bytes-per-connection: such \
                 requests will be refused; raise the budget"
            );
        }
    }

    /// The largest OpenSession request message now.
    pub(super) fn max_open_session(&self) -> usize {
        self.max_open_session.load(Ordering::Relaxed)
    }

    pub(super) fn budget(&self) -> Option<&Arc<MemoryBudget>> {
        self.budget.as_ref()
    }

    /// Bytes held now over all connections.
    pub(super) fn held(&self) -> usize {
        self.held.load(Ordering::Relaxed)
    }

    fn refuse(&self, status: Status) -> Status {
        self.metrics.error(&status);
        status
    }

    /// Admits a call from its headers, or says why not; the admitted call's body comes through
    /// the returned [`IntakeBody`], and its memory charge is held until its response ends.
    pub(super) fn admit(
        self: &Arc<Self>,
        connection: &Arc<ConnectionIntake>,
        request: http::Request<Incoming>,
    ) -> Result<(http::Request<IntakeBody>, Option<Charge>), Status> {
        let path = request.uri().path();
        let prac = path.starts_with(PRAC_PATH);
        let caller = match &self.tokens {
            Some(tokens) if prac => Some(
                tokens
                    .caller(request.headers())
                    .map_err(|s| self.refuse(s))?,
            ),
            _ => None,
        };
        if connection.held.load(Ordering::Relaxed) >= self.limits.bytes_per_connection {
            return Err(self.refuse(Status::resource_exhausted(format!(
                "this connection holds its maximum of {} bytes of unfinished requests; finish \
                 them or retry",
                self.limits.bytes_per_connection
            ))));
        }
        // Health and reflection requests are small and open to all: they count against their
        // connection alone, so that no number of them can spend what prac calls share.
        if prac && self.held() >= self.limits.bytes_total {
            return Err(self.refuse(server_full(self.limits.bytes_total)));
        }
        let (charge, pending) = match &self.budget {
            Some(budget) => {
                let Admission { charge, pending } = budget
                    .admit_call(&connection.share)
                    .map_err(|s| self.refuse(s))?;
                (Some(charge), pending)
            }
            None => (None, None),
        };
        let streamed = STREAMED_REQUESTS.contains(&path);
        let now = Instant::now();
        let call_deadline = request
            .headers()
            .get("grpc-timeout")
            .and_then(|v| super::deadline::parse(v.to_str().ok()?))
            .map(|timeout| now + timeout);
        let max_message = if path == OPEN_SESSION_PATH {
            self.max_open_session()
        } else if prac {
            self.max_other.load(Ordering::Relaxed)
        } else {
            SMALL_MESSAGE
        };
        let (mut parts, incoming) = request.into_parts();
        // With tokens off there is no caller to name (handlers take none as none).
        if caller.is_some() {
            parts.extensions.insert(Caller(caller));
        }
        let message_due = streamed.then(MessageDue::default);
        if let Some(due) = &message_due {
            parts.extensions.insert(due.clone());
        }
        let mut body = IntakeBody {
            inner: Some(incoming),
            intake: self.clone(),
            connection: connection.clone(),
            max_message,
            counts_in_total: prac,
            streamed,
            call_deadline,
            due: None,
            message_due,
            timer: None,
            framing: Framing::default(),
            holding: None,
            messages: 0,
            failed: false,
            reset: pending
                .as_ref()
                .map(|p| Box::pin(p.reset().cancelled_owned())),
            pending,
        };
        if !streamed {
            body.set_due(Some(body.bound(now)));
        }
        Ok((http::Request::from_parts(parts, body), charge))
    }
}

fn server_full(total: usize) -> Status {
    Status::resource_exhausted(format!(
        "the server holds its maximum of {total} bytes of unfinished requests; retry shortly"
    ))
}

/// One connection's share of the intake.
pub(super) struct ConnectionIntake {
    held: AtomicUsize,
    /// Until its first request message is complete, the connection may be shed to admit another.
    probation: Mutex<Option<Probation>>,
    /// Its never-started calls and its GOAWAY, as the memory budget sees them.
    pub(crate) share: Arc<ConnectionShare>,
}

impl ConnectionIntake {
    pub(super) fn new(probation: Option<Probation>) -> ConnectionIntake {
        ConnectionIntake {
            held: AtomicUsize::new(0),
            probation: Mutex::new(probation),
            share: Arc::default(),
        }
    }

    fn passed(&self) {
        self.probation
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take();
    }
}

/// When the message a streamed request has begun must be complete, shared with the call's
/// handler. A handler that stops reading its requests (its client does not read the answers, so
/// the handler waits to hand one over) would never see the body's own timer fire: it waits on
/// [`MessageDue::passed`] as well and ends the stream then, letting go of what the message held.
#[derive(Clone, Default)]
pub(super) struct MessageDue(Arc<MessageDueState>);

#[derive(Default)]
struct MessageDueState {
    due: Mutex<Option<Instant>>,
    changed: tokio::sync::Notify,
}

impl MessageDue {
    fn set(&self, due: Option<Instant>) {
        *self.0.due.lock().unwrap_or_else(|p| p.into_inner()) = due;
        self.0.changed.notify_waiters();
    }

    fn get(&self) -> Option<Instant> {
        *self.0.due.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Resolves once a message is due and not complete by then.
    pub(super) async fn passed(&self) {
        loop {
            let changed = self.0.changed.notified();
            tokio::pin!(changed);
            changed.as_mut().enable();
            match self.get() {
                None => changed.await,
                Some(due) => {
                    tokio::select! {
                        _ = tokio::time::sleep_until(due.into()) => {
                            if self.get() == Some(due) {
                                return;
                            }
                        }
                        _ = changed => {}
                    }
                }
            }
        }
    }
}

/// Resolves when `due` passes; never without one.
pub(super) async fn message_overdue(due: Option<&MessageDue>) {
    match due {
        Some(due) => due.passed().await,
        None => std::future::pending().await,
    }
}

/// The answer to a streamed call whose begun message did not complete in time.
pub(super) fn message_overdue_status() -> Status {
    Status::deadline_exceeded(
        "a request message was not complete within the request timeout (--request-timeout) or \
         the call's deadline",
    )
}

/// Declared bytes of one unfinished message, given back when dropped.
struct Holding {
    intake: Arc<Intake>,
    connection: Arc<ConnectionIntake>,
    bytes: usize,
    /// Counted in the server-wide total too (prac.v1 calls).
    in_total: bool,
    _memory: Option<Charge>,
}

impl Holding {
    fn take(
        intake: &Arc<Intake>,
        connection: &Arc<ConnectionIntake>,
        bytes: usize,
        in_total: bool,
    ) -> Result<Holding, Status> {
        let on_connection = connection.held.fetch_add(bytes, Ordering::Relaxed) + bytes;
        let in_all = if in_total {
            intake.held.fetch_add(bytes, Ordering::Relaxed) + bytes
        } else {
            0
        };
        let holding = Holding {
            intake: intake.clone(),
            connection: connection.clone(),
            bytes,
            in_total,
            _memory: intake
                .budget
                .as_ref()
                .map(|b| b.charge(Item::Request, bytes as u64)),
        };
        if on_connection > intake.limits.bytes_per_connection {
            return Err(Status::resource_exhausted(format!(
                "a message of {bytes} bytes would take this connection past its {} bytes of \
                 unfinished requests; finish the others first",
                intake.limits.bytes_per_connection
            )));
        }
        if in_all > intake.limits.bytes_total {
            return Err(server_full(intake.limits.bytes_total));
        }
        Ok(holding)
    }
}

impl Drop for Holding {
    fn drop(&mut self) {
        self.connection
            .held
            .fetch_sub(self.bytes, Ordering::Relaxed);
        if self.in_total {
            self.intake.held.fetch_sub(self.bytes, Ordering::Relaxed);
        }
    }
}

/// Where the gRPC framing of a request stands: the 5-byte prefix read so far, or what is left of
/// the message it declared.
#[derive(Default)]
struct Framing {
    prefix: [u8; 5],
    prefix_read: usize,
    body_left: usize,
}

impl Framing {
    fn in_message(&self) -> bool {
        self.prefix_read > 0 || self.body_left > 0
    }
}

/// A request body read through the intake's limits.
pub(super) struct IntakeBody {
    /// Always Some once admitted (kept optional only while it is built).
    inner: Option<Incoming>,
    intake: Arc<Intake>,
    connection: Arc<ConnectionIntake>,
    max_message: usize,
    /// A prac.v1 call: its messages count in the server-wide total.
    counts_in_total: bool,
    streamed: bool,
    call_deadline: Option<Instant>,
    /// When the request (unary: up to its end of stream) or the message in progress (streamed)
    /// must be complete.
    due: Option<Instant>,
    /// The same, shared with a streamed call's handler (see [`MessageDue`]).
    message_due: Option<MessageDue>,
    timer: Option<Pin<Box<tokio::time::Sleep>>>,
    framing: Framing,
    holding: Option<Holding>,
    /// Messages completed so far.
    messages: u64,
    failed: bool,
    /// Until its first message is complete, the call may be reset to make room in the memory
    /// budget: `reset` resolves then.
    pending: Option<PendingCall>,
    reset: Option<Pin<Box<tokio_util::sync::WaitForCancellationFutureOwned>>>,
}

impl IntakeBody {
    /// The request timeout from `start`, or the call's deadline if sooner.
    fn bound(&self, start: Instant) -> Instant {
        let own = start + self.intake.limits.request_timeout;
        self.call_deadline.map_or(own, |d| d.min(own))
    }

    fn set_due(&mut self, due: Option<Instant>) {
        self.due = due;
        if due.is_none() {
            self.timer = None;
        }
        if let Some(shared) = &self.message_due {
            shared.set(due);
        }
    }

    /// Ends the body with `status`: what it held is let go, and what the client sends after is
    /// never read (h2 releases it as the stream closes).
    fn fail(&mut self, status: Status) -> Status {
        self.failed = true;
        self.holding = None;
        self.started();
        self.inner = None;
        self.set_due(None);
        if self.streamed {
            // A streamed call's handler ends its stream with the status and counts it there.
            status
        } else {
            self.intake.refuse(status)
        }
    }

    /// Follows the framing through one DATA frame.
    fn take_in(&mut self, data: &Bytes) -> Result<(), Status> {
        let mut rest: &[u8] = data;
        while !rest.is_empty() {
            if self.framing.body_left == 0 {
                if self.framing.prefix_read == 0 && self.streamed {
                    self.set_due(Some(self.bound(Instant::now())));
                }
                let n = (5 - self.framing.prefix_read).min(rest.len());
                let at = self.framing.prefix_read;
                self.framing.prefix[at..at + n].copy_from_slice(&rest[..n]);
                self.framing.prefix_read += n;
                rest = &rest[n..];
                if self.framing.prefix_read < 5 {
                    continue;
                }
                self.framing.prefix_read = 0;
                let p = self.framing.prefix;
                let declared = u32::from_be_bytes([p[1], p[2], p[3], p[4]]) as usize;
                if declared > self.max_message {
                    // OUT_OF_RANGE, as tonic answers a message over its own limit.
                    return Err(Status::out_of_range(format!(
                        "a request message of {declared} bytes is too large: this server's limit \
                         is {} bytes (the largest request its policies allow; \
                         --max-message-bytes)",
                        self.max_message
                    )));
                }
                self.holding = Some(Holding::take(
                    &self.intake,
                    &self.connection,
                    declared + 5,
                    self.counts_in_total,
                )?);
                self.framing.body_left = declared;
            } else {
                let n = self.framing.body_left.min(rest.len());
                self.framing.body_left -= n;
                rest = &rest[n..];
            }
            if !self.framing.in_message() {
                self.message_complete();
            }
        }
        Ok(())
    }

    fn message_complete(&mut self) {
        // tonic decodes a complete message at once: what it held is given back.
        self.holding = None;
        self.messages += 1;
        self.started();
        if self.streamed {
            self.set_due(None);
            self.connection.passed();
        }
        // A unary request is complete only at its end of stream: tonic waits for it before the
        // handler runs, so its bound stays until then.
    }

    /// Past its first message (or its end): no longer a call that may be reset to make room.
    fn started(&mut self) {
        self.pending = None;
        self.reset = None;
    }

    fn end_of_stream(&mut self) {
        self.holding = None;
        self.started();
        self.set_due(None);
        if self.messages > 0 {
            self.connection.passed();
        }
    }
}

impl HttpBody for IntakeBody {
    type Data = Bytes;
    type Error = Box<dyn std::error::Error + Send + Sync>;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        let this = &mut *self;
        if this.failed {
            return Poll::Ready(None);
        }
        let Some(inner) = this.inner.as_mut() else {
            return Poll::Ready(None);
        };
        match Pin::new(inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref()
                    && let Err(status) = this.take_in(data)
                {
                    return Poll::Ready(Some(Err(this.fail(status).into())));
                }
                if frame.is_trailers() || this.inner.as_ref().is_some_and(|b| b.is_end_stream()) {
                    this.end_of_stream();
                }
                return Poll::Ready(Some(Ok(frame)));
            }
            Poll::Ready(Some(Err(e))) => {
                this.failed = true;
                this.holding = None;
                this.set_due(None);
                return Poll::Ready(Some(Err(e.into())));
            }
            Poll::Ready(None) => {
                this.end_of_stream();
                return Poll::Ready(None);
            }
            Poll::Pending => {}
        }
        if let Some(reset) = this.reset.as_mut()
            && reset.as_mut().poll(cx).is_ready()
        {
            return Poll::Ready(Some(Err(this
                .fail(super::memory::call_reset_status())
                .into())));
        }
        let Some(due) = this.due else {
            return Poll::Pending;
        };
        let due = tokio::time::Instant::from_std(due);
        let timer = this
            .timer
            .get_or_insert_with(|| Box::pin(tokio::time::sleep_until(due)));
        if timer.deadline() != due {
            timer.as_mut().reset(due);
        }
        match timer.as_mut().poll(cx) {
            Poll::Ready(()) => {
                let status = if this.streamed {
                    message_overdue_status()
                } else {
                    Status::deadline_exceeded(
                        "the request was not complete (its message and end of stream) within \
                         the request timeout (--request-timeout) or the call's deadline",
                    )
                };
                Poll::Ready(Some(Err(this.fail(status).into())))
            }
            Poll::Pending => Poll::Pending,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.failed || self.inner.as_ref().is_none_or(|b| b.is_end_stream())
    }

    fn size_hint(&self) -> SizeHint {
        self.inner
            .as_ref()
            .map_or_else(SizeHint::default, |b| b.size_hint())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_largest_request_grows_with_the_plan_and_the_dimensions() {
        let hopper = largest_request_bytes(256, 15, 3);
        let humanoid = largest_request_bytes(256, 44, 17);
        assert!(humanoid > hopper && hopper >= MIN_DERIVED_MESSAGE);
        // 257 entries of 61 floats: over 62 KB, well under the 4 MiB it replaces.
        assert!(
            humanoid > 257 * 61 * 4 && humanoid < 128 * 1024,
            "{humanoid}"
        );
        assert_eq!(largest_request_bytes(1, 1, 1), MIN_DERIVED_MESSAGE);
        assert!(largest_step_bytes(44) >= 44 * 4 + 64);
        // No bundle loaded: room for ids and options, never a limit of 0.
        let empty = super::super::registry::Registry::default().largest_requests(256);
        assert_eq!(empty, RequestSizes::default());
        assert!(empty.open_session >= MIN_DERIVED_MESSAGE && empty.other >= SMALL_MESSAGE);
    }
}
