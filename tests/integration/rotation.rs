//! Certificate and token rotation against the real server, with the files swapped the way
//! kubelet updates a mounted Secret (a new timestamped folder, then `..data` renamed onto it):
//! new connections get the new certificate while an open stream goes on, a removed token is
//! refused on its next call, and bad new files keep what was served, counted in the metrics.

use std::path::Path;
use std::time::{Duration, Instant};

use crate::common;

use common::{OBS, Server, bundle_dir, metrics_address, scrape};
use prac::proto;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::metadata::MetadataValue;

const OLD_TOKEN: &str = "old-7f3c9a0d5e21b864";
const NEW_TOKEN: &str = "new-0a9e8d7c6b5a4f3e";

/// A mounted Secret as kubelet lays it out: `NAME -> ..data/NAME`, `..data -> ..VERSION`.
struct Mounted<'a> {
    root: &'a Path,
    version: usize,
}

impl Mounted<'_> {
    /// Writes `files` into a new version folder and swaps `..data` onto it at once.
    fn publish(&mut self, files: &[(&str, &str)]) {
        self.version += 1;
        let folder = format!("..2026_12_07_00_00_{:02}.{}", self.version, self.version);
        std::fs::create_dir(self.root.join(&folder)).unwrap();
        for (name, contents) in files {
            std::fs::write(self.root.join(&folder).join(name), contents).unwrap();
            let link = self.root.join(name);
            if !link.exists() {
                std::os::unix::fs::symlink(format!("..data/{name}"), link).unwrap();
            }
        }
        let staged = self.root.join("..data_tmp");
        std::os::unix::fs::symlink(&folder, &staged).unwrap();
        std::fs::rename(&staged, self.root.join("..data")).unwrap();
    }
}

/// A self-signed certificate for localhost valid for `days` more days, and its key.
fn certificate(days: i64) -> (String, String) {
    let mut params = rcgen::CertificateParams::new(vec!["localhost".to_string()]).unwrap();
    let now = time::OffsetDateTime::now_utc();
    params.not_before = now - time::Duration::days(1);
    params.not_after = now + time::Duration::days(days);
    let key = rcgen::KeyPair::generate().unwrap();
    (params.self_signed(&key).unwrap().pem(), key.serialize_pem())
}

fn days_left(text: &str) -> f64 {
    let expiry: f64 = text
        .lines()
        .find(|l| l.starts_with("prac_tls_cert_expiry_timestamp_seconds{"))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no certificate expiry in\n{text}"));
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    (expiry - now) / 86_400.0
}

fn with_token<T>(message: T, token: &str) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    let value: MetadataValue<_> = format!("Bearer {token}").parse().unwrap();
    request.metadata_mut().insert("authorization", value);
    request
}

