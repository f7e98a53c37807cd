//! `prac serve`: the gRPC daemon.

pub(crate) mod arrival;
mod auth;
mod batch;
mod config;
mod credentials;
mod deadline;
mod health;
mod intake;
mod memory;
mod metrics;
mod registry;
mod scheduling;
mod service;
pub(crate) mod session;
mod transport;
mod workspace;

use std::future::Future;
use std::io::IsTerminal;
use std::sync::{Arc, RwLock};

use anyhow::Context;
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tonic_health::ServingStatus;

pub use config::{LogFormat, ServeArgs, ServeConfig, duration, socket_address};
use registry::Registry;
pub use registry::servable;
pub use scheduling::handlers_do_not_preempt;
use service::{PracService, ServerState};
use session::Sessions;

use crate::proto::{self, prac_server::PracServer};

/// Connections the health port holds at once: probes are few.
const PROBE_CONNECTIONS: usize = 64;

/// Largest response (and request, by tonic's own check) when `--max-message-bytes` is not set.
const DEFAULT_MAX_RESPONSE_BYTES: usize = 4 << 20;

/// Sets up tracing on stderr in the chosen format (RUST_LOG overrides the level, default info).
pub fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr)
        // A line stderr cannot take (its reader gone) is dropped: reporting the failure on that
        // same stderr panics the task that logged it, and the shutdown task with it.
        .log_internal_errors(false);
    let _ = match format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
}

