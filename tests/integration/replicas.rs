//! Two `prac serve` replicas behind nginx (deploy/nginx/prac.conf, grpc_pass, affinity by
//! `x-prac-affinity`): killing the replica that holds a client's session mid-episode loses no
//! step; the client resumes on the other replica with the committed plan. Needs nginx on PATH or
//! in /usr/sbin (`.ci/run` installs it); without it the test says it was skipped.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{OBS, Server, bundle_dir};
use prac::client::ResumingSession;
use prac::proto::{self, prac_client::PracClient, session_options::Tolerance};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

struct Nginx {
    child: Child,
    _prefix: tempfile::TempDir,
}

impl Drop for Nginx {
    fn drop(&mut self) {
        // SIGTERM: the master stops its workers too (SIGKILL would leave them running).
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let _ = self.child.wait();
    }
}

/// nginx, if installed. Without it the test says it was skipped, unless PRAC_REQUIRE_NGINX is set
/// (`.ci/run` sets it after installing nginx, so CI never skips it).
fn nginx_binary() -> Option<PathBuf> {
    let found = ["/usr/sbin/nginx", "/usr/local/sbin/nginx", "/usr/bin/nginx"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
        .or_else(|| {
            let path = std::env::var_os("PATH")?;
            std::env::split_paths(&path)
                .map(|dir| dir.join("nginx"))
                .find(|p| p.exists())
        });
    if found.is_none() {
        assert!(
            std::env::var_os("PRAC_REQUIRE_NGINX").is_none(),
            "PRAC_REQUIRE_NGINX is set but nginx is not installed"
        );
        println!(
            "SKIPPED: nginx is not installed, so the replica test did not run; \
             `apt-get install nginx` runs it"
        );
        eprintln!("replica test skipped: nginx is not installed (apt-get install nginx)");
    }
    found
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn start_nginx(nginx: &Path, listen: &str, replicas: [&str; 2]) -> Nginx {
    let prefix = tempfile::tempdir().unwrap();
    let template = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/nginx/prac.conf"),
    )
    .unwrap();
    let config = template
        .replace("@PREFIX@", prefix.path().to_str().unwrap())
        .replace("@LISTEN@", listen)
        .replace("@REPLICA_A@", replicas[0])
        .replace("@REPLICA_B@", replicas[1]);
    let path = prefix.path().join("nginx.conf");
    std::fs::write(&path, config).unwrap();
    let child = Command::new(nginx)
        .arg("-p")
        .arg(prefix.path())
        .arg("-c")
        .arg(&path)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("nginx (apt-get install nginx)");
    let start = Instant::now();
    while std::net::TcpStream::connect(listen).is_err() {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "nginx did not start"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    Nginx {
        child,
        _prefix: prefix,
    }
}

/// Whether `server` holds session `id` (asked directly, not through nginx).
async fn holds(server: &Server, id: &str) -> bool {
    let mut client = server.client().await;
    client
        .get_plan(proto::GetPlanRequest {
            session_id: id.to_string(),
        })
        .await
        .is_ok()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn killing_a_replica_loses_no_step_for_a_resuming_client() {
    let Some(nginx) = nginx_binary() else {
        return;
    };
    let bundles = bundle_dir();
    let mut replicas = [
        Server::start(bundles.path(), &[]),
        Server::start(bundles.path(), &[]),
    ];
    for r in &replicas {
        r.wait_serving().await;
    }
    let listen = format!("127.0.0.1:{}", free_port());
    let _nginx = start_nginx(&nginx, &listen, [&replicas[0].addr, &replicas[1].addr]);
    let client = PracClient::connect(format!("http://{listen}"))
        .await
        .unwrap();
    // A wide tolerance keeps every plan, so the committed action is the one executed.
    let options = proto::SessionOptions {
        tolerance: Some(Tolerance::Epsilon(1e6)),
        max_horizon: 16,
        ..Default::default()
    };
    let mut session = ResumingSession::open(client, "toy", Some(options), Some("robot-17"))
        .await
        .unwrap();

    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut responses: Vec<proto::StepResponse> = Vec::new();
    let mut killed = None;
    for t in 0..20u64 {
        if t == 8 {
            // Kill whichever replica holds the session, mid-episode.
            let mut owner = None;
            for (k, r) in replicas.iter().enumerate() {
                if holds(r, session.session_id()).await {
                    owner = Some(k);
                }
            }
            let owner = owner.expect("one replica holds the session");
            replicas[owner].signal("KILL");
            replicas[owner].wait_exit(Duration::from_secs(10)).unwrap();
            killed = Some(owner);
        }
        let obs: Vec<f32> = (0..OBS).map(|_| rng.random_range(-1.0..1.0)).collect();
        let answer = session.step(&obs, t == 0).await.unwrap();
        assert!(!answer.local, "no fallback: every answer is served");
        let response = answer.response;
        // No step lost: the step counter and episode go on without a gap.
        assert_eq!((response.step, response.episode), (t, 0), "{response:?}");
        if let Some(previous) = responses.last() {
            // The action executed is the one committed for this step at the previous one.
            for (a, b) in response.action.iter().zip(&previous.forecast[1].action) {
                assert!(
                    (a - b).abs() < 1e-5,
                    "step {t}: {response:?} vs {previous:?}"
                );
            }
        }
        responses.push(response);
    }
    assert_eq!(session.resumes, 1);
    let survivor = 1 - killed.unwrap();
    assert!(holds(&replicas[survivor], session.session_id()).await);
}