/// Waits until `ok` holds of a scrape of `server`'s metrics; returns that scrape.
async fn wait_metrics(server: &Server, what: &str, ok: impl Fn(&str) -> bool) -> String {
    let address = metrics_address(server);
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        let text = scrape(&address);
        if ok(&text) {
            return text;
        }
        assert!(Instant::now() < deadline, "{what}: never seen in\n{text}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn reloads(text: &str, file: &str, result: &str) -> f64 {
    let name = format!("prac_credential_reloads_total{{file=\"{file}\",result=\"{result}\"}}");
    text.lines()
        .find_map(|l| l.strip_prefix(&name).and_then(|v| v.trim().parse().ok()))
        .unwrap_or(0.0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_swapped_secret_is_served_to_new_connections_while_open_streams_go_on() {
    let bundles = bundle_dir();
    let secret = tempfile::tempdir().unwrap();
    let mut mounted = Mounted {
        root: secret.path(),
        version: 0,
    };
    let (first_cert, first_key) = certificate(10);
    let tokens = format!("{OLD_TOKEN}\n{NEW_TOKEN}\n");
    mounted.publish(&[
        ("tls.crt", &first_cert),
        ("tls.key", &first_key),
        ("tokens", &tokens),
    ]);
    let path = |name: &str| secret.path().join(name).to_str().unwrap().to_string();
    let server = Server::start(
        bundles.path(),
        &[
            "--tls-cert",
            &path("tls.crt"),
            "--tls-key",
            &path("tls.key"),
            "--auth-tokens",
            &path("tokens"),
            "--metrics-listen",
            "127.0.0.1:0",
        ],
    );
    let text = wait_metrics(&server, "serving", |t| t.contains("\nprac_serving 1\n")).await;
    assert!(
        (days_left(&text) - 10.0).abs() < 0.1,
        "{}",
        days_left(&text)
    );

    // A session stepping over a stream on a connection made with the first certificate.
    let mut old_client =
        proto::prac_client::PracClient::new(server.try_tls_channel(&first_cert).await.unwrap());
    let session = old_client
        .open_session(with_token(
            proto::OpenSessionRequest {
                local_steps: 0,
                policy: "toy".into(),
                options: None,
                resume: None,
            },
            OLD_TOKEN,
        ))
        .await
        .unwrap()
        .into_inner()
        .session_id;
    let (tx, rx) = mpsc::channel(4);
    let mut answers = old_client
        .step_stream(with_token(ReceiverStream::new(rx), OLD_TOKEN))
        .await
        .unwrap()
        .into_inner();
    let step = |t: u64| proto::StepRequest {
        session_id: session.clone(),
        observation: vec![0.1 * t as f32; OBS],
        new_episode: t == 0,
    };
    for t in 0..3 {
        tx.send(step(t)).await.unwrap();
        assert_eq!(answers.message().await.unwrap().unwrap().step, t);
    }

    // Renewal: a new certificate and key, and the old token dropped.
    let (second_cert, second_key) = certificate(90);
    let only_new = format!("{NEW_TOKEN}\n");
    mounted.publish(&[
        ("tls.crt", &second_cert),
        ("tls.key", &second_key),
        ("tokens", &only_new),
    ]);
    let text = wait_metrics(&server, "both reloads", |t| {
        reloads(t, "certificate", "ok") == 1.0 && reloads(t, "tokens", "ok") == 1.0
    })
    .await;
    assert!(
        (days_left(&text) - 90.0).abs() < 0.1,
        "{}",
        days_left(&text)
    );

    // New connections get the second certificate: one trusting only the first fails.
    let mut new_client =
        proto::prac_client::PracClient::new(server.try_tls_channel(&second_cert).await.unwrap());
    let listed = new_client
        .list_policies(with_token(proto::ListPoliciesRequest {}, NEW_TOKEN))
        .await;
    assert!(listed.is_ok(), "{listed:?}");
    let refused = match server.try_tls_channel(&first_cert).await {
        Err(_) => true,
        Ok(channel) => proto::prac_client::PracClient::new(channel)
            .list_policies(with_token(proto::ListPoliciesRequest {}, NEW_TOKEN))
            .await
            .is_err(),
    };
    assert!(
        refused,
        "a client trusting only the old certificate got through"
    );

    // The open stream goes on; the dropped token is refused from its next call.
    for t in 3..6 {
        tx.send(step(t)).await.unwrap();
        assert_eq!(answers.message().await.unwrap().unwrap().step, t);
    }
    let again = old_client
        .get_plan(with_token(
            proto::GetPlanRequest {
                session_id: session.clone(),
            },
            OLD_TOKEN,
        ))
        .await;
    assert_eq!(again.unwrap_err().code(), Code::Unauthenticated);

    // Bad renewals: garbage, a key that does not match, an empty token file. The second
    // certificate and the new token go on serving; the session stays.
    let (third_cert, _) = certificate(90);
    let (_, unrelated_key) = certificate(90);
    mounted.publish(&[
        ("tls.crt", "garbage"),
        ("tls.key", &second_key),
        ("tokens", ""),
    ]);
    wait_metrics(&server, "refused garbage", |t| {
        reloads(t, "certificate", "error") == 1.0 && reloads(t, "tokens", "error") == 1.0
    })
    .await;
    mounted.publish(&[
        ("tls.crt", &third_cert),
        ("tls.key", &unrelated_key),
        ("tokens", ""),
    ]);
    wait_metrics(&server, "refused a mismatched key", |t| {
        reloads(t, "certificate", "error") == 2.0
    })
    .await;
    // A vanished token file keeps the tokens too.
    std::fs::remove_file(secret.path().join("tokens")).unwrap();
    wait_metrics(&server, "refused a missing token file", |t| {
        reloads(t, "tokens", "error") == 2.0
    })
    .await;
    let mut after =
        proto::prac_client::PracClient::new(server.try_tls_channel(&second_cert).await.unwrap());
    assert!(
        after
            .list_policies(with_token(proto::ListPoliciesRequest {}, NEW_TOKEN))
            .await
            .is_ok()
    );
    let text = scrape(&metrics_address(&server));
    assert!(
        (days_left(&text) - 90.0).abs() < 0.1,
        "the second certificate's expiry stays"
    );
    for t in 6..8 {
        tx.send(step(t)).await.unwrap();
        assert_eq!(answers.message().await.unwrap().unwrap().step, t);
    }
    let log = server.stderr();
    assert!(
        log.contains("TLS certificate not reloaded; serving the previous one"),
        "{log}"
    );
    assert!(
        log.contains("auth tokens not reloaded; serving the previous ones"),
        "{log}"
    );
}
