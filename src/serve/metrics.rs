//! Prometheus metrics of `prac serve`, served over HTTP at `--metrics-listen ADDR` `/metrics`.

use std::sync::{Arc, OnceLock};
use std::time::Duration;

use axum::Router;
use axum::extract::State;
use axum::http::StatusCode;
use axum::http::header::CONTENT_TYPE;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use tokio_util::sync::CancellationToken;

use super::memory::{Item, Shed, Snapshot};
use super::transport::{Admitted, ConnectionStats, Limits, accept_loop};
use axum::extract::Request;
use hyper::body::Incoming;

type Labels = Vec<(&'static str, String)>;

pub(super) struct Metrics {
    registry: Registry,
    steps: Family<Labels, Counter>,
    step_latency: Histogram,
    open_sessions: Gauge,
    sessions_opened: Counter,
    /// Steps clients answered on board while no server answered, as reported when they resumed.
    local_steps: Family<Labels, Counter>,
    evictions: Counter,
    plan_breaks: Counter,
    forecast_length: Histogram,
    forecast_age: Histogram,
    serving: Gauge,
    max_sessions: Gauge,
    build_info: Family<Labels, Gauge>,
    errors: Family<Labels, Counter>,
    reloads: Family<Labels, Counter>,
    credential_reloads: Family<Labels, Counter>,
    /// One sample, labelled with the certificate's path, once TLS is on: a plaintext server
    /// exports none, so it never looks expired.
    certificate_expiry: Family<Labels, Gauge>,
    replanned: Family<Labels, Counter>,
    /// The two `replanned` counters, each taken from the family at its first step, so that
    /// counting a step allocates nothing after.
    replanned_by_handler: OnceLock<Counter>,
    replanned_by_batch_worker: OnceLock<Counter>,
    memory_limit: Gauge,
    memory_reserved: Gauge,
    memory_budget: Gauge,
    memory_high_water: Gauge,
    memory_charged: Family<Labels, Gauge>,
    memory_resident: Gauge,
    memory_shed: Family<Labels, Counter>,
}

/// What a served step's answer says, as the metrics count it.
pub(super) struct StepAnswer {
    /// Committed actions in the forecast.
    pub(crate) forecast_length: usize,
    /// f_t of the action executed now.
    pub(crate) f_t: u64,
    /// Whether the previous plan failed the critic's test.
    pub(crate) broke: bool,
}

/// Where a step was replanned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum ReplannedBy {
    /// In its request handler: alone, or with batching off.
    Handler,
    /// By a batch worker, with the steps queued with it.
    BatchWorker,
}

