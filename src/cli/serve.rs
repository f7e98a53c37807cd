//! `prac serve`: the gRPC server (its settings are declared once, with the config file's keys, in
//! `prac::serve::config`).

use prac::serve::{ServeArgs, ServeConfig};

pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    let config = ServeConfig::resolve(&args)?;
    prac::serve::init_logging(config.log_format);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .on_thread_start(prac::serve::handlers_do_not_preempt)
        .build()?;
    runtime.block_on(prac::serve::run(config))
}
