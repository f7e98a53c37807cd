//! The client side of prac, shared by the bundled clients (`prac-sim`, `prac-bench`,
//! `prac-soak`) and the integration tests: connecting, waiting for a starting server's policies,
//! a `prac serve` child of one's own ([`local`]) and a session that survives losing its server
//! ([`ResumingSession`]).

use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use tonic::Code;
use tonic::transport::Channel;

use crate::proto::{self, PolicyInfo, prac_client::PracClient};

pub mod local;
mod resuming;

pub use resuming::{AFFINITY_HEADER, ResumingSession};

/// How long a client waits for a starting server to list its policies (it answers UNAVAILABLE
/// until its bundles are loaded; the largest bundled one loads in well under a second).
pub const POLICY_PATIENCE: Duration = Duration::from_secs(30);

/// A plaintext channel to `addr` (`HOST:PORT` or a URL), with Nagle off: a step is one small
/// request and its answer, which Nagle's algorithm would hold back.
pub async fn channel(addr: &str) -> anyhow::Result<Channel> {
    let target = if addr.starts_with("http") {
        addr.to_string()
    } else {
        format!("http://{addr}")
    };
    Channel::from_shared(target)
        .with_context(|| format!("'{addr}' is not an address"))?
        .tcp_nodelay(true)
        .connect()
        .await
        .with_context(|| format!("connecting to {addr}"))
}

/// A client over [`channel`].
pub async fn connect(addr: &str) -> anyhow::Result<PracClient<Channel>> {
    Ok(PracClient::new(channel(addr).await?))
}

/// The policy to use: `wanted`, else the only one served. Waits up to `patience` for a starting
/// server to list its policies; a served list without the wanted one is an error at once.
pub async fn choose_policy(
    client: &mut PracClient<Channel>,
    wanted: Option<&str>,
    patience: Duration,
) -> anyhow::Result<PolicyInfo> {
    let deadline = Instant::now() + patience;
    loop {
        let listed = match client.list_policies(proto::ListPoliciesRequest {}).await {
            Ok(listed) => listed.into_inner().policies,
            Err(status) if status.code() == Code::Unavailable => Vec::new(),
            Err(status) => bail!("ListPolicies: {}", status.message()),
        };
        let names: Vec<&str> = listed.iter().map(|p| p.name.as_str()).collect();
        match wanted {
            _ if listed.is_empty() => {}
            Some(name) => {
                return listed
                    .iter()
                    .find(|p| p.name == name)
                    .cloned()
                    .with_context(|| {
                        format!(
                            "the server has no policy '{name}'; it serves: {}",
                            names.join(", ")
                        )
                    });
            }
            None if listed.len() == 1 => return Ok(listed[0].clone()),
            None => bail!(
                "the server serves {} policies; choose one with --policy: {}",
                listed.len(),
                names.join(", ")
            ),
        }
        if Instant::now() > deadline {
            bail!(
                "the server listed no policies within {} s",
                patience.as_secs()
            );
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
