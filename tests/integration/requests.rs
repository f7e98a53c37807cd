//! Requests in transit against a real server: a client that declares large messages on many
//! streams and never finishes them holds at most its connection's budget, oversized declarations
//! are refused from their prefix, calls without a token are refused from their HEADERS, an
//! unfinished request is answered DEADLINE_EXCEEDED after `--request-timeout`, and real clients
//! are served throughout.

use crate::common;

use std::time::{Duration, Instant};

use bytes::Bytes;
use common::{Server, bundle_dir, grpc_request, h2_connect, open_default_session, rss_kib};
use prac::proto;

/// The body a slow client sends: a gRPC prefix declaring `declared` bytes, then zeros.
fn unfinished_message(declared: u32, sent: usize) -> Bytes {
    let mut body = vec![0u8; 5 + sent];
    body[1..5].copy_from_slice(&declared.to_be_bytes());
    Bytes::from(body)
}

/// What came of an attack's streams: grpc-status of each answered one (trailers-only answers
/// carry it in the headers).
struct Attack {
    responses: Vec<h2::client::ResponseFuture>,
    _bodies: Vec<h2::SendStream<Bytes>>,
    _connection: tokio::task::JoinHandle<Result<(), h2::Error>>,
}

/// Opens `streams` unary Step calls on one connection, each declaring a message of `declared`
/// bytes and sending `sent` of them, never finishing.
async fn attack(
    addr: &str,
    streams: usize,
    declared: u32,
    sent: usize,
    token: Option<&str>,
) -> Attack {
    let (send, connection) = h2_connect(addr).await;
    let mut responses = Vec::new();
    let mut bodies = Vec::new();
    for _ in 0..streams {
        let mut request = grpc_request(addr, "/prac.v1.Prac/Step");
        if let Some(token) = token {
            request
                .headers_mut()
                .insert("authorization", format!("Bearer {token}").parse().unwrap());
        }
        let mut ready = send.clone().ready().await.unwrap();
        let (response, mut body) = ready.send_request(request, false).unwrap();
        // Sent as the server's windows allow; a refused stream's data is dropped.
        let _ = body.send_data(unfinished_message(declared, sent), false);
        responses.push(response);
        bodies.push(body);
    }
    Attack {
        responses,
        _bodies: bodies,
        _connection: connection,
    }
}

/// The grpc-status of an answered call, waiting at most `within`; None if unanswered by then.
async fn status_of(response: &mut h2::client::ResponseFuture, within: Duration) -> Option<String> {
    let response = tokio::time::timeout(within, response).await.ok()?.ok()?;
    if let Some(status) = response.headers().get("grpc-status") {
        return Some(status.to_str().unwrap().to_string());
    }
    let mut body = response.into_body();
    while let Some(chunk) = body.data().await {
        let Ok(chunk) = chunk else { break };
        let _ = body.flow_control().release_capacity(chunk.len());
    }
    let trailers = body.trailers().await.ok()??;
    Some(trailers.get("grpc-status")?.to_str().ok()?.to_string())
}

/// Counts of each grpc-status among the answers that came within `within`.
async fn statuses(
    attack: &mut Attack,
    within: Duration,
) -> std::collections::BTreeMap<String, usize> {
    let mut counts = std::collections::BTreeMap::new();
    let deadline = Instant::now() + within;
    for response in &mut attack.responses {
        let left = deadline.saturating_duration_since(Instant::now());
        let status = status_of(response, left)
            .await
            .unwrap_or_else(|| "none".into());
        *counts.entry(status).or_insert(0) += 1;
    }
    counts
}

/// A real client on its own connection: opens a session and steps once, within a second.
async fn real_client_is_served(server: &Server) {
    let served = tokio::time::timeout(Duration::from_secs(1), async {
        let mut client = server.client().await;
        let session = open_default_session(&mut client, "toy").await;
        client
            .step(proto::StepRequest {
                session_id: session,
                observation: vec![0.1; common::OBS],
                new_episode: false,
            })
            .await
            .unwrap();
    })
    .await;
    assert!(served.is_ok(), "a real client was not served within 1 s");
}