/// Resolves when the process gets SIGINT or SIGTERM. The handlers are installed when this is
/// called, not when the future is first polled, so that a signal sent as soon as the ready line
/// is out drains the server rather than killing it.
fn termination_signal() -> impl Future<Output = ()> + Send + 'static {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let interrupt = signal(SignalKind::interrupt());
        let term = signal(SignalKind::terminate());
        async move {
            match (interrupt, term) {
                (Ok(mut interrupt), Ok(mut term)) => {
                    tokio::select! {
                        _ = interrupt.recv() => {}
                        _ = term.recv() => {}
                    }
                }
                (interrupt, term) => {
                    if let Err(e) = interrupt.as_ref().and(term.as_ref()) {
                        tracing::error!(error = %e, "cannot listen for SIGINT or SIGTERM");
                    }
                    match (interrupt, term) {
                        (Ok(mut interrupt), _) => {
                            interrupt.recv().await;
                        }
                        (_, Ok(mut term)) => {
                            term.recv().await;
                        }
                        _ => std::future::pending::<()>().await,
                    }
                }
            }
        }
    }
    #[cfg(not(unix))]
    async {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// While no policy is served (an empty, missing or unreadable bundle directory, as a volume not
/// yet filled), the directory is read again this often.
const RETRY_EMPTY_BUNDLES: std::time::Duration = std::time::Duration::from_secs(10);

/// Hot reload: on each SIGHUP (which also re-reads changed certificate and token files), and
/// every [`RETRY_EMPTY_BUNDLES`] while nothing is served, re-reads the bundle directory ([`Registry::reload`]). New sessions get the new versions; open sessions
/// keep the policy they opened with until they close; a broken new file keeps the old version.
#[cfg(unix)]
async fn reload_on_hangup(
    state: Arc<ServerState>,
    dir: std::path::PathBuf,
    health: Health,
    credentials: Arc<credentials::Credentials>,
    hangup: Option<tokio::signal::unix::Signal>,
    max_sessions: usize,
    threads: usize,
) {
    let Some(mut hangup) = hangup else {
        return;
    };
    let mut retry = tokio::time::interval(RETRY_EMPTY_BUNDLES);
    retry.tick().await;
    loop {
        let serving_none = state
            .registry
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .is_none_or(|r| r.is_empty());
        let retrying = tokio::select! {
            signal = hangup.recv() => {
                if signal.is_none() {
                    return;
                }
                let credentials = credentials.clone();
                let _ = tokio::task::spawn_blocking(move || credentials.reload_changed()).await;
                false
            }
            _ = retry.tick(), if serving_none => true,
            // Looks again at whether anything is served.
            _ = tokio::time::sleep(RETRY_EMPTY_BUNDLES), if !serving_none => continue,
        };
        if retrying && std::fs::read_dir(&dir).is_err() {
            // Still unreadable: said once at start, not every retry.
            continue;
        }
        let current = state
            .registry
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
            .unwrap_or_default();
        let reload_dir = dir.clone();
        let reloaded = tokio::task::spawn_blocking(move || current.reload(&reload_dir)).await;
        let (registry, report) = match reloaded {
            Ok(Ok(done)) => done,
            Ok(Err(e)) => {
                tracing::error!(dir = %dir.display(), error = %e, "reload failed: cannot read the bundle directory; serving as before");
                state.metrics.reload(false);
                continue;
            }
            Err(e) => {
                tracing::error!(error = %e, "reload failed; serving as before");
                state.metrics.reload(false);
                continue;
            }
        };
        if retrying && report.added.is_empty() && report.errors.is_empty() {
            // Still nothing to serve: not a reload worth a log line or a count.
            continue;
        }
        for error in &report.errors {
            tracing::error!(%error, "reload: bad bundle (a loaded version of it, if any, stays)");
        }
        tracing::info!(
            added = ?report.added,
            replaced = ?report.replaced,
            removed = ?report.removed,
            kept_old = ?report.kept_old,
            unchanged = report.unchanged.len(),
            "reloaded bundles"
        );
        if let Err(e) = fit_memory(&state, &registry, max_sessions, threads) {
            tracing::error!(error = %format!("{e:#}"), "reload refused: the new bundles do not fit the memory budget; serving as before");
            state.metrics.reload(false);
            continue;
        }
        state.metrics.reload(report.errors.is_empty());
        let serving = !registry.is_empty();
        state
            .intake
            .bundles_need(registry.largest_requests(state.max_horizon_limit));
        *state.registry.write().unwrap_or_else(|p| p.into_inner()) = Some(Arc::new(registry));
        if !state.shutdown.is_cancelled() {
            health
                .set(if serving {
                    ServingStatus::Serving
                } else {
                    ServingStatus::NotServing
                })
                .await;
        }
    }
}

/// The listeners and what the transport needs, made ready before any bundle loads.
pub(crate) struct Bound {
    pub(crate) grpc: TcpListener,
    /// The Prometheus endpoint's, when asked for.
    pub(crate) metrics: Option<TcpListener>,
    /// The plaintext health port's, when asked for.
    pub(crate) health: Option<TcpListener>,
    tls: Option<tokio_rustls::TlsAcceptor>,
    credentials: Arc<credentials::Credentials>,
    /// The server's metrics, made here so that loading the credentials can record theirs.
    telemetry: Arc<metrics::Metrics>,
    limits: transport::Limits,
    /// SIGHUP's handler, installed before the ready line: a SIGHUP's default action would end
    /// the process.
    #[cfg(unix)]
    hangup: Option<tokio::signal::unix::Signal>,
}

/// Reads what the settings name (token file, certificate, bundle directory) and binds the
/// listeners. Anything wrong stops the server here, before its ready line: a supervisor waiting
/// for `listening on` must not see it from a server that is about to exit.
pub(crate) async fn bind(config: &ServeConfig) -> anyhow::Result<Bound> {
    // A bad token file or certificate stops the server: starting without the auth or the TLS
    // it was asked for is worse.
    let telemetry = Arc::new(metrics::Metrics::default());
    let credentials = Arc::new(credentials::Credentials::load(
        config.tls.as_ref(),
        config.auth_tokens.as_deref(),
        telemetry.clone(),
    )?);
    let tls = credentials.acceptor()?;
    let mut limits = config.connections;
    let (soft, hard) =
        transport::raise_open_file_limit().context("cannot read the open-file limit")?;
    limits.max_connections = transport::connection_cap(limits.max_connections, soft);
    anyhow::ensure!(
        limits.max_connections >= transport::MIN_WORKABLE_CONNECTIONS
            || limits.max_connections == config.connections.max_connections,
        "the open-file limit is {soft} (hard limit {hard}), which leaves {} connections once 64 \
         descriptors are kept for bundles, logs and listeners; at least {} are needed. Raise \
         the hard limit: `ulimit -Hn 4096` in the shell that starts prac (as root), \
         LimitNOFILE=4096 in a systemd unit, or --ulimit nofile=4096 for a container",
        limits.max_connections,
        transport::MIN_WORKABLE_CONNECTIONS
    );
    if limits.max_connections < config.connections.max_connections {
        tracing::warn!(
            max_connections = limits.max_connections,
            asked = config.connections.max_connections,
            open_file_limit = soft,
            "the open-file limit (ulimit -n) allows fewer connections than asked; raise it to serve more"
        );
    }
    if config.strict {
        // Without --strict an unreadable directory leaves the server up, NOT_SERVING (a volume
        // not yet mounted); with it, nothing may be missing.
        std::fs::read_dir(&config.bundles).with_context(|| {
            format!("cannot read bundle directory {}", config.bundles.display())
        })?;
    }
    let grpc = TcpListener::bind(config.listen)
        .await
        .with_context(|| format!("cannot listen on {}", config.listen))?;
    let metrics = match config.metrics_listen {
        Some(at) => Some(
            TcpListener::bind(at)
                .await
                .with_context(|| format!("cannot listen for metrics on {at}"))?,
        ),
        None => None,
    };
    let health = match config.health_listen {
        Some(at) => Some(
            TcpListener::bind(at)
                .await
                .with_context(|| format!("cannot listen for health probes on {at}"))?,
        ),
        None => None,
    };
    #[cfg(unix)]
    let hangup = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup())
        .inspect_err(|e| tracing::error!(error = %e, "cannot listen for SIGHUP; hot reload is off"))
        .ok();
    Ok(Bound {
        grpc,
        metrics,
        health,
        tls,
        credentials,
        telemetry,
        limits,
        #[cfg(unix)]
        hangup,
    })
}

