//! A step is applied exactly when it is answered: under tight client deadlines every failed step
//! is DEADLINE_EXCEEDED and changes nothing, so the steps a session served equal the steps its
//! client was answered.

use crate::common;

use common::{Server, h2_connect, h2_unary, open_default_session};
use prac::bundle;
use prac::proto;
use prac::testing::hopper_sized_manifest;

fn hopper_bundles() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let policy = prac::testing::random_policy(hopper_sized_manifest(), 3);
    bundle::save(&policy, &dir.path().join("hopper.safetensors")).unwrap();
    dir
}

async fn steps_under_deadlines(server: &Server, sessions: usize, steps: usize) {
    let mut tasks = Vec::new();
    for k in 0..sessions {
        let mut client = server.client().await;
        let addr = server.addr.clone();
        tasks.push(tokio::spawn(async move {
            let id = open_default_session(&mut client, "hopper").await;
            // Raw HTTP/2: the server alone enforces the deadline (tonic and grpcio clients also
            // give up by themselves, possibly while an applied step's answer is on its way).
            let (mut send, _connection) = h2_connect(&addr).await;
            let (mut answered, mut failed) = (0u64, 0u64);
            for i in 0..steps {
                let request = proto::StepRequest {
                    session_id: id.clone(),
                    observation: vec![0.01 * (i % 7) as f32; 15],
                    new_episode: false,
                };
                // 1 ns to 9.8 ms: some steps make it, some do not.
                let timeout = format!("{}n", 1 + ((i * 37 + k * 11) % 50) * 200_000);
                let path = "/prac.v1.Prac/Step";
                match h2_unary(&mut send, &addr, path, &request, Some(&timeout))
                    .await
                    .0
                    .as_str()
                {
                    "0" => answered += 1,
                    "4" => failed += 1,
                    other => {
                        panic!("step {i}: grpc-status {other}, expected 0 or 4 (DEADLINE_EXCEEDED)")
                    }
                }
            }
            let closed = client
                .close_session(proto::CloseSessionRequest { session_id: id })
                .await
                .unwrap()
                .into_inner();
            assert_eq!(
                closed.steps, answered,
                "session {k}: {answered} steps answered, {failed} failed, but {} applied",
                closed.steps
            );
            (answered, failed)
        }));
    }
    let (mut answered, mut failed) = (0, 0);
    for task in tasks {
        let (a, f) = task.await.unwrap();
        answered += a;
        failed += f;
    }
    assert!(answered > 0, "no step made its deadline");
    assert!(
        failed > 0,
        "no step missed its deadline; the test proves nothing"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn steps_that_miss_their_deadline_are_not_applied_when_batched() {
    let bundles = hopper_bundles();
    let server = Server::start(bundles.path(), &[]);
    server.wait_serving().await;
    steps_under_deadlines(&server, 8, 150).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn steps_that_miss_their_deadline_are_not_applied_inline() {
    let bundles = hopper_bundles();
    let server = Server::start(bundles.path(), &["--batch-max", "0"]);
    server.wait_serving().await;
    steps_under_deadlines(&server, 8, 150).await;
}