const CODE_OUT_OF_RANGE: &str = "11";
const CODE_RESOURCE_EXHAUSTED: &str = "8";
const CODE_DEADLINE_EXCEEDED: &str = "4";
const CODE_UNAUTHENTICATED: &str = "16";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unfinished_messages_hold_at_most_the_connection_budget() {
    let bundles = bundle_dir();
    let server = Server::start(
        bundles.path(),
        &["--request-timeout", "2s", "--max-message-bytes", "262144"],
    );
    server.wait_serving().await;
    let pid = server.child.id();
    let before = rss_kib(pid);

    // Declarations over the limit are refused from their prefix: nothing is buffered.
    let mut oversized = attack(&server.addr, 64, 4_194_303, 60_000, None).await;
    let counts = statuses(&mut oversized, Duration::from_secs(5)).await;
    assert_eq!(counts.get(CODE_OUT_OF_RANGE), Some(&64), "{counts:?}");

    // At the limit, on 256 streams: the connection's 1 MiB budget takes four messages; the other
    // calls are refused at once, and the four are answered DEADLINE_EXCEEDED after the timeout.
    let started = Instant::now();
    let mut held = attack(&server.addr, 256, 262_139, 200_000, None).await;
    tokio::time::sleep(Duration::from_millis(800)).await;
    let during = rss_kib(pid);
    real_client_is_served(&server).await;
    let counts = statuses(&mut held, Duration::from_secs(10)).await;
    assert_eq!(counts.get(CODE_DEADLINE_EXCEEDED), Some(&4), "{counts:?}");
    assert_eq!(
        counts.get(CODE_RESOURCE_EXHAUSTED),
        Some(&252),
        "{counts:?}"
    );
    assert!(
        started.elapsed() >= Duration::from_secs(2),
        "held calls answered before the request timeout"
    );
    let growth_kib = during.saturating_sub(before);
    eprintln!("server RSS {before} KiB before, {during} KiB under attack (+{growth_kib} KiB)");
    // Without the budget these 256 streams made the server reserve 64 MiB.
    assert!(growth_kib < 8 * 1024, "the server grew by {growth_kib} KiB");
    real_client_is_served(&server).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_wide_budget_holds_across_connections() {
    let bundles = bundle_dir();
    let server = Server::start(
        bundles.path(),
        &[
            "--request-timeout",
            "2s",
            "--max-message-bytes",
            "262144",
            "--max-request-bytes-total",
            "2097152",
        ],
    );
    server.wait_serving().await;
    // Two connections fill the 2 MiB; a third is refused with the server's reason.
    let mut first = attack(&server.addr, 4, 262_139, 100_000, None).await;
    let mut second = attack(&server.addr, 4, 262_139, 100_000, None).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut third = attack(&server.addr, 4, 262_139, 100_000, None).await;
    let counts = statuses(&mut third, Duration::from_secs(1)).await;
    assert_eq!(counts.get(CODE_RESOURCE_EXHAUSTED), Some(&4), "{counts:?}");
    // Once the held calls time out, the budget is back.
    let counts = statuses(&mut first, Duration::from_secs(5)).await;
    assert_eq!(counts.get(CODE_DEADLINE_EXCEEDED), Some(&4), "{counts:?}");
    let counts = statuses(&mut second, Duration::from_secs(5)).await;
    assert_eq!(counts.get(CODE_DEADLINE_EXCEEDED), Some(&4), "{counts:?}");
    real_client_is_served(&server).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calls_without_a_token_are_refused_before_their_body_is_read() {
    let bundles = bundle_dir();
    let tokens = bundles.path().join("tokens.txt");
    std::fs::write(&tokens, "alice-7f3c9a0d5e21b864\n").unwrap();
    let server = Server::start(
        bundles.path(),
        &[
            "--auth-tokens",
            tokens.to_str().unwrap(),
            "--idle-timeout",
            "1s",
            "--keepalive-interval",
            "1s",
            "--max-message-bytes",
            "262144",
        ],
    );
    let pid = server.child.id();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let before = rss_kib(pid);
    let mut attacks = Vec::new();
    for token in [None, Some("mallory-0000000000000")] {
        attacks.push(attack(&server.addr, 32, 262_139, 200_000, token).await);
    }
    for attack in &mut attacks {
        let counts = statuses(attack, Duration::from_secs(2)).await;
        assert_eq!(counts.get(CODE_UNAUTHENTICATED), Some(&32), "{counts:?}");
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let growth_kib = rss_kib(pid).saturating_sub(before);
    assert!(growth_kib < 4 * 1024, "the server grew by {growth_kib} KiB");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_streamed_message_must_complete_once_begun() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &["--request-timeout", "1s"]);
    server.wait_serving().await;
    let (send, _connection) = h2_connect(&server.addr).await;
    // A StepStream may wait between messages as long as it likes...
    let request = grpc_request(&server.addr, "/prac.v1.Prac/StepStream");
    let mut ready = send.clone().ready().await.unwrap();
    let (response, mut body) = ready.send_request(request, false).unwrap();
    let mut answer = response.await.unwrap().into_body();
    let trailers = tokio::time::timeout(Duration::from_millis(1500), answer.trailers()).await;
    assert!(trailers.is_err(), "the idle stream ended: {trailers:?}");
    // ...but a message begun must be finished within the request timeout.
    body.send_data(unfinished_message(100, 10), false).unwrap();
    let started = Instant::now();
    let trailers = tokio::time::timeout(Duration::from_secs(5), answer.trailers())
        .await
        .expect("no answer within 5 s")
        .unwrap()
        .unwrap();
    assert_eq!(trailers.get("grpc-status").unwrap(), CODE_DEADLINE_EXCEEDED);
    assert!(started.elapsed() >= Duration::from_millis(900));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_unary_request_without_its_end_of_stream_times_out() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &["--request-timeout", "1s"]);
    server.wait_serving().await;
    let (send, _connection) = h2_connect(&server.addr).await;
    // A whole message, but no END_STREAM: tonic waits for it before the handler runs.
    let request = grpc_request(&server.addr, "/grpc.health.v1.Health/Check");
    let mut ready = send.clone().ready().await.unwrap();
    let (mut response, mut body) = ready.send_request(request, false).unwrap();
    body.send_data(unfinished_message(0, 0), false).unwrap();
    let started = Instant::now();
    let status = status_of(&mut response, Duration::from_secs(5)).await;
    assert_eq!(status.as_deref(), Some(CODE_DEADLINE_EXCEEDED));
    assert!(started.elapsed() >= Duration::from_millis(900));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_that_is_never_read_lets_go_of_a_begun_message() {
    let bundles = bundle_dir();
    let server = Server::start(
        bundles.path(),
        &[
            "--request-timeout",
            "1s",
            "--max-request-bytes-per-connection",
            "4096",
        ],
    );
    server.wait_serving().await;
    let mut client = server.client().await;
    let session = open_default_session(&mut client, "toy").await;
    // A client window of 256 bytes: the server's answers stall after a few, and the stream's
    // handler waits to hand one over instead of reading requests.
    let tcp = tokio::net::TcpStream::connect(&server.addr).await.unwrap();
    let (send, connection) = h2::client::Builder::new()
        .initial_window_size(256)
        .handshake::<_, Bytes>(tcp)
        .await
        .unwrap();
    let _connection = tokio::spawn(connection);
    let request = grpc_request(&server.addr, "/prac.v1.Prac/StepStream");
    let mut ready = send.clone().ready().await.unwrap();
    let (_response, mut body) = ready.send_request(request, false).unwrap();
    // One DATA frame: 40 steps, then a message that declares the connection's whole budget and
    // never finishes. The server takes the frame in at once, so the budget is spent while the
    // handler is still answering the steps.
    let mut frame = Vec::new();
    for t in 0..40 {
        let step = proto::StepRequest {
            session_id: session.clone(),
            observation: vec![0.01 * t as f32; common::OBS],
            new_episode: t == 0,
        };
        frame.extend_from_slice(&common::grpc_frame(&step));
    }
    frame.extend_from_slice(&unfinished_message(4091, 10));
    body.send_data(Bytes::from(frame), false).unwrap();
    tokio::time::sleep(Duration::from_millis(2500)).await;
    // Past the request timeout the stream has ended and let go of its budget: the connection
    // takes a new call again.
    let mut send = send;
    let request = tonic_health::pb::HealthCheckRequest::default();
    let (status, _) = common::h2_unary(
        &mut send,
        &server.addr,
        "/grpc.health.v1.Health/Check",
        &request,
        None,
    )
    .await;
    assert_eq!(
        status, "0",
        "the connection still holds the stalled stream's budget"
    );
}
