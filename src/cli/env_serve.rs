//! `prac env-serve`: a built-in domain over DeepMind's dm_env_rpc protocol.

use clap::Args;

#[derive(Args, Debug)]
pub struct EnvServeArgs {
    /// The domain (`prac domains` lists them).
    #[arg(long)]
    domain: String,
    /// HOST:PORT (port 0 picks a free one).
    #[arg(long, default_value = "127.0.0.1:50061", value_parser = prac::serve::socket_address)]
    listen: std::net::SocketAddr,
    /// Seed of each world's first episode unless its settings give one.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

impl EnvServeArgs {
    pub fn run(self) -> anyhow::Result<()> {
        tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()?
            .block_on(prac::env_rpc::serve(&self.domain, self.listen, self.seed))
    }
}
