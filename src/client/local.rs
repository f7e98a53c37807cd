//! A `prac serve` child process on a free loopback port, for clients that bring their own server
//! (`prac-sim`, `prac-bench`). It is killed when dropped.

use std::path::{Path, PathBuf};
use std::process::Stdio;

use anyhow::{Context, bail};
use tokio::io::{AsyncBufReadExt, BufReader};

pub struct LocalServer {
    pub addr: String,
    child: tokio::process::Child,
    /// The server's last lines on stderr, to pass its own words on when something fails.
    log: std::sync::Arc<std::sync::Mutex<std::collections::VecDeque<String>>>,
}

/// Lines of the local server's stderr kept for error messages.
const LOG_LINES: usize = 20;

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

/// Drop ends the server only when this process unwinds; a client killed outright (SIGKILL, or
/// a SIGTERM it does not handle) would leave its server running on. On Linux the server is
/// also sent SIGTERM when the thread that started it ends (its parent-death signal).
#[cfg(target_os = "linux")]
fn end_with_this_process(command: &mut tokio::process::Command) {
    let parent = std::process::id();
    // SAFETY: between fork and exec the closure calls only prctl and getppid, which are
    // async-signal-safe, and allocates nothing.
    unsafe {
        command.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The parent may have died before the signal was asked for.
            if libc::getppid() as u32 != parent {
                return Err(std::io::Error::other(
                    "the client exited while starting its server",
                ));
            }
            Ok(())
        });
    }
}

#[cfg(not(target_os = "linux"))]
fn end_with_this_process(_command: &mut tokio::process::Command) {}

impl LocalServer {
    /// Starts `bin serve --listen 127.0.0.1:0 --bundles DIR ARGS...` and waits for its
    /// `listening on ADDR` line.
    pub async fn start(bin: &Path, bundles: &Path, args: &[String]) -> anyhow::Result<LocalServer> {
        let mut command = tokio::process::Command::new(bin);
        command
            .args(["serve", "--listen", "127.0.0.1:0", "--bundles"])
            .arg(bundles)
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .kill_on_drop(true);
        end_with_this_process(&mut command);
        let mut child = command.spawn().with_context(|| {
            format!(
                "starting {} (build it: cargo build --release)",
                bin.display()
            )
        })?;
        let log: std::sync::Arc<std::sync::Mutex<std::collections::VecDeque<String>>> =
            Default::default();
        let stderr = child.stderr.take().context("server stderr")?;
        let collected = log.clone();
        let collector = tokio::spawn(async move {
            let mut lines = BufReader::new(stderr).lines();
            while let Ok(Some(line)) = lines.next_line().await {
                let mut log = collected.lock().unwrap_or_else(|p| p.into_inner());
                if log.len() == LOG_LINES {
                    log.pop_front();
                }
                log.push_back(line);
            }
        });
        let stdout = child.stdout.take().context("server stdout")?;
        let mut line = String::new();
        BufReader::new(stdout).read_line(&mut line).await?;
        let Some(addr) = line.trim().strip_prefix("listening on ") else {
            // It exited: its last words say why.
            let _ = tokio::time::timeout(std::time::Duration::from_secs(2), collector).await;
            let said = log.lock().unwrap_or_else(|p| p.into_inner());
            let said: Vec<&str> = said.iter().map(String::as_str).collect();
            bail!(
                "the local server ({}) did not start: {}",
                bin.display(),
                if said.is_empty() {
                    "it printed nothing".to_string()
                } else {
                    said.join("\n")
                }
            );
        };
        Ok(LocalServer {
            addr: addr.to_string(),
            child,
            log,
        })
    }

    /// The server's last lines on stderr (its logs: bundles skipped and why).
    pub fn recent_log(&self) -> String {
        let log = self.log.lock().unwrap_or_else(|p| p.into_inner());
        log.iter()
            .map(String::as_str)
            .collect::<Vec<_>>()
            .join("\n")
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
