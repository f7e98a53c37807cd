//! Starts the real `prac serve` binary on an ephemeral port over bundles written by test code.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use prac::bundle;
use prac::proto::prac_client::PracClient;
use tonic::transport::Channel;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

pub use prac::testing::{TOY_ACT as ACT, TOY_OBS as OBS, toy_policy};

/// A temporary bundle directory holding `toy.safetensors` (and whatever else a test adds).
pub fn bundle_dir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    bundle::save(&toy_policy("toy", 1), &dir.path().join("toy.safetensors")).unwrap();
    dir
}

pub struct Server {
    pub child: Child,
    pub addr: String,
    /// stdout lines before `listening on ADDR`.
    pub preamble: Vec<String>,
    pub stderr_path: PathBuf,
    _stderr_dir: tempfile::TempDir,
}

impl Server {
    /// Starts `prac serve --listen 127.0.0.1:0 --bundles DIR ARGS..` and waits for its address.
    pub fn start(bundles: &Path, args: &[&str]) -> Server {
        let mut command = Command::new(env!("CARGO_BIN_EXE_prac"));
        command
            .args(["serve", "--listen", "127.0.0.1:0", "--bundles"])
            .arg(bundles)
            .args(args);
        Server::spawn(command)
    }

    /// Runs `command` (a `prac serve` on 127.0.0.1:0, or a shell that execs one) and waits for
    /// its address.
    pub fn spawn(mut command: Command) -> Server {
        let stderr_dir = tempfile::tempdir().unwrap();
        let stderr_path = stderr_dir.path().join("stderr.log");
        let mut child = command
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&stderr_path).unwrap())
            .spawn()
            .unwrap();
        let stdout = child.stdout.take().unwrap();
        let mut stdout = BufReader::new(stdout);
        // Lines before the ready line (e.g. `metrics on ADDR`).
        let mut preamble = Vec::new();
        let addr = loop {
            let mut line = String::new();
            stdout.read_line(&mut line).unwrap();
            if let Some(addr) = line.trim().strip_prefix("listening on ") {
                break addr.to_string();
            }
            if line.is_empty() {
                panic!(
                    "no address from the server; stderr: {}",
                    std::fs::read_to_string(&stderr_path).unwrap_or_default()
                );
            }
            preamble.push(line.trim().to_string());
        };
        Server {
            child,
            addr,
            preamble,
            stderr_path,
            _stderr_dir: stderr_dir,
        }
    }

    pub async fn channel(&self) -> Channel {
        prac::client::channel(&self.addr).await.unwrap()
    }

    /// A TLS channel to a server whose certificate (PEM) names localhost.
    pub async fn tls_channel(&self, cert_pem: &str) -> Channel {
        self.try_tls_channel(cert_pem).await.unwrap()
    }

    /// A TLS channel trusting `cert_pem` alone (a certificate for localhost), or why none
    /// could be made.
    pub async fn try_tls_channel(
        &self,
        cert_pem: &str,
    ) -> Result<Channel, tonic::transport::Error> {
        let port = self.addr.rsplit(':').next().unwrap();
        let tls = tonic::transport::ClientTlsConfig::new()
            .ca_certificate(tonic::transport::Certificate::from_pem(cert_pem))
            .domain_name("localhost");
        Channel::from_shared(format!("https://localhost:{port}"))
            .unwrap()
            .tls_config(tls)?
            .connect()
            .await
    }

    pub async fn client(&self) -> PracClient<Channel> {
        prac::client::connect(&self.addr).await.unwrap()
    }

    pub async fn health(&self, service: &str) -> ServingStatus {
        let mut health = HealthClient::new(self.channel().await);
        let response = health
            .check(HealthCheckRequest {
                service: service.to_string(),
            })
            .await
            .unwrap();
        response.into_inner().status()
    }

    /// Waits until the server reports SERVING (bundles loaded).
    pub async fn wait_serving(&self) {
        let start = Instant::now();
        while self.health("prac.v1.Prac").await != ServingStatus::Serving {
            assert!(
                start.elapsed() < Duration::from_secs(20),
                "server never became SERVING"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    pub fn stderr(&self) -> String {
        std::fs::read_to_string(&self.stderr_path).unwrap_or_default()
    }

    pub fn signal(&self, name: &str) {
        let status = Command::new("kill")
            .args([&format!("-{name}"), &self.child.id().to_string()])
            .status()
            .unwrap();
        assert!(status.success());
    }

    /// Waits for the process to exit; None if it is still running after `timeout`.
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        let start = Instant::now();
        while start.elapsed() < timeout {
            if let Some(status) = self.child.try_wait().unwrap() {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Opens a session on `policy` with the server's default options; returns its id.
pub async fn open_default_session(client: &mut PracClient<Channel>, policy: &str) -> String {
    client
        .open_session(prac::proto::OpenSessionRequest {
            local_steps: 0,
            policy: policy.into(),
            options: None,
            resume: None,
        })
        .await
        .unwrap_or_else(|e| panic!("opening a session on {policy}: {e}"))
        .into_inner()
        .session_id
}

/// A raw HTTP/2 connection to the server: no client-side deadlines, frames as written.
pub async fn h2_connect(
    addr: &str,
) -> (
    h2::client::SendRequest<bytes::Bytes>,
    tokio::task::JoinHandle<Result<(), h2::Error>>,
) {
    let tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    let (send, connection) = h2::client::handshake(tcp).await.unwrap();
    (send, tokio::spawn(connection))
}

/// The headers of a gRPC call to `path`.
pub fn grpc_request(addr: &str, path: &str) -> http::Request<()> {
    http::Request::builder()
        .method("POST")
        .uri(format!("http://{addr}{path}"))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(())
        .unwrap()
}

/// One gRPC message: the 5-byte prefix and the encoded message.
pub fn grpc_frame(message: &impl prost::Message) -> bytes::Bytes {
    let body = message.encode_to_vec();
    let mut framed = Vec::with_capacity(5 + body.len());
    framed.push(0);
    framed.extend_from_slice(&(body.len() as u32).to_be_bytes());
    framed.extend_from_slice(&body);
    bytes::Bytes::from(framed)
}

/// A unary call over a raw HTTP/2 connection, with `grpc-timeout` set to `timeout` if given
/// (the server alone enforces it): the grpc-status and the response body.
pub async fn h2_unary(
    send: &mut h2::client::SendRequest<bytes::Bytes>,
    addr: &str,
    path: &str,
    message: &impl prost::Message,
    timeout: Option<&str>,
) -> (String, Vec<u8>) {
    let mut request = grpc_request(addr, path);
    if let Some(timeout) = timeout {
        request
            .headers_mut()
            .insert("grpc-timeout", timeout.parse().unwrap());
    }
    let mut ready = send.clone().ready().await.unwrap();
    let (response, mut body) = ready.send_request(request, false).unwrap();
    body.send_data(grpc_frame(message), true).unwrap();
    let response = response.await.unwrap();
    // A trailers-only answer carries its status in the headers.
    let headers_status = response.headers().get("grpc-status").cloned();
    let mut stream = response.into_body();
    let mut data = Vec::new();
    while let Some(chunk) = stream.data().await {
        let chunk = chunk.unwrap();
        let _ = stream.flow_control().release_capacity(chunk.len());
        data.extend_from_slice(&chunk);
    }
    let trailers = stream.trailers().await.unwrap().unwrap_or_default();
    let status = trailers
        .get("grpc-status")
        .cloned()
        .or(headers_status)
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    (status, data)
}

/// A self-signed certificate for localhost and its key, written into `dir` as cert.pem and
/// key.pem: (the certificate's PEM, the certificate file, the key file).
pub fn tls_files(dir: &Path) -> (String, PathBuf, PathBuf) {
    let certified = rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).unwrap();
    let (cert, key) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert, certified.cert.pem()).unwrap();
    std::fs::write(&key, certified.signing_key.serialize_pem()).unwrap();
    (certified.cert.pem(), cert, key)
}

/// Resident memory of a process, in KiB.
pub fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap()
}

/// The whole answer (status line, headers, body) to `GET path` at `addr` over HTTP/1.1.
pub fn http_get(addr: &str, path: &str) -> String {
    use std::io::{Read, Write};
    let mut stream = std::net::TcpStream::connect(addr).unwrap();
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut text = String::new();
    stream.read_to_string(&mut text).unwrap();
    text
}

/// The answer to `GET /metrics` at `addr`, checked to be 200.
pub fn scrape(addr: &str) -> String {
    let text = http_get(addr, "/metrics");
    assert!(text.starts_with("HTTP/1.1 200"), "{text}");
    text
}

/// The value of the sample line that starts with `name` (labels included).
pub fn sample(text: &str, name: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(name).and_then(|v| v.trim().parse().ok()))
        .unwrap_or_else(|| panic!("no {name} in:\n{text}"))
}

/// Where a server started with `--metrics-listen` serves its metrics.
pub fn metrics_address(server: &Server) -> String {
    server
        .preamble
        .iter()
        .find_map(|l| l.strip_prefix("metrics on "))
        .expect("the metrics address")
        .to_string()
}
