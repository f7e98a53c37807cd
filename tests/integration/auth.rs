//! Bearer-token auth against the real server: calls without a valid token are UNAUTHENTICATED,
//! a session belongs to the token that opened it (another token gets PERMISSION_DENIED), and
//! health stays open for probes.

use crate::common;

use common::{OBS, Server, bundle_dir};
use prac::proto;
use tonic::Code;
use tonic::metadata::MetadataValue;

const ALICE: &str = "alice-7f3c9a0d5e21b864";
const BOB: &str = "bob-0a9e8d7c6b5a4f3e";

fn with_token<T>(message: T, token: Option<&str>) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    if let Some(token) = token {
        let value: MetadataValue<_> = format!("Bearer {token}").parse().unwrap();
        request.metadata_mut().insert("authorization", value);
    }
    request
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_belong_to_the_token_that_opened_them() {
    let bundles = bundle_dir();
    let tokens = bundles.path().join("tokens.txt");
    std::fs::write(&tokens, format!("# operators\n{ALICE}\n{BOB}\n")).unwrap();
    let server = Server::start(bundles.path(), &["--auth-tokens", tokens.to_str().unwrap()]);
    // Health needs no token.
    server.wait_serving().await;
    let mut client = server.client().await;

    for token in [None, Some("mallory-0000000000000000")] {
        let status = client
            .list_policies(with_token(proto::ListPoliciesRequest {}, token))
            .await
            .unwrap_err();
        assert_eq!(status.code(), Code::Unauthenticated, "{status:?}");
    }
    let open = proto::OpenSessionRequest {
        local_steps: 0,
        policy: "toy".into(),
        options: None,
        resume: None,
    };
    assert_eq!(
        client
            .open_session(with_token(open.clone(), None))
            .await
            .unwrap_err()
            .code(),
        Code::Unauthenticated
    );
    let session = client
        .open_session(with_token(open, Some(ALICE)))
        .await
        .unwrap()
        .into_inner()
        .session_id;
    let step = proto::StepRequest {
        session_id: session.clone(),
        observation: vec![0.1; OBS],
        new_episode: true,
    };
    // Bob holds a valid token but not this session: the leaked id is useless to him.
    let denied = client
        .step(with_token(step.clone(), Some(BOB)))
        .await
        .unwrap_err();
    assert_eq!(denied.code(), Code::PermissionDenied, "{denied:?}");
    let get = proto::GetPlanRequest {
        session_id: session.clone(),
    };
    assert_eq!(
        client
            .get_plan(with_token(get.clone(), Some(BOB)))
            .await
            .unwrap_err()
            .code(),
        Code::PermissionDenied
    );
    let close = proto::CloseSessionRequest {
        session_id: session.clone(),
    };
    assert_eq!(
        client
            .close_session(with_token(close.clone(), Some(BOB)))
            .await
            .unwrap_err()
            .code(),
        Code::PermissionDenied
    );
    // Bob's attempts changed nothing: Alice's session is open and steps from 0.
    let response = client
        .step(with_token(step, Some(ALICE)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(response.step, 0);
    assert!(client.get_plan(with_token(get, Some(ALICE))).await.is_ok());
    let closed = client
        .close_session(with_token(close, Some(ALICE)))
        .await
        .unwrap();
    assert_eq!(closed.into_inner().steps, 1);
}

#[test]
fn a_bad_token_file_stops_the_server() {
    let bundles = bundle_dir();
    let tokens = bundles.path().join("tokens.txt");
    std::fs::write(&tokens, "short\n").unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_prac"))
        .args(["serve", "--listen", "127.0.0.1:0", "--auth-tokens"])
        .arg(&tokens)
        .arg("--bundles")
        .arg(bundles.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(out.stdout.is_empty(), "it never listened");
    assert!(String::from_utf8_lossy(&out.stderr).contains("at least 16 characters"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_serves_clients_that_trust_the_certificate() {
    let bundles = bundle_dir();
    let (cert_pem, cert, key) = common::tls_files(bundles.path());
    let server = Server::start(
        bundles.path(),
        &[
            "--tls-cert",
            cert.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
        ],
    );
    let channel = server.tls_channel(&cert_pem).await;
    let mut client = proto::prac_client::PracClient::new(channel);
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    loop {
        match client.list_policies(proto::ListPoliciesRequest {}).await {
            Ok(listed) if !listed.get_ref().policies.is_empty() => break,
            _ if std::time::Instant::now() < deadline => {
                tokio::time::sleep(std::time::Duration::from_millis(50)).await
            }
            other => panic!("no policies over TLS: {other:?}"),
        }
    }
    // A plaintext client gets no answer from the TLS port.
    let plain = tonic::transport::Channel::from_shared(format!("http://{}", server.addr))
        .unwrap()
        .connect()
        .await;
    if let Ok(channel) = plain {
        let mut plain = proto::prac_client::PracClient::new(channel);
        assert!(
            plain
                .list_policies(proto::ListPoliciesRequest {})
                .await
                .is_err()
        );
    }

    // A key that is not PEM stops the server before it listens.
    std::fs::write(&key, "not a key").unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_prac"))
        .args(["serve", "--listen", "127.0.0.1:0", "--tls-cert"])
        .arg(&cert)
        .arg("--tls-key")
        .arg(&key)
        .arg("--bundles")
        .arg(bundles.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(out.stdout.is_empty(), "it never listened");
}

/// `--health-listen`: a plaintext port that answers grpc.health.v1 alone, without a token, for
/// probes (the kubelet's speak neither TLS nor tokens) while the main port wants both.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_health_port_answers_health_alone_in_plaintext() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    let bundles = bundle_dir();
    let tokens = bundles.path().join("tokens.txt");
    std::fs::write(&tokens, format!("{ALICE}\n")).unwrap();
    let (cert_pem, cert, key) = common::tls_files(bundles.path());
    let server = Server::start(
        bundles.path(),
        &[
            "--auth-tokens",
            tokens.to_str().unwrap(),
            "--tls-cert",
            cert.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
            "--health-listen",
            "127.0.0.1:0",
        ],
    );
    let health_addr = server
        .preamble
        .iter()
        .find_map(|l| l.strip_prefix("health on "))
        .expect("the health address")
        .to_string();
    let channel = prac::client::channel(&health_addr).await.unwrap();
    let mut health = HealthClient::new(channel.clone());
    let check = |service: &str| HealthCheckRequest {
        service: service.to_string(),
    };
    let start = std::time::Instant::now();
    loop {
        let status = health
            .check(check("prac.v1.Prac"))
            .await
            .unwrap()
            .into_inner();
        if status.status() == ServingStatus::Serving {
            break;
        }
        assert!(start.elapsed() < std::time::Duration::from_secs(20));
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    let liveness = health.check(check("liveness")).await.unwrap().into_inner();
    assert_eq!(liveness.status(), ServingStatus::Serving);
    // Nothing else is served there: not prac.v1, not reflection.
    let mut prac = proto::prac_client::PracClient::new(channel);
    let refused = prac
        .list_policies(with_token(proto::ListPoliciesRequest {}, Some(ALICE)))
        .await
        .unwrap_err();
    assert_eq!(refused.code(), Code::Unimplemented, "{refused:?}");
    // The main port still wants TLS and a token.
    let mut client = proto::prac_client::PracClient::new(server.tls_channel(&cert_pem).await);
    let denied = client
        .list_policies(with_token(proto::ListPoliciesRequest {}, None))
        .await
        .unwrap_err();
    assert_eq!(denied.code(), Code::Unauthenticated);
}
