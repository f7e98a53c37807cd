//! Hot reload on SIGHUP: new sessions get the new version of a bundle, open sessions keep theirs,
//! a new bundle file is picked up, and a broken file keeps the old version.

use crate::common;

use std::time::{Duration, Instant};

use common::{Server, bundle_dir, toy_policy};
use prac::bundle;
use prac::proto;
use tonic::transport::Channel;

type Client = prac::proto::prac_client::PracClient<Channel>;

async fn hashes(client: &mut Client) -> Vec<(String, String)> {
    let listed = client
        .list_policies(proto::ListPoliciesRequest {})
        .await
        .unwrap()
        .into_inner();
    listed
        .policies
        .into_iter()
        .map(|p| (p.name, p.content_hash))
        .collect()
}

async fn wait_for(client: &mut Client, what: &str, ok: impl Fn(&[(String, String)]) -> bool) {
    let start = Instant::now();
    loop {
        if ok(&hashes(client).await) {
            return;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "never saw {what}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// The action of a fresh plan at `obs`: a function of the session's policy only.
async fn first_action(client: &mut Client, session: &str, obs: &[f32]) -> Vec<f32> {
    client
        .step(proto::StepRequest {
            session_id: session.to_string(),
            observation: obs.to_vec(),
            new_episode: true,
        })
        .await
        .unwrap()
        .into_inner()
        .action
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_reloads_bundles_without_touching_open_sessions() {
    let bundles = bundle_dir();
    let dir = bundles.path();
    let server = Server::start(dir, &[]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let before = hashes(&mut client).await;
    let obs = [0.3f32, -0.2, 0.7];
    let old_session = common::open_default_session(&mut client, "toy").await;
    let old_action = first_action(&mut client, &old_session, &obs).await;

    // Replace toy (written aside, then renamed: a reload never sees half a file) and add extra.
    bundle::save(&toy_policy("toy", 2), &dir.join("toy.tmp")).unwrap();
    std::fs::rename(dir.join("toy.tmp"), dir.join("toy.safetensors")).unwrap();
    bundle::save(&toy_policy("extra", 3), &dir.join("extra.safetensors")).unwrap();
    server.signal("HUP");
    let old_hash = before[0].1.clone();
    wait_for(&mut client, "the new toy and extra", |h| {
        h.len() == 2 && h.iter().any(|(n, x)| n == "toy" && *x != old_hash)
    })
    .await;
    let after = hashes(&mut client).await;

    let new_session = common::open_default_session(&mut client, "toy").await;
    let new_action = first_action(&mut client, &new_session, &obs).await;
    assert_ne!(
        new_action, old_action,
        "a new session must get the new version"
    );
    // The open session still plans with the version it opened with.
    assert_eq!(
        first_action(&mut client, &old_session, &obs).await,
        old_action
    );

    // A broken file: the loaded version stays and the error is logged.
    std::fs::write(dir.join("toy.safetensors"), b"not a bundle").unwrap();
    server.signal("HUP");
    let start = Instant::now();
    while !server.stderr().contains("reload: bad bundle") {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "{}",
            server.stderr()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(hashes(&mut client).await, after);

    // A hostile file (a manifest that declares a billion critics) is one more bad bundle.
    let policy = toy_policy("toy", 6);
    let mut manifest = policy.manifest.clone();
    manifest.critic.n_critics = 1_000_000_000;
    let text = serde_json::to_string(&manifest).unwrap();
    std::fs::write(
        dir.join("toy.safetensors"),
        bundle::to_bytes_with_manifest(&policy, &text).unwrap(),
    )
    .unwrap();
    server.signal("HUP");
    let start = Instant::now();
    while server.stderr().matches("reload: bad bundle").count() < 2 {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "{}",
            server.stderr()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(
        server
            .stderr()
            .contains("critic.qf2.0.weight: missing tensor")
    );
    assert_eq!(hashes(&mut client).await, after);
    let third = common::open_default_session(&mut client, "toy").await;
    assert_eq!(first_action(&mut client, &third, &obs).await, new_action);
    assert_eq!(
        first_action(&mut client, &old_session, &obs).await,
        old_action
    );
}