/// Runs the server until SIGINT/SIGTERM. Prints `listening on ADDR` on stdout once bound (port 0
/// picks a free port; scripts and tests read that line).
pub async fn run(config: ServeConfig) -> anyhow::Result<()> {
    let bound = bind(&config).await?;
    let shutdown = termination_signal();
    if let Some(metrics) = &bound.metrics {
        // Printed before the gRPC address, which scripts wait for as the ready line.
        println!("metrics on {}", metrics.local_addr()?);
    }
    if let Some(health) = &bound.health {
        println!("health on {}", health.local_addr()?);
    }
    let addr = bound.grpc.local_addr()?;
    println!("listening on {addr}");
    tracing::info!(%addr, bundles = %config.bundles.display(), "listening");
    serve(bound, &config, shutdown).await
}

/// The health service's view of the server: NOT_SERVING until bundles load and from shutdown on,
/// reported to the health service and the `prac_serving` gauge alike.
#[derive(Clone)]
struct Health {
    reporter: tonic_health::server::HealthReporter,
    metrics: Arc<metrics::Metrics>,
}

/// The health service that answers SERVING for as long as the process answers at all: a
/// liveness probe's, where `""` and `prac.v1.Prac` (readiness) follow the bundles and the drain.
pub(crate) const LIVENESS_SERVICE: &str = "liveness";

impl Health {
    async fn set(&self, status: ServingStatus) {
        self.metrics.set_serving(status == ServingStatus::Serving);
        self.reporter.set_service_status("", status).await;
        self.reporter
            .set_service_status(
                <PracServer<PracService> as tonic::server::NamedService>::NAME,
                status,
            )
            .await;
    }
}