impl Default for Metrics {
    fn default() -> Self {
        let m = Metrics {
            registry: Registry::with_prefix("prac"),
            steps: Family::default(),
            // 10 us .. ~80 ms.
            step_latency: Histogram::new(exponential_buckets(1e-5, 2.0, 14)),
            open_sessions: Gauge::default(),
            sessions_opened: Counter::default(),
            local_steps: Family::default(),
            evictions: Counter::default(),
            plan_breaks: Counter::default(),
            // 1 .. 256 actions.
            forecast_length: Histogram::new(exponential_buckets(1.0, 2.0, 9)),
            forecast_age: Histogram::new(exponential_buckets(1.0, 2.0, 9)),
            serving: Gauge::default(),
            max_sessions: Gauge::default(),
            build_info: Family::default(),
            errors: Family::default(),
            reloads: Family::default(),
            credential_reloads: Family::default(),
            certificate_expiry: Family::default(),
            replanned: Family::default(),
            replanned_by_handler: OnceLock::new(),
            replanned_by_batch_worker: OnceLock::new(),
            memory_limit: Gauge::default(),
            memory_reserved: Gauge::default(),
            memory_budget: Gauge::default(),
            memory_high_water: Gauge::default(),
            memory_charged: Family::default(),
            memory_resident: Gauge::default(),
            memory_shed: Family::default(),
        };
        let mut m = m;
        let r = &mut m.registry;
        r.register("steps", "Steps served, by policy", m.steps.clone());
        r.register(
            "step_latency_seconds",
            "Time from a step's arrival to its answer (batching included)",
            m.step_latency.clone(),
        );
        r.register(
            "open_sessions",
            "Sessions open now",
            m.open_sessions.clone(),
        );
        r.register(
            "sessions_opened",
            "Sessions opened",
            m.sessions_opened.clone(),
        );
        r.register(
            "local_steps",
            "Steps clients answered on board (their fallback) while no server answered, by policy, \
             as reported when the session resumed",
            m.local_steps.clone(),
        );
        r.register(
            "session_evictions",
            "Sessions evicted after the session TTL idle",
            m.evictions.clone(),
        );
        r.register(
            "plan_breaks",
            "Steps whose plan failed the critic's test and was replanned from the break",
            m.plan_breaks.clone(),
        );
        r.register(
            "forecast_length",
            "Committed actions in each step's forecast",
            m.forecast_length.clone(),
        );
        r.register(
            "f_t",
            "f_t = t + 1 - i of each executed action: steps since the step i that decided it (1 = decided now)",
            m.forecast_age.clone(),
        );
        r.register(
            "serving",
            "1 while prac.v1.Prac is SERVING (bundles loaded, not draining), else 0: readiness",
            m.serving.clone(),
        );
        r.register(
            "max_sessions",
            "The --max-sessions limit: open_sessions beyond it are refused",
            m.max_sessions.clone(),
        );
        m.build_info
            .get_or_create(&vec![("version", env!("CARGO_PKG_VERSION").to_string())])
            .set(1);
        r.register(
            "build_info",
            "1, labelled with the server's version",
            m.build_info.clone(),
        );
        r.register(
            "errors",
            "Calls and streams that ended with an error, by gRPC status code",
            m.errors.clone(),
        );
        r.register(
            "replanned",
            "Steps replanned, by where: in their request handler or by a batch worker",
            m.replanned.clone(),
        );
        r.register(
            "reloads",
            "Bundle reloads (SIGHUP), by result",
            m.reloads.clone(),
        );
        r.register(
            "tls_cert_expiry_timestamp_seconds",
            "When the certificate served to new connections expires (its notAfter), in Unix seconds",
            m.certificate_expiry.clone(),
        );
        r.register(
            "credential_reloads",
            "Changed certificate and token files loaded (ok) or refused, the old ones kept (error)",
            m.credential_reloads.clone(),
        );
        r.register(
            "memory_limit_bytes",
            "Memory the server may use in all: --max-memory, else the cgroup's limit, else the machine's",
            m.memory_limit.clone(),
        );
        r.register(
            "memory_reserved_bytes",
            "Of the limit, set aside for the runtime and the loaded bundles",
            m.memory_reserved.clone(),
        );
        r.register(
            "memory_budget_bytes",
            "The clients' memory budget: the limit less the reserve and a tenth as slack",
            m.memory_budget.clone(),
        );
        r.register(
            "memory_high_water_bytes",
            "Past this much charged, never-started calls and idle watchers are shed to make room",
            m.memory_high_water.clone(),
        );
        r.register(
            "memory_charged_bytes",
            "Charged against the clients' memory budget now, by item",
            m.memory_charged.clone(),
        );
        r.register(
            "memory_resident_bytes",
            "The server's resident memory (VmRSS) at the scrape",
            m.memory_resident.clone(),
        );
        r.register(
            "memory_shed",
            "What the server did to stay within its memory budget, by action",
            m.memory_shed.clone(),
        );
        m
    }
}

impl Metrics {
    /// Readiness as the health service reports it for prac.v1.Prac.
    pub(super) fn set_serving(&self, serving: bool) {
        self.serving.set(i64::from(serving));
    }

    pub(super) fn set_max_sessions(&self, limit: usize) {
        self.max_sessions
            .set(i64::try_from(limit).unwrap_or(i64::MAX));
    }

