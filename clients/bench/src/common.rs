//! What prac-bench and prac-soak share: their own local server and the client connection.

use std::path::Path;

use prac::proto::prac_client::PracClient;
use tonic::transport::Channel;

/// A `prac serve` of its own on a random Hopper-sized bundle, with the folder it lives in.
pub struct LocalServer {
    pub server: prac::serve::local::LocalServer,
    _dir: tempfile::TempDir,
}

impl LocalServer {
    /// Starts `prac serve ARGS...` (the binary beside this one unless `prac_bin`) on a fresh
    /// `hopper-bench` policy with random weights.
    pub async fn start(prac_bin: Option<&Path>, args: &[String]) -> anyhow::Result<LocalServer> {
        let dir = tempfile::tempdir()?;
        let policy = prac::policy::Policy::random(prac::policy::hopper_sized_manifest(), 7);
        prac::bundle::save(&policy, &dir.path().join("hopper-bench.safetensors"))?;
        let bin = prac::serve::local::prac_binary(prac_bin)?;
        let server = prac::serve::local::LocalServer::start(&bin, dir.path(), args).await?;
        Ok(LocalServer { server, _dir: dir })
    }
}

/// A connection with Nagle off (one-step round trips).
pub async fn connect(addr: &str) -> anyhow::Result<PracClient<Channel>> {
    let channel = Channel::from_shared(format!("http://{addr}"))?
        .tcp_nodelay(true)
        .connect()
        .await?;
    Ok(PracClient::new(channel))
}