/// Serves on `bound` until `shutdown` resolves, then drains for up to the drain timeout: health
/// goes NOT_SERVING first, open streams end with UNAVAILABLE. Bundles load from the settings'
/// directory while the listener already accepts (answering UNAVAILABLE until they are in).
pub(crate) async fn serve(
    bound: Bound,
    config: &ServeConfig,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let cancel = CancellationToken::new();
    #[cfg(unix)]
    let hangup = bound.hangup;
    let reporter = tonic_health::server::HealthReporter::new();
    let health_service = tonic_health::pb::health_server::HealthServer::new(
        health::ShutdownAwareHealth::new(reporter.clone(), cancel.clone()),
    );
    let probe_health = bound.health.as_ref().map(|_| {
        tonic_health::pb::health_server::HealthServer::new(health::ShutdownAwareHealth::new(
            reporter.clone(),
            cancel.clone(),
        ))
    });
    reporter
        .set_service_status(LIVENESS_SERVICE, ServingStatus::Serving)
        .await;
    let state = server_state(
        config,
        bound.credentials.tokens(),
        bound.telemetry,
        cancel.clone(),
    )?;
    tokio::spawn(credentials::watch(
        bound.credentials.clone(),
        cancel.clone(),
    ));
    let health = Health {
        reporter,
        metrics: state.metrics.clone(),
    };
    health.set(ServingStatus::NotServing).await;
    // Reflection in both versions: grpcurl and grpcio's reflection client speak v1, Postman,
    // older grpcurl and many others v1alpha. Both list prac.v1.Prac and grpc.health.v1.Health.
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection_v1 = reflection()
        .build_v1()
        .context("building the reflection service")?;
    let reflection_v1alpha = reflection()
        .build_v1alpha()
        .context("building the reflection service (v1alpha)")?;

    let prac = PracServer::new(PracService {
        state: state.clone(),
    })
    // The intake holds requests to what the bundles need before tonic sees them.
    .max_decoding_message_size(
        config
            .requests
            .max_message_bytes
            .unwrap_or(DEFAULT_MAX_RESPONSE_BYTES),
    )
    .max_encoding_message_size(
        config
            .requests
            .max_message_bytes
            .unwrap_or(DEFAULT_MAX_RESPONSE_BYTES),
    );
    let routes = tonic::service::Routes::new(health_service)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(prac);
    let connection_stats = Arc::new(transport::ConnectionStats::default());
    tokio::spawn(memory::give_back_after_bursts(
        connection_stats.clone(),
        state.budget.clone(),
        cancel.clone(),
    ));
    let server = transport::serve_grpc(
        bound.grpc,
        bound.tls,
        routes,
        bound.limits,
        state.intake.clone(),
        connection_stats,
        cancel.clone(),
    );
    let mut server = tokio::spawn(server);
    if let (Some(listener), Some(probe_health)) = (bound.health, probe_health) {
        // Plaintext, no token, grpc.health.v1 alone: what the kubelet's gRPC probes can reach.
        let limits = transport::Limits {
            max_connections: bound.limits.max_connections.min(PROBE_CONNECTIONS),
            ..bound.limits
        };
        // Outside the memory budget: probes are few, and must be answered however short it is.
        let intake = Arc::new(intake::Intake::new(
            config.requests,
            None,
            state.metrics.clone(),
            None,
        ));
        tokio::spawn(transport::serve_grpc(
            listener,
            None,
            tonic::service::Routes::new(probe_health),
            limits,
            intake,
            Arc::new(transport::ConnectionStats::default()),
            cancel.clone(),
        ));
    }
    if let Some(listener) = bound.metrics {
        let (sessions, metrics) = (state.sessions.clone(), state.metrics.clone());
        let readiness = state.metrics.clone();
        let budget = state.budget.clone();
        let scrape: metrics::Scrape = Arc::new(move || {
            metrics.memory(&budget.snapshot());
            metrics.encode(sessions.len())
        });
        tokio::spawn(metrics::serve(
            listener,
            scrape,
            readiness,
            bound.limits,
            cancel.clone(),
        ));
    }
    tokio::spawn({
        let (cancel, health) = (cancel.clone(), health.clone());
        async move {
            shutdown.await;
            tracing::info!("shutdown requested: draining");
            // Health first, so watchers and load balancers see NOT_SERVING before streams end.
            health.set(ServingStatus::NotServing).await;
            cancel.cancel();
        }
    });
    let dir = config.bundles.clone();
    let load = tokio::task::spawn_blocking(move || Registry::load_dir(&dir));
    let loaded = tokio::select! {
        loaded = load => loaded?,
        _ = cancel.cancelled() => {
            // Stopped before the bundles loaded: no session exists, only the listener to close.
            let _ = tokio::time::timeout(config.drain_timeout, &mut server).await;
            return Ok(());
        }
    };
    if let Err(e) = install_bundles(&state, config, &health, loaded).await {
        cancel.cancel();
        return Err(e);
    }
    #[cfg(unix)]
    let reloader = tokio::spawn(reload_on_hangup(
        state.clone(),
        config.bundles.clone(),
        health.clone(),
        bound.credentials.clone(),
        hangup,
        config.max_sessions,
        replanning_threads(config),
    ));
    #[cfg(not(unix))]
    let reloader = tokio::spawn(async {});

    tokio::select! {
        result = &mut server => {
            reloader.abort();
            return result.context("server failed");
        }
        _ = cancel.cancelled() => {}
    }
    reloader.abort();
    match tokio::time::timeout(config.drain_timeout, &mut server).await {
        Ok(result) => {
            result.context("server failed")?;
            tracing::info!("drained; bye");
        }
        Err(_) => {
            server.abort();
            tracing::warn!(
                timeout = ?config.drain_timeout,
                "drain timeout passed with connections still open; exiting anyway"
            );
        }
    }
    Ok(())
}

