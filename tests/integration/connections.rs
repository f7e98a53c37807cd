//! Connection limits against a real server: silent connections are closed, the connection cap
//! holds, idle connections get GOAWAY, streams per connection are capped, a stream whose client
//! never reads stalls alone, and the TLS port and metrics endpoint shrug off slow, plaintext,
//! oversized and numerous clients.

use crate::common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use bytes::Bytes;
use common::{
    Server, bundle_dir, grpc_frame, grpc_request, h2_connect, h2_unary, metrics_address,
    open_default_session, rss_kib, tls_files,
};
use prac::proto;

/// Whether the server closes `stream` within `within` (EOF or a reset), sending at most a GOAWAY.
fn closed_within(stream: &mut TcpStream, within: Duration) -> bool {
    stream.set_read_timeout(Some(within)).unwrap();
    let start = Instant::now();
    let mut buf = [0u8; 4096];
    loop {
        match stream.read(&mut buf) {
            Ok(0) => return true,
            // HTTP/2 SETTINGS and GOAWAY frames may come first.
            Ok(_) if start.elapsed() < within => continue,
            Ok(_) => return false,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                return false;
            }
            Err(_) => return true,
        }
    }
}

async fn wait_healthy(server: &Server, within: Duration) {
    let start = Instant::now();
    loop {
        let attempt = tokio::time::timeout(Duration::from_secs(1), server.health("")).await;
        if attempt.is_ok() {
            return;
        }
        assert!(
            start.elapsed() < within,
            "no health answer within {within:?}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_connections_are_closed_and_the_cap_holds() {
    let bundles = bundle_dir();
    let server = Server::start(
        bundles.path(),
        &["--handshake-timeout", "500ms", "--max-connections", "8"],
    );
    server.wait_serving().await;
    let mut silent: Vec<TcpStream> = (0..40)
        .map(|_| TcpStream::connect(&server.addr).unwrap())
        .collect();
    let start = Instant::now();
    for (i, stream) in silent.iter_mut().enumerate() {
        assert!(
            closed_within(stream, Duration::from_secs(5)),
            "silent connection {i} still open after {:?}",
            start.elapsed()
        );
    }
    // Freed: a real client is served again.
    wait_healthy(&server, Duration::from_secs(5)).await;
}

#[test]
fn the_connection_cap_follows_the_open_file_limit() {
    let bundles = bundle_dir();
    let mut command = std::process::Command::new("sh");
    command.arg("-c").arg(format!(
        "ulimit -n 200 && exec {} serve --listen 127.0.0.1:0 --bundles {} --max-connections 5000",
        env!("CARGO_BIN_EXE_prac"),
        bundles.path().display()
    ));
    // The warning comes before the ready line.
    let server = Server::spawn(command);
    let stderr = server.stderr();
    assert!(
        stderr.contains("max_connections=136") && stderr.contains("ulimit -n"),
        "{stderr}"
    );
}

/// A unary health check over a raw HTTP/2 connection; its grpc-status.
async fn h2_health_check(send: &mut h2::client::SendRequest<Bytes>, addr: &str) -> String {
    let request = tonic_health::pb::HealthCheckRequest::default();
    h2_unary(send, addr, "/grpc.health.v1.Health/Check", &request, None)
        .await
        .0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_connections_get_goaway_and_clients_reconnect() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &["--idle-timeout", "300ms"]);
    server.wait_serving().await;
    let (mut send, connection) = h2_connect(&server.addr).await;
    assert_eq!(h2_health_check(&mut send, &server.addr).await, "0");
    // No call in flight: the server ends the connection.
    let ended = tokio::time::timeout(Duration::from_secs(5), connection).await;
    assert!(ended.is_ok(), "the idle connection is still open");

    // A tonic channel reconnects by itself after the server's GOAWAY.
    let channel = server.channel().await;
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    for _ in 0..2 {
        health
            .check(tonic_health::pb::HealthCheckRequest::default())
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(700)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streams_per_connection_are_capped() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &["--max-streams-per-connection", "7"]);
    server.wait_serving().await;
    let (mut send, _connection) = h2_connect(&server.addr).await;
    // The server's SETTINGS arrive with its first answer.
    assert_eq!(h2_health_check(&mut send, &server.addr).await, "0");
    assert_eq!(send.current_max_send_streams(), 7);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_whose_client_never_reads_stalls_alone() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &[]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let session = open_default_session(&mut client, "toy").await;

    // A small receive window, so that the unread answers cost this client little: the test is
    // whether the server holds the stalled stream's requests without harm to the connection.
    let tcp = tokio::net::TcpStream::connect(&server.addr).await.unwrap();
    let (mut send, connection) = h2::client::Builder::new()
        .initial_window_size(2048)
        .handshake::<_, Bytes>(tcp)
        .await
        .unwrap();
    let connection = tokio::spawn(connection);
    let ready = send.clone().ready().await.unwrap();
    let mut ready = ready;
    let (_response, mut requests) = ready
        .send_request(
            grpc_request(&server.addr, "/prac.v1.Prac/StepStream"),
            false,
        )
        .unwrap();
    // 20,000 small requests, one DATA frame each, whose answers are never read.
    let step = grpc_frame(&proto::StepRequest {
        session_id: session.clone(),
        observation: vec![0.1, 0.2, 0.3],
        new_episode: false,
    });
    for _ in 0..20_000 {
        requests.send_data(step.clone(), false).unwrap();
    }
    tokio::time::sleep(Duration::from_secs(1)).await;
    // Other calls on the same connection still go through.
    for _ in 0..3 {
        assert_eq!(h2_health_check(&mut send, &server.addr).await, "0");
    }
    assert!(!connection.is_finished(), "the connection was closed");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_tls_port_closes_plaintext_and_slow_handshakes() {
    let bundles = bundle_dir();
    let (cert_pem, cert, key) = tls_files(bundles.path());
    let server = Server::start(
        bundles.path(),
        &[
            "--tls-cert",
            cert.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
            "--handshake-timeout",
            "500ms",
        ],
    );
    // Plaintext HTTP/2 to the TLS port: refused at once.
    let mut plain = TcpStream::connect(&server.addr).unwrap();
    plain
        .write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n")
        .unwrap();
    assert!(closed_within(&mut plain, Duration::from_secs(2)));
    // A handshake that never finishes: half a ClientHello, then silence.
    let mut slow: Vec<TcpStream> = (0..20)
        .map(|_| {
            let mut s = TcpStream::connect(&server.addr).unwrap();
            s.write_all(&[0x16, 0x03, 0x01, 0x00, 0xff]).unwrap();
            s
        })
        .collect();
    for s in &mut slow {
        assert!(closed_within(s, Duration::from_secs(5)));
    }
    // Real TLS clients are served throughout.
    let channel = server.tls_channel(&cert_pem).await;
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    health
        .check(tonic_health::pb::HealthCheckRequest::default())
        .await
        .unwrap();
}

fn scrape_status(addr: &str, extra_header: &str) -> String {
    let mut stream = TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let _ = write!(
        stream,
        "GET /metrics HTTP/1.1\r\nHost: {addr}\r\n{extra_header}\r\n"
    );
    let mut text = String::new();
    let _ = stream.read_to_string(&mut text);
    text.lines().next().unwrap_or_default().to_string()
}

#[test]
fn the_metrics_endpoint_sheds_slow_huge_and_numerous_clients() {
    let bundles = bundle_dir();
    let server = Server::start(
        bundles.path(),
        &[
            "--metrics-listen",
            "127.0.0.1:0",
            "--handshake-timeout",
            "500ms",
        ],
    );
    let addr = metrics_address(&server);
    assert!(scrape_status(&addr, "").starts_with("HTTP/1.1 200"));
    // Silent and numerous: 100 connections that send nothing are all closed.
    let mut silent: Vec<TcpStream> = (0..100)
        .map(|_| TcpStream::connect(&addr).unwrap())
        .collect();
    for s in &mut silent {
        assert!(closed_within(s, Duration::from_secs(5)));
    }
    // A request head over 16 KiB is refused.
    let huge = format!("X-Padding: {}\r\n", "a".repeat(64 * 1024));
    let status = scrape_status(&addr, &huge);
    assert!(!status.starts_with("HTTP/1.1 200"), "{status}");
    // A client that sends half a request and stalls is closed.
    let mut stalled = TcpStream::connect(&addr).unwrap();
    stalled.write_all(b"GET /metr").unwrap();
    assert!(closed_within(&mut stalled, Duration::from_secs(5)));
    assert!(scrape_status(&addr, "").starts_with("HTTP/1.1 200"));
}

/// Not a test: the figures of docs/operations.md ("Limits"). Run with
/// `cargo test --release --test integration connections:: -- --ignored --nocapture`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement; prints figures"]
async fn measure_connection_stream_and_tls_costs() {
    let bundles = bundle_dir();
    let (_, cert, key) = tls_files(bundles.path());
    let server = Server::start(
        bundles.path(),
        &["--max-connections", "4000", "--handshake-timeout", "60s"],
    );
    server.wait_serving().await;
    let pid = server.child.id();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let base = rss_kib(pid);

    // 1,000 connections that completed the HTTP/2 handshake and sent nothing else.
    let mut connections = Vec::new();
    for _ in 0..1000 {
        connections.push(h2_connect(&server.addr).await);
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let with_connections = rss_kib(pid);
    println!(
        "idle HTTP/2 connections: 1000 held, {:.1} KiB each",
        (with_connections - base) as f64 / 1000.0
    );

    // 4 x 256 StepStreams with headers only (the most a connection may open by default); the
    // server answers each with its response headers.
    let mut streams = Vec::new();
    for (send, _) in connections.iter_mut().take(4) {
        for _ in 0..256 {
            let mut ready = send.clone().ready().await.unwrap();
            let (response, body) = ready
                .send_request(
                    grpc_request(&server.addr, "/prac.v1.Prac/StepStream"),
                    false,
                )
                .unwrap();
            streams.push((response.await.unwrap(), body));
        }
    }
    // A 257th on one connection is not served until one of the 256 ends.
    let mut ready = connections[0].0.clone().ready().await.unwrap();
    let (response, _body) = ready
        .send_request(
            grpc_request(&server.addr, "/prac.v1.Prac/StepStream"),
            false,
        )
        .unwrap();
    let served = tokio::time::timeout(Duration::from_millis(500), response).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let with_streams = rss_kib(pid);
    println!(
        "header-only StepStreams: 1024 held on 4 connections, {:.1} KiB each; a 257th on one connection {}",
        (with_streams - with_connections) as f64 / 1024.0,
        if served.is_err() {
            "waits"
        } else {
            "was served"
        }
    );
    drop(streams);
    drop(connections);
    drop(server);

    // TLS handshakes per second: 2 clients back to back, for 3 s, on the same 2 cores.
    let server = Server::start(
        bundles.path(),
        &[
            "--tls-cert",
            cert.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
        ],
    );
    let mut roots = tokio_rustls::rustls::RootCertStore::empty();
    use tokio_rustls::rustls::pki_types::CertificateDer;
    use tokio_rustls::rustls::pki_types::pem::PemObject;
    for c in CertificateDer::pem_file_iter(&cert).unwrap() {
        roots.add(c.unwrap()).unwrap();
    }
    let provider = std::sync::Arc::new(tokio_rustls::rustls::crypto::ring::default_provider());
    let mut config = tokio_rustls::rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_no_client_auth();
    config.alpn_protocols = vec![b"h2".to_vec()];
    // Fresh sessions only: no resumption.
    config.resumption = tokio_rustls::rustls::client::Resumption::disabled();
    let connector = tokio_rustls::TlsConnector::from(std::sync::Arc::new(config));
    let until = Instant::now() + Duration::from_secs(3);
    let mut tasks = Vec::new();
    for _ in 0..2 {
        let connector = connector.clone();
        let addr = server.addr.clone();
        tasks.push(tokio::spawn(async move {
            let mut done = 0u64;
            while Instant::now() < until {
                let tcp = tokio::net::TcpStream::connect(&addr).await.unwrap();
                let name = "localhost".try_into().unwrap();
                connector.connect(name, tcp).await.unwrap();
                done += 1;
            }
            done
        }));
    }
    let mut total = 0;
    for task in tasks {
        total += task.await.unwrap();
    }
    println!(
        "TLS handshakes: {:.0}/s (2 clients on the same 2 cores, full handshakes)",
        total as f64 / 3.0
    );
}

/// Keeps `count` silent connections open to `addr`, replacing the oldest with a new one every
/// 10 ms (100 a second), until `stop`.
fn flood_silent(
    addr: String,
    count: usize,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> std::thread::JoinHandle<usize> {
    std::thread::spawn(move || {
        let mut open = std::collections::VecDeque::new();
        let mut made = 0;
        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
            if let Ok(stream) = TcpStream::connect(&addr) {
                open.push_back(stream);
                made += 1;
            }
            while open.len() > count {
                open.pop_front();
            }
            if open.len() >= count {
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        made
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_silent_connections_does_not_lock_out_real_clients() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &["--max-connections", "64"]);
    server.wait_serving().await;
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    // Twice the cap, refreshed continuously: without shedding, the cap stays full for the 10 s
    // handshake timeout and a new client is closed on accept.
    let flood = flood_silent(server.addr.clone(), 128, stop.clone());
    tokio::time::sleep(Duration::from_millis(500)).await;
    for round in 0..10 {
        let served = tokio::time::timeout(Duration::from_secs(1), async {
            assert_eq!(
                server.health("").await,
                tonic_health::pb::health_check_response::ServingStatus::Serving
            );
            let mut client = server.client().await;
            open_default_session(&mut client, "toy").await;
        })
        .await;
        assert!(served.is_ok(), "round {round}: not served within 1 s");
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let made = flood.join().unwrap();
    assert!(made > 300, "the flood made only {made} connections");
}

/// `prac serve` under a shell's open-file limit (`ulimit ARGS` first).
fn serve_under_ulimit(ulimit: &str, bundles: &std::path::Path) -> std::process::Child {
    std::process::Command::new("sh")
        .arg("-c")
        .arg(format!(
            "ulimit {ulimit} && exec {} serve --listen 127.0.0.1:0 --bundles {}",
            env!("CARGO_BIN_EXE_prac"),
            bundles.display()
        ))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

#[test]
fn a_low_open_file_limit_is_raised_or_refused() {
    let bundles = bundle_dir();
    // Soft and hard limit 64: nothing to raise, and no connection fits. The server says so.
    let mut child = serve_under_ulimit("-n 64", bundles.path());
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() && start.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = child.kill();
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "the server started: {stderr}");
    assert!(
        stderr.contains("open-file limit is 64") && stderr.contains("ulimit -Hn"),
        "{stderr}"
    );
    assert!(!String::from_utf8_lossy(&out.stdout).contains("listening on"));

    // Soft limit 64 under a higher hard limit: raised to the hard limit, and serving.
    let hard: u64 = std::fs::read_to_string("/proc/self/limits")
        .unwrap()
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .and_then(|l| l.split_whitespace().nth(4)?.parse().ok())
        .unwrap();
    assert!(
        hard > 1024,
        "this test needs a hard open-file limit above 1024"
    );
    let mut child = serve_under_ulimit("-Sn 64", bundles.path());
    let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    std::io::BufRead::read_line(&mut stdout, &mut line).unwrap();
    let limits = std::fs::read_to_string(format!("/proc/{}/limits", child.id())).unwrap();
    let _ = child.kill();
    let _ = child.wait();
    assert!(line.starts_with("listening on"), "{line}");
    let soft = limits
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .and_then(|l| l.split_whitespace().nth(3))
        .unwrap()
        .to_string();
    assert_eq!(soft, hard.min(1 << 20).to_string(), "{limits}");
}

#[test]
fn slow_clients_cannot_starve_the_metrics_endpoint() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &["--metrics-listen", "127.0.0.1:0"]);
    let addr = metrics_address(&server);
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    // 1,000 clients each sending one byte of a request every 100 ms, reconnecting when closed.
    let slow: Vec<_> = (0..4)
        .map(|_| {
            let (addr, stop) = (addr.clone(), stop.clone());
            std::thread::spawn(move || {
                let request = b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n";
                let mut clients: Vec<(Option<TcpStream>, usize)> =
                    (0..250).map(|_| (None, 0)).collect();
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    for (stream, sent) in &mut clients {
                        if stream.is_none() {
                            *stream = TcpStream::connect(&addr).ok();
                            *sent = 0;
                        }
                        let Some(s) = stream else { continue };
                        // Never the last byte: the request stays incomplete.
                        let byte = &request[*sent % (request.len() - 1)..][..1];
                        if s.write_all(byte).is_err() {
                            *stream = None;
                        }
                        *sent += 1;
                    }
                    std::thread::sleep(Duration::from_millis(100));
                }
            })
        })
        .collect();
    std::thread::sleep(Duration::from_millis(500));
    for scrape in 0..8 {
        let started = Instant::now();
        let status = scrape_status(&addr, "");
        assert!(
            status.starts_with("HTTP/1.1 200") && started.elapsed() < Duration::from_secs(1),
            "scrape {scrape}: {status:?} after {:?}",
            started.elapsed()
        );
        std::thread::sleep(Duration::from_secs(1));
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    for thread in slow {
        thread.join().unwrap();
    }
}

/// One round of streams that are never read: `connections` connections with `per_connection`
/// StepStreams each (one per session of `sessions`), `steps` steps sent on each, then every
/// connection dropped, which cancels its streams.
async fn unread_stream_round(addr: &str, sessions: &[String], connections: usize, steps: usize) {
    let per_connection = sessions.len() / connections;
    let mut streams = Vec::new();
    let mut tasks = Vec::new();
    let mut senders = Vec::new();
    for c in 0..connections {
        // A client window large enough that h2's guard against small DATA frames never closes
        // the connection while the answers go unread.
        let tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
        let (send, connection) = h2::client::Builder::new()
            .initial_window_size(1 << 20)
            .initial_connection_window_size(1 << 30)
            .handshake(tcp)
            .await
            .unwrap();
        tasks.push(tokio::spawn(connection));
        senders.push(send.clone());
        for session in &sessions[c * per_connection..(c + 1) * per_connection] {
            let request = grpc_request(addr, "/prac.v1.Prac/StepStream");
            let mut ready = send.clone().ready().await.unwrap();
            let (response, mut body) = ready.send_request(request, false).unwrap();
            for t in 0..steps {
                let step = proto::StepRequest {
                    session_id: session.clone(),
                    observation: vec![0.01 * t as f32; common::OBS],
                    new_episode: false,
                };
                let _ = body.send_data(grpc_frame(&step), false);
            }
            streams.push((response, body));
        }
    }
    // The server takes in what the windows allow and answers until the streams stall.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    drop(streams);
    drop(senders);
    for task in tasks {
        task.abort();
    }
    tokio::time::sleep(Duration::from_millis(1000)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn memory_comes_back_after_cancelled_streams() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &["--max-sessions", "4096"]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let mut sessions = Vec::new();
    for _ in 0..2000 {
        sessions.push(open_default_session(&mut client, "toy").await);
    }
    let pid = server.child.id();
    let mut after = Vec::new();
    for _ in 0..10 {
        unread_stream_round(&server.addr, &sessions, 20, 12).await;
        after.push(rss_kib(pid));
    }
    eprintln!("server RSS after each round (KiB): {after:?}");
    let growth = after[9].saturating_sub(after[0]);
    assert!(
        growth < 4 * 1024,
        "ten rounds grew the server by {growth} KiB past the first: {after:?}"
    );
}
