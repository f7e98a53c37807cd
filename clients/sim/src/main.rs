//! prac-sim: the bundled simulator client. It plays the domains against `prac serve` over
//! StepStream (starting a local server on the bundled policies when no `--server` is given),
//! sweeps PrAC's eps coefficient and draws the paper's Figures 3 and 4.

mod curves;
mod play;
mod sweep;
mod table;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};

use play::Tol;

/// A failure of a command against its own local server, with what that server logged.
fn with_server_log(
    e: anyhow::Error,
    local: Option<&prac::client::local::LocalServer>,
) -> anyhow::Error {
    match local.map(prac::client::local::LocalServer::recent_log) {
        Some(log) if !log.is_empty() => anyhow::anyhow!("{e:#}\nthe local server logged:\n{log}"),
        _ => e,
    }
}

#[derive(Parser)]
#[command(version, about)]
struct Cli {
    /// A running server (host:port); without it a local `prac serve` runs for the command.
    #[arg(long, global = true)]
    server: Option<String>,
    /// Bundles for the local server [default: bundles/ in the working directory, as prac serve's].
    #[arg(long, global = true)]
    bundles: Option<PathBuf>,
    /// The `prac` binary for the local server [default: beside prac-sim].
    #[arg(long, global = true)]
    prac_bin: Option<PathBuf>,
    /// Hide progress bars.
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

/// The sessions' plan growth and cap (SessionOptions); the server's defaults are grow 2 and a
/// cap of 32 actions.
#[derive(clap::Args, Clone, Copy, Debug)]
struct PlanArgs {
    /// Append K policy actions after the kept part of the plan each step [server default: 2].
    #[arg(long, value_name = "K", conflicts_with = "fixed")]
    grow: Option<u32>,
    /// Refill the plan to N actions each step (a fixed horizon) instead of growing it.
    #[arg(long, value_name = "N")]
    fixed: Option<u32>,
    /// Longest plan, the action executed now included [server default: 32, or N with --fixed N].
    #[arg(long, value_name = "N")]
    max_horizon: Option<u32>,
    /// Guard the plans: any one critic rating a kept action more than eps below pi(s) also
    /// breaks the plan (the session option guard.every_critic).
    #[arg(long)]
    every_critic: bool,
    /// Guard the plans: an action further than Z of the policy's standard deviations from its
    /// mean also breaks the plan (guard.support_limit) [default: no limit].
    #[arg(long, value_name = "Z")]
    support_limit: Option<f64>,
    /// Hold the sessions' eps to at most C x (V_pi - V_rand) of the policy's value scale
    /// (guard.max_epsilon_coef) [default: no limit].
    #[arg(long, value_name = "C")]
    max_epsilon_coef: Option<f64>,
    /// The paper's test alone, whatever guard the policy's bundle sets by default (an empty
    /// guard). Without any guard flag the sessions get the bundle's default_guard.
    #[arg(long, conflicts_with_all = ["every_critic", "support_limit", "max_epsilon_coef"])]
    paper_test: bool,
}

impl PlanArgs {
    fn shape(&self) -> anyhow::Result<play::PlanShape> {
        use prac::proto::session_options::Growth;
        for (flag, value) in [
            ("--grow", self.grow),
            ("--fixed", self.fixed),
            ("--max-horizon", self.max_horizon),
        ] {
            anyhow::ensure!(value != Some(0), "{flag} must be >= 1");
        }
        Ok(play::PlanShape {
            growth: self
                .grow
                .map(Growth::Grow)
                .or(self.fixed.map(Growth::Fixed)),
            max_horizon: self.max_horizon.unwrap_or(0),
            every_critic: self.every_critic,
            support_limit: self.support_limit.unwrap_or(0.0),
            max_epsilon_coef: self.max_epsilon_coef.unwrap_or(0.0),
            paper_test: self.paper_test,
        })
    }
}

#[derive(Subcommand)]
enum Command {
    /// Play a policy's domain: per-episode return, discounted return, forecast, replans.
    Play {
        #[arg(long)]
        policy: String,
        /// eps = C * (V_pi - V_rand) from the bundle's value scale.
        #[arg(long, conflicts_with = "epsilon")]
        epsilon_coef: Option<f64>,
        /// Absolute eps.
        #[arg(long)]
        epsilon: Option<f64>,
        #[arg(long, default_value_t = 5)]
        episodes: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Draw the first episode at --render-step with the committed plan overlaid.
        #[arg(long)]
        render: Option<PathBuf>,
        #[arg(long, default_value_t = 50)]
        render_step: u64,
        /// Print the episodes as JSON.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        plan: PlanArgs,
    },
    /// Training-then-PrAC: NP, forecast and the Lemma-1 bound per eps coefficient.
    Sweep {
        #[arg(long)]
        policy: String,
        #[arg(
            long,
            value_delimiter = ',',
            default_value = "0,0.001,0.003,0.005,0.008,0.01"
        )]
        coefs: Vec<f64>,
        #[arg(long, default_value_t = 20)]
        episodes: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        plan: PlanArgs,
    },
    /// Training curves (return and forecast against steps) from `prac train` CSVs: every run
    /// into DIR/curves.png and, where NAME.train.csv and NAME-seedK.train.csv are seeds of one
    /// setting, their mean and std across seeds into DIR/curves-seeds.png. With --at, also
    /// Figure 4's table into DIR/table.md.
    Curves {
        #[arg(long, value_delimiter = ',', required = true)]
        csv: Vec<PathBuf>,
        /// Normalise returns: R_RAND,R_REF map to 0 and 1.
        #[arg(long, value_name = "R_RAND,R_REF", allow_hyphen_values = true)]
        normalize: Option<String>,
        #[arg(long)]
        out: PathBuf,
        /// Training steps for DIR/table.md: per run, the return of the last 20 episodes ended by
        /// each and its ratio to plain SAC of the same seed, the forecast, episodes that ended
        /// early, the last evaluation (NAME.eval.csv) and wall seconds per 1,000 steps.
        #[arg(long, value_delimiter = ',', value_name = "STEPS")]
        at: Vec<u64>,
        /// The runs' domain, whose step limit tells which training episodes ended early
        /// [default: the CSVs' folder name, where it names a domain].
        #[arg(long)]
        domain: Option<String>,
    },
}