/// What the handlers share, before any bundle is loaded.
fn server_state(
    config: &ServeConfig,
    auth: Option<Arc<auth::Tokens>>,
    metrics: Arc<metrics::Metrics>,
    cancel: CancellationToken,
) -> anyhow::Result<Arc<ServerState>> {
    metrics.set_max_sessions(config.max_sessions);
    let limit = memory::limit::resolve(config.max_memory)?;
    tracing::info!(
        max_memory = %memory::show_size(limit.bytes),
        from = %limit.source,
        "memory budget"
    );
    let budget = memory::MemoryBudget::new(limit);
    Ok(Arc::new(ServerState {
        intake: Arc::new(intake::Intake::new(
            config.requests,
            auth.clone(),
            metrics.clone(),
            Some(budget.clone()),
        )),
        budget,
        registry: RwLock::new(None),
        sessions: {
            let metrics = metrics.clone();
            Sessions::start(config.max_sessions, config.session_ttl, move |evicted| {
                metrics.evicted(evicted)
            })
        },
        max_horizon_limit: config.max_horizon_limit,
        max_message_bytes: config
            .requests
            .max_message_bytes
            .unwrap_or(DEFAULT_MAX_RESPONSE_BYTES),
        shutdown: cancel,
        batcher: config.batch.map(batch::Batcher::start),
        auth,
        metrics,
    }))
}

/// Threads that keep a workspace per bundle: the runtime's and the batch workers.
fn replanning_threads(config: &ServeConfig) -> usize {
    let runtime = std::thread::available_parallelism().map_or(1, |n| n.get());
    runtime + config.batch.map_or(0, |b| b.workers)
}

/// Checks that `registry` fits the memory budget with `max_sessions` sessions, and sets aside
/// what it needs; else the error says which numbers do not fit.
fn fit_memory(
    state: &ServerState,
    registry: &Registry,
    max_sessions: usize,
    threads: usize,
) -> anyhow::Result<()> {
    let needed = state.budget.check_fit(
        registry.iter().map(|(name, p)| (name.as_str(), p.as_ref())),
        max_sessions,
        threads,
    )?;
    state.budget.reserve_for_bundles(needed);
    tracing::info!(
        bundles = %memory::show_size(needed),
        clients = %memory::show_size(state.budget.budget()),
        "memory set aside for the bundles; the rest is the clients' budget"
    );
    Ok(())
}

/// Puts the first load of the bundle directory in service: SERVING when it holds a policy.
async fn install_bundles(
    state: &ServerState,
    config: &ServeConfig,
    health: &Health,
    loaded: std::io::Result<registry::Loaded>,
) -> anyhow::Result<()> {
    let loaded = match loaded {
        Ok(loaded) => loaded,
        Err(e) if !config.strict => {
            // A volume not mounted or not yet filled: stay up, NOT_SERVING, and look again.
            tracing::error!(dir = %config.bundles.display(), error = %e, "cannot read bundle directory; serving nothing (health NOT_SERVING) until it can be read: read again every 10 s and on SIGHUP");
            return Ok(());
        }
        Err(e) => {
            return Err(e).with_context(|| {
                format!("cannot read bundle directory {}", config.bundles.display())
            });
        }
    };
    for error in &loaded.errors {
        tracing::error!(%error, "skipping bad bundle");
    }
    if config.strict && !loaded.errors.is_empty() {
        anyhow::bail!(
            "{} bad bundle(s) and --strict: {}",
            loaded.errors.len(),
            loaded
                .errors
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join("; ")
        );
    }
    let count = loaded.registry.len();
    fit_memory(
        state,
        &loaded.registry,
        config.max_sessions,
        replanning_threads(config),
    )?;
    state
        .intake
        .bundles_need(loaded.registry.largest_requests(config.max_horizon_limit));
    *state.registry.write().unwrap_or_else(|p| p.into_inner()) = Some(Arc::new(loaded.registry));
    if count == 0 {
        tracing::warn!(dir = %config.bundles.display(), "no bundles loaded; health stays NOT_SERVING (the directory is read again every 10 s and on SIGHUP)");
    } else if !state.shutdown.is_cancelled() {
        health.set(ServingStatus::Serving).await;
        // A signal that came in meanwhile has set NOT_SERVING already: restore it.
        if state.shutdown.is_cancelled() {
            health.set(ServingStatus::NotServing).await;
        }
        tracing::info!(policies = count, "serving");
    }
    Ok(())
}

#[cfg(test)]
mod tests;
