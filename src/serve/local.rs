//! A `prac serve` child process on a free loopback port, for clients that bring their own server
//! (`prac-sim`, `prac-bench`). It is killed when dropped.

use std::path::{Path, PathBuf};
use std::process::Stdio;

use anyhow::{Context, bail};
use tokio::io::{AsyncBufReadExt, BufReader};

pub struct LocalServer {
    pub addr: String,
    child: tokio::process::Child,
}

/// The `prac` binary beside the running one (cargo puts workspace binaries together), unless
/// `explicit` names one.
pub fn prac_binary(explicit: Option<&Path>) -> anyhow::Result<PathBuf> {
    match explicit {
        Some(bin) => Ok(bin.to_path_buf()),
        None => Ok(std::env::current_exe()?
            .parent()
            .context("the running binary has no folder")?
            .join("prac")),
    }
}

impl LocalServer {
    /// Starts `bin serve --listen 127.0.0.1:0 --bundles DIR ARGS...` and waits for its
    /// `listening on ADDR` line.
    pub async fn start(bin: &Path, bundles: &Path, args: &[String]) -> anyhow::Result<LocalServer> {
        let mut child = tokio::process::Command::new(bin)
            .args(["serve", "--listen", "127.0.0.1:0", "--bundles"])
            .arg(bundles)
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .kill_on_drop(true)
            .spawn()
            .with_context(|| {
                format!(
                    "starting {} (build it: cargo build --release)",
                    bin.display()
                )
            })?;
        let stdout = child.stdout.take().context("server stdout")?;
        let mut line = String::new();
        BufReader::new(stdout).read_line(&mut line).await?;
        let Some(addr) = line.trim().strip_prefix("listening on ") else {
            bail!("the local server did not start: {line:?}");
        };
        Ok(LocalServer {
            addr: addr.to_string(),
            child,
        })
    }

    /// The server's process id (None once it has exited).
    pub fn pid(&self) -> Option<u32> {
        self.child.id()
    }

    /// Stops the server (SIGKILL; it holds nothing to save).
    pub async fn stop(mut self) {
        let _ = self.child.kill().await;
    }
}