pub fn progress(total: u64, show: bool) -> indicatif::ProgressBar {
    let bar = if show {
        indicatif::ProgressBar::new(total)
    } else {
        indicatif::ProgressBar::hidden()
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} episodes {msg}",
        )
        .expect("a valid template")
        .progress_chars("=> "),
    );
    bar
}

fn parse_pair(text: &str) -> anyhow::Result<(f64, f64)> {
    let (a, b) = prac::client::parse_number_pair(text, "A,B")?;
    anyhow::ensure!(a != b, "expected two different numbers A,B, got '{text}'");
    Ok((a, b))
}

/// Figure 4's table of the runs `csvs` at the steps `at` (returns normalised where asked) into
/// DIR/table.md.
fn write_table(
    csvs: &[PathBuf],
    at: &[u64],
    domain: Option<&str>,
    normalize: Option<(f64, f64)>,
    dir: &std::path::Path,
) -> anyhow::Result<PathBuf> {
    let folder = csvs[0]
        .parent()
        .and_then(|p| p.file_name())
        .and_then(|n| n.to_str());
    let episode_len = match domain {
        Some(name) => Some(
            prac::domains::make(name)
                .with_context(|| {
                    format!("--domain: no domain '{name}' (`prac domains` lists them)")
                })?
                .spec()
                .episode_len,
        ),
        None => folder
            .and_then(prac::domains::make)
            .map(|env| env.spec().episode_len),
    };
    let at: Vec<f64> = at.iter().map(|&x| x as f64).collect();
    let runs = table::summarise_all(csvs, &at, episode_len)?;
    let path = dir.join("table.md");
    std::fs::write(&path, table::markdown(&runs, &at, normalize))
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// The policy's description, waiting for a starting server; a local server's own last words
/// come with the error.
async fn served_policy(
    client: &mut play::Client,
    policy: &str,
    local: Option<&prac::client::local::LocalServer>,
) -> anyhow::Result<prac::proto::PolicyInfo> {
    prac::client::choose_policy(client, Some(policy), prac::client::POLICY_PATIENCE)
        .await
        .map_err(|e| with_server_log(e, local))
}

async fn run(cli: Cli) -> anyhow::Result<()> {
    if let Command::Curves {
        csv,
        normalize,
        out,
        at,
        domain,
    } = &cli.command
    {
        let normalize = normalize.as_deref().map(parse_pair).transpose()?;
        let (summary, mut written) = curves::write(csv, normalize, out)?;
        print!("{summary}");
        if !at.is_empty() {
            written.push(write_table(csv, at, domain.as_deref(), normalize, out)?);
        }
        for path in written {
            println!("wrote {}", path.display());
        }
        return Ok(());
    }
    let local = match &cli.server {
        Some(_) => None,
        None => {
            let bin = prac::client::local::prac_binary(cli.prac_bin.as_deref())?;
            let bundles = cli
                .bundles
                .clone()
                .unwrap_or_else(|| PathBuf::from("bundles"));
            Some(prac::client::local::LocalServer::start(&bin, &bundles, &[]).await?)
        }
    };
    let addr = cli
        .server
        .clone()
        .or_else(|| local.as_ref().map(|l| l.addr.clone()))
        .unwrap_or_default();
    let mut client = prac::client::connect(&addr).await?;
    let outcome = match &cli.command {
        Command::Play {
            policy,
            epsilon_coef,
            epsilon,
            episodes,
            seed,
            render,
            render_step,
            json,
            plan,
        } => {
            anyhow::ensure!(*episodes >= 1, "--episodes must be >= 1");
            let plan = plan.shape()?;
            let info = served_policy(&mut client, policy, local.as_ref()).await?;
            let plan = plan.with_default_guard(&info);
            let tol = match (epsilon, epsilon_coef) {
                (Some(e), _) => Tol::Absolute(*e),
                (None, Some(c)) => Tol::Coef(*c),
                (None, None) => Tol::Absolute(0.0),
            };
            let bar = progress(*episodes as u64, !cli.quiet && !json);
            let mut results = Vec::new();
            for k in 0..*episodes as u64 {
                let snap_at = (k == 0 && render.is_some()).then_some(*render_step);
                let (result, snapshot) =
                    play::play_episode(&mut client, &info, tol, plan, seed + k, snap_at).await?;
                if k == 0 && render.is_some() && snapshot.is_none() {
                    anyhow::bail!(
                        "episode 0 ended after {} steps, before --render-step {render_step}, so \
                         nothing was drawn; give a smaller --render-step",
                        result.steps
                    );
                }
                if let (Some(out), Some(snap)) = (render, snapshot) {
                    play::render(
                        &snap,
                        &format!(
                            "{} | policy {} | seed {} | {} | step {} | plan of {}",
                            info.domain,
                            info.name,
                            seed + k,
                            match tol {
                                Tol::Coef(c) => format!("eps coef {c}"),
                                Tol::Absolute(e) => format!("eps {e}"),
                            },
                            snap.step,
                            snap.trace.len()
                        ),
                        out,
                    )?;
                    bar.suspend(|| eprintln!("wrote {}", out.display()));
                }
                if !json {
                    bar.suspend(|| {
                        println!(
                            "episode {k} (seed {}): return {:.2}, discounted {:.3}, {} steps, forecast {:.2}, replans/step {:.3}",
                            result.seed, result.ret, result.discounted, result.steps, result.forecast, result.replans_per_step
                        )
                    });
                }
                bar.inc(1);
                results.push(result);
            }
            bar.finish_and_clear();
            if *json {
                println!("{}", serde_json::to_string_pretty(&results)?);
            } else {
                let summary = prac::eval::Summary::of(results.iter().map(|e| e.outcome()));
                let (r, rs) = (summary.return_mean, summary.return_std);
                let (f, fs) =
                    prac::eval::mean_std(&results.iter().map(|e| e.forecast).collect::<Vec<_>>());
                let ended = summary.terminated;
                println!(
                    "{} episodes: return {r:.2} +- {rs:.2}, forecast {f:.2} +- {fs:.2}, \
                     ended by the task in {ended}",
                    summary.episodes
                );
                if let (Some(d), Some(ds)) = (summary.distance_mean, summary.distance_std) {
                    println!("moved forward {d:.2} +- {ds:.2} m");
                }
            }
            Ok(())
        }
        Command::Sweep {
            policy,
            coefs,
            episodes,
            seed,
            out,
            plan,
        } => {
            let plan = plan.shape()?;
            anyhow::ensure!(
                coefs.iter().all(|c| c.is_finite() && *c >= 0.0),
                "--coefs must be >= 0"
            );
            anyhow::ensure!(*episodes >= 2, "--episodes must be >= 2");
            let info = served_policy(&mut client, policy, local.as_ref()).await?;
            let plan = plan.with_default_guard(&info);
            let result =
                sweep::run(&client, &info, coefs, plan, *episodes, *seed, !cli.quiet).await?;
            sweep::write(&result, out)?;
            print!("{}", std::fs::read_to_string(out.join("sweep.md"))?);
            Ok(())
        }
        Command::Curves { .. } => unreachable!("handled above"),
    };
    if let Some(local) = local {
        local.stop().await;
    }
    outcome
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("a tokio runtime");
    match runtime.block_on(run(cli)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
