//! `prac serve`: the gRPC daemon.

pub mod arrival;
pub mod auth;
pub mod batch;
pub mod config;
pub mod deadline;
pub mod health;
pub mod local;
pub mod metrics;
pub mod registry;
pub mod service;
pub mod session;
pub mod transport;

use std::io::IsTerminal;
use std::sync::{Arc, RwLock};
use std::time::Duration;

use anyhow::Context;
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tonic_health::ServingStatus;

pub use config::{LogFormat, ServeArgs, ServeConfig};
use registry::Registry;
use service::{PracService, ServerState};
use session::Sessions;

use crate::proto::{self, prac_server::PracServer};

/// Sets up tracing on stderr in the chosen format (RUST_LOG overrides the level, default info).
pub fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr);
    let _ = match format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
}

/// Resolves when the process gets SIGINT or SIGTERM.
async fn termination_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term = match tokio::signal::unix::signal(
            tokio::signal::unix::SignalKind::terminate(),
        ) {
            Ok(term) => term,
            Err(e) => {
                tracing::error!(error = %e, "cannot listen for SIGTERM; only SIGINT stops the server");
                let _ = ctrl_c.await;
                return;
            }
        };
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    let _ = ctrl_c.await;
}

/// Hot reload: on each SIGHUP, re-reads the bundle directory ([`Registry::reload`]). New sessions
/// get the new versions; open sessions keep the policy they opened with until they close; a
/// broken new file keeps the old version.
#[cfg(unix)]
async fn reload_on_hangup<F, Fut>(state: Arc<ServerState>, dir: std::path::PathBuf, set_health: F)
where
    F: Fn(ServingStatus) -> Fut,
    Fut: std::future::Future<Output = ()>,
{
    let mut hangup = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()) {
        Ok(hangup) => hangup,
        Err(e) => {
            tracing::error!(error = %e, "cannot listen for SIGHUP; hot reload is off");
            return;
        }
    };
    while hangup.recv().await.is_some() {
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
        state.metrics.reload(report.errors.is_empty());
        let serving = !registry.is_empty();
        *state.registry.write().unwrap_or_else(|p| p.into_inner()) = Some(Arc::new(registry));
        if !state.shutdown.is_cancelled() {
            set_health(if serving {
                ServingStatus::Serving
            } else {
                ServingStatus::NotServing
            })
            .await;
        }
    }
}