    /// The step counter of one policy, taken once per session so a step allocates nothing.
    pub(super) fn policy_steps(&self, policy: &str) -> Counter {
        self.steps
            .get_or_create(&vec![("policy", policy.to_string())])
            .clone()
    }

    /// One step served: `steps` is its policy's counter (`policy_steps`).
    pub(super) fn step_answered(&self, steps: &Counter, latency: Duration, answer: &StepAnswer) {
        steps.inc();
        self.step_latency.observe(latency.as_secs_f64());
        self.forecast_length.observe(answer.forecast_length as f64);
        self.forecast_age.observe(answer.f_t as f64);
        let broke = answer.broke;
        if broke {
            self.plan_breaks.inc();
        }
    }

    pub(super) fn replanned(&self, by: ReplannedBy) {
        let (counter, label) = match by {
            ReplannedBy::Handler => (&self.replanned_by_handler, "handler"),
            ReplannedBy::BatchWorker => (&self.replanned_by_batch_worker, "batch_worker"),
        };
        counter
            .get_or_init(|| {
                let labels = vec![("by", label.to_string())];
                self.replanned.get_or_create(&labels).clone()
            })
            .inc();
    }

    pub(super) fn error(&self, status: &tonic::Status) {
        self.errors
            .get_or_create(&vec![("code", format!("{:?}", status.code()))])
            .inc();
    }

    pub(super) fn session_opened(&self) {
        self.sessions_opened.inc();
    }

    pub(super) fn local_steps(&self, policy: &str, steps: u64) {
        if steps > 0 {
            self.local_steps
                .get_or_create(&vec![("policy", policy.to_string())])
                .inc_by(steps);
        }
    }

    pub(super) fn evicted(&self, count: usize) {
        self.evictions.inc_by(count as u64);
    }

    pub(super) fn reload(&self, clean: bool) {
        let result = if clean { "ok" } else { "errors" };
        self.reloads
            .get_or_create(&vec![("result", result.to_string())])
            .inc();
    }

    pub(super) fn credential_reload(&self, file: &str, ok: bool) {
        let result = if ok { "ok" } else { "error" };
        self.credential_reloads
            .get_or_create(&vec![
                ("file", file.to_string()),
                ("result", result.to_string()),
            ])
            .inc();
    }

    #[cfg(test)]
    pub(super) fn credential_reloads(&self, file: &str, ok: bool) -> u64 {
        let result = if ok { "ok" } else { "error" };
        self.credential_reloads
            .get_or_create(&vec![
                ("file", file.to_string()),
                ("result", result.to_string()),
            ])
            .get()
    }

    /// Exports the served certificate's expiry.
    pub(super) fn set_certificate_expiry(&self, cert: &std::path::Path, not_after: i64) {
        self.certificate_expiry
            .get_or_create(&vec![("cert", cert.display().to_string())])
            .set(not_after);
    }

    pub(super) fn is_serving(&self) -> bool {
        self.serving.get() == 1
    }

    /// The memory budget's numbers, as read now.
    pub(super) fn memory(&self, snapshot: &Snapshot) {
        let gauge = |g: &Gauge, v: u64| g.set(i64::try_from(v).unwrap_or(i64::MAX));
        gauge(&self.memory_limit, snapshot.total);
        gauge(&self.memory_reserved, snapshot.reserved);
        gauge(&self.memory_budget, snapshot.budget);
        gauge(&self.memory_high_water, snapshot.high_water);
        for item in Item::ALL {
            let labels = vec![("item", item.name().to_string())];
            gauge(
                &self.memory_charged.get_or_create(&labels),
                snapshot.used[item as usize],
            );
        }
        for shed in Shed::ALL {
            let labels = vec![("action", shed.name().to_string())];
            let counter = self.memory_shed.get_or_create(&labels);
            counter.inc_by(snapshot.shed[shed as usize].saturating_sub(counter.get()));
        }
        if let Some(resident) = super::memory::limit::resident_bytes() {
            gauge(&self.memory_resident, resident);
        }
    }

