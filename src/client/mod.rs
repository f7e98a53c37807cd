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

pub use resuming::{AFFINITY_HEADER, Answer, Fallback, ResumingSession};

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

/// Two finite numbers "A,B" from a command-line value (`--value-scale`, prac-sim's
/// `--normalize`); `what` names the flag's form in the error.
pub fn parse_number_pair(text: &str, what: &str) -> anyhow::Result<(f64, f64)> {
    let numbers: Vec<f64> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| anyhow::anyhow!("expected {what} (two numbers), got '{text}'"))?;
    match numbers[..] {
        [a, b] if a.is_finite() && b.is_finite() => Ok((a, b)),
        _ => anyhow::bail!("expected {what} (two finite numbers), got '{text}'"),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn number_pairs_take_exactly_two_finite_numbers() {
        assert_eq!(super::parse_number_pair("1,2", "A,B").unwrap(), (1.0, 2.0));
        assert_eq!(
            super::parse_number_pair(" -3 , 4.5", "A,B").unwrap(),
            (-3.0, 4.5)
        );
        for bad in ["1", "1,2,3", "a,b", "nan,1", "1,inf", ""] {
            let e = super::parse_number_pair(bad, "A,B").unwrap_err();
            assert!(e.to_string().contains("A,B"), "{bad}: {e}");
        }
    }
}