/// Runs the server until SIGINT/SIGTERM. Prints `listening on ADDR` on stdout once bound (port 0
/// picks a free port; scripts and tests read that line).
pub async fn run(config: ServeConfig) -> anyhow::Result<()> {
    // A bad token file stops the server: starting without the auth it was asked for is worse.
    let auth = config
        .auth_tokens
        .as_deref()
        .map(auth::Tokens::load)
        .transpose()?;
    let tls = match &config.tls {
        Some((cert, key)) => {
            let read = |p: &std::path::Path| {
                std::fs::read(p).with_context(|| format!("cannot read {}", p.display()))
            };
            Some(transport::tls_acceptor(&read(cert)?, &read(key)?)?)
        }
        None => None,
    };
    let mut limits = config.connections;
    limits.max_connections = transport::connection_cap(limits.max_connections);
    if limits.max_connections < config.connections.max_connections {
        tracing::warn!(
            max_connections = limits.max_connections,
            asked = config.connections.max_connections,
            "the open-file limit (ulimit -n) allows fewer connections than asked; raise it to serve more"
        );
    }
    // A directory that cannot be read stops the server before its ready line: a supervisor
    // waiting for `listening on` must not see it from a server that is about to exit.
    std::fs::read_dir(&config.bundles)
        .with_context(|| format!("cannot read bundle directory {}", config.bundles.display()))?;
    let listener = TcpListener::bind(config.listen)
        .await
        .with_context(|| format!("cannot listen on {}", config.listen))?;
    let addr = listener.local_addr()?;
    let metrics_listener = match config.metrics_listen {
        Some(at) => Some(
            TcpListener::bind(at)
                .await
                .with_context(|| format!("cannot listen for metrics on {at}"))?,
        ),
        None => None,
    };

    let shutdown = CancellationToken::new();
    let health = tonic_health::server::HealthReporter::new();
    let health_service = tonic_health::pb::health_server::HealthServer::new(
        health::ShutdownAwareHealth::new(health.clone(), shutdown.clone()),
    );
    let set_health = move |status: ServingStatus| {
        let health = health.clone();
        async move {
            health.set_service_status("", status).await;
            health
                .set_service_status(
                    <PracServer<PracService> as tonic::server::NamedService>::NAME,
                    status,
                )
                .await;
        }
    };
    set_health(ServingStatus::NotServing).await;

    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
        .build_v1()
        .context("building the reflection service")?;

    let state = Arc::new(ServerState {
        registry: RwLock::new(None),
        sessions: Sessions::new(config.max_sessions, config.session_ttl),
        max_horizon_limit: config.max_horizon_limit,
        max_message_bytes: config.max_message_bytes,
        shutdown: shutdown.clone(),
        batcher: config.batch.map(batch::Batcher::start),
        auth,
        metrics: metrics::Metrics::default(),
    });
    let prac = PracServer::new(PracService {
        state: state.clone(),
    })
    .max_decoding_message_size(config.max_message_bytes)
    .max_encoding_message_size(config.max_message_bytes);

    let routes = tonic::service::Routes::new(health_service)
        .add_service(reflection)
        .add_service(prac);
    let connections = Arc::new(transport::ConnectionStats::default());
    let server = transport::serve_grpc(
        listener,
        tls,
        routes,
        limits,
        connections.clone(),
        shutdown.clone(),
    );
    let mut server = tokio::spawn(async move {
        server.await;
        anyhow::Ok(())
    });
    if let Some(listener) = metrics_listener {
        // Printed before the gRPC address, which scripts wait for as the ready line.
        println!("metrics on {}", listener.local_addr()?);
        tokio::spawn(metrics::serve(
            listener,
            state.clone(),
            limits,
            shutdown.clone(),
        ));
    }
    println!("listening on {addr}");
    tracing::info!(%addr, bundles = %config.bundles.display(), "listening");

    tokio::spawn({
        let shutdown = shutdown.clone();
        let set_health = set_health.clone();
        async move {
            termination_signal().await;
            tracing::info!("shutdown requested: draining");
            // Health first, so watchers and load balancers see NOT_SERVING before streams end.
            set_health(ServingStatus::NotServing).await;
            shutdown.cancel();
        }
    });

    let dir = config.bundles.clone();
    let load = tokio::task::spawn_blocking(move || Registry::load_dir(&dir));
    let loaded = tokio::select! {
        loaded = load => loaded?,
        _ = shutdown.cancelled() => {
            // Stopped before the bundles loaded: no session exists, only the listener to close.
            let _ = tokio::time::timeout(config.drain_timeout, &mut server).await;
            return Ok(());
        }
    };
    let loaded = match loaded {
        Ok(loaded) => loaded,
        Err(e) => {
            shutdown.cancel();
            return Err(e).with_context(|| {
                format!("cannot read bundle directory {}", config.bundles.display())
            });
        }
    };
    for error in &loaded.errors {
        tracing::error!(%error, "skipping bad bundle");
    }
    if config.strict && !loaded.errors.is_empty() {
        shutdown.cancel();
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
    *state.registry.write().unwrap_or_else(|p| p.into_inner()) = Some(Arc::new(loaded.registry));
    if count == 0 {
        tracing::warn!(dir = %config.bundles.display(), "no bundles loaded; health stays NOT_SERVING");
    } else if !shutdown.is_cancelled() {
        set_health(ServingStatus::Serving).await;
        // A signal that came in meanwhile has set NOT_SERVING already: restore it.
        if shutdown.is_cancelled() {
            set_health(ServingStatus::NotServing).await;
        }
        tracing::info!(policies = count, "serving");
    }

    #[cfg(unix)]
    let reloader = tokio::spawn(reload_on_hangup(
        state.clone(),
        config.bundles.clone(),
        set_health.clone(),
    ));
    #[cfg(not(unix))]
    let reloader = tokio::spawn(async {});

    let evictor = tokio::spawn({
        let state = state.clone();
        let period =
            (config.session_ttl / 4).clamp(Duration::from_millis(10), Duration::from_secs(1));
        async move {
            let mut tick = tokio::time::interval(period);
            loop {
                tick.tick().await;
                let evicted = state.sessions.evict_idle();
                state.metrics.evicted(evicted);
            }
        }
    });

    tokio::select! {
        result = &mut server => {
            evictor.abort();
            reloader.abort();
            return result?.context("server failed");
        }
        _ = shutdown.cancelled() => {}
    }
    evictor.abort();
    reloader.abort();
    match tokio::time::timeout(config.drain_timeout, &mut server).await {
        Ok(result) => {
            result?.context("server failed")?;
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