    /// The OpenMetrics text of every metric, with the open-session gauge read now.
    pub(super) fn encode(&self, open_sessions: usize) -> String {
        self.open_sessions.set(open_sessions as i64);
        let mut text = String::new();
        encode(&mut text, &self.registry).expect("writing to a String cannot fail");
        text
    }
}

/// Writes the OpenMetrics text of a scrape.
pub(super) type Scrape = Arc<dyn Fn() -> String + Send + Sync>;

async fn scrape(State(scrape): State<Scrape>) -> impl IntoResponse {
    let text = scrape();
    Response::builder()
        .status(StatusCode::OK)
        .header(
            CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )
        .body(axum::body::Body::from(text))
        .unwrap_or_else(|_| StatusCode::INTERNAL_SERVER_ERROR.into_response())
}

/// `GET /readyz`: 200 while prac.v1.Prac is SERVING, else 503, for load balancers and proxies
/// that check health over HTTP/1.1 rather than gRPC (HAProxy, cloud load balancers).
async fn readyz(State(metrics): State<Arc<Metrics>>) -> impl IntoResponse {
    if metrics.is_serving() {
        (StatusCode::OK, "SERVING\n")
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, "NOT_SERVING\n")
    }
}

/// Connections the metrics endpoint holds at once: scrapers are few.
pub(super) const MAX_METRICS_CONNECTIONS: usize = 64;

/// A scraper sends its request head at once: a client slower than this is closed (and at the cap
/// the oldest one without its headers in is shed sooner, to admit a new one).
const METRICS_HEADER_DEADLINE: Duration = Duration::from_secs(2);

/// Largest request head (request line and headers) the metrics endpoint reads.
const MAX_METRICS_REQUEST_BYTES: usize = 16 * 1024;

/// Serves `/metrics` and `/readyz` on `listener` until shutdown: one request per connection, whose whole life
/// (request, scrape, response read) must fit in the handshake timeout, so slow or silent clients
/// cannot hold the endpoint; at most [`MAX_METRICS_CONNECTIONS`] at once.
pub(super) async fn serve(
    listener: tokio::net::TcpListener,
    scrape_text: Scrape,
    readiness: Arc<Metrics>,
    limits: Limits,
    shutdown: CancellationToken,
) {
    use hyper_util::rt::{TokioIo, TokioTimer};
    use tonic::codegen::Service;
    let router = Router::new()
        .route("/metrics", get(scrape))
        .with_state(scrape_text)
        .merge(
            Router::new()
                .route("/readyz", get(readyz))
                .with_state(readiness),
        );
    let stats = Arc::new(ConnectionStats::default());
    let cap = MAX_METRICS_CONNECTIONS.min(limits.max_connections);
    let lifetime = limits.handshake_timeout;
    let header_deadline = lifetime.min(METRICS_HEADER_DEADLINE);
    accept_loop(listener, cap, stats, shutdown, |tcp, peer, admitted| {
        let router = router.clone();
        tokio::spawn(async move {
            let Admitted { permit, probation } = admitted;
            let _permit = permit;
            let shed = probation.shed_signal();
            // A request whose headers are in is past its probation: it cannot be shed.
            let probation = std::sync::Mutex::new(Some(probation));
            let service = hyper::service::service_fn(move |request: Request<Incoming>| {
                probation.lock().unwrap_or_else(|p| p.into_inner()).take();
                // axum's router is always ready, and its future owns what it needs.
                router.clone().call(request.map(axum::body::Body::new))
            });
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder
                .timer(TokioTimer::new())
                .header_read_timeout(header_deadline)
                .max_buf_size(MAX_METRICS_REQUEST_BYTES)
                .keep_alive(false);
            let connection = builder.serve_connection(TokioIo::new(tcp), service);
            tokio::select! {
                done = tokio::time::timeout(lifetime, connection) => {
                    if done.is_err() {
                        tracing::debug!(%peer, "metrics connection closed: not done within the handshake timeout");
                    }
                }
                _ = shed.cancelled() => {
                    tracing::debug!(%peer, "metrics connection shed at the cap: no request headers yet");
                }
            }
        });
    })
    .await;
}
