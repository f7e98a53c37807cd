use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use clap::{Parser, Subcommand};

use prac::serve::{ServeArgs, ServeConfig};

/// prac: predictable actor-critic control, served over gRPC.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Serve the bundles of a directory over gRPC (prac.v1.Prac, health, reflection).
    Serve(Box<ServeArgs>),
    /// Wait, then exit: the Kubernetes preStop pause (deploy/k8s) in an image that carries no
    /// shell, so that endpoints stop routing to a pod before its SIGTERM.
    Sleep {
        /// How long, e.g. "5s".
        #[arg(value_parser = prac::serve::duration)]
        duration: Duration,
    },
    /// Check every bundle of FROM as the server loads it, then copy them all into TO (each
    /// renamed into place); copies nothing if any is bad: the init container that moves bundles
    /// from an image into a server's volume (deploy/k8s).
    CopyBundles { from: PathBuf, to: PathBuf },
    /// Validate a bundle, print its manifest and run one forward pass.
    Inspect {
        file: PathBuf,
        /// Print only the manifest, as JSON.
        #[arg(long)]
        json: bool,
    },
    /// A bundle's deterministic policy against random actions on its domain: return, falls,
    /// forward distance.
    Evaluate {
        file: PathBuf,
        #[arg(long, default_value_t = 50)]
        episodes: usize,
        /// First episode's seed (the training runs evaluate from 2^41).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Print the evaluation as JSON.
        #[arg(long)]
        json: bool,
        /// Also write the evaluation as JSON to this file.
        #[arg(long)]
        json_out: Option<PathBuf>,
    },
    /// The domains: name, obs and act dims, episode length, control period, physics engine.
    Domains,
    /// Env steps/s per domain under random actions (one thread), and random-policy returns.
    BenchDomains {
        /// Seconds of stepping per domain.
        #[arg(long, default_value_t = 2.0)]
        seconds: f64,
        /// Random-policy episodes per domain.
        #[arg(long, default_value_t = 100)]
        episodes: usize,
        /// Discount of the discounted returns.
        #[arg(long, default_value_t = 0.98)]
        gamma: f64,
        /// Domains to measure [default: all].
        #[arg(long, value_delimiter = ',')]
        domains: Vec<String>,
        /// Also write every row as JSON (episode lengths, falls, forward distance, reward terms
        /// per step) to this file, as scripts/conformance reads it.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Plays given actions from given states of a planar walker (PyBullet's states, as
    /// scripts/conformance records them) and writes each step's observation, reward terms and
    /// end as JSON: our physics against PyBullet's from matched states.
    PlayFromStates {
        /// JSON: {"domain": "hopper", "cases": [{"state": {"root", "root_velocity", "joints",
        /// "joint_velocities"}, "actions": [[...], ...]}, ...]}.
        input: PathBuf,
        /// Where the steps go (JSON).
        #[arg(long)]
        out: PathBuf,
        /// Play this bundle's deterministic policy from each state (closed loop) instead of the
        /// cases' actions.
        #[arg(long)]
        policy: Option<PathBuf>,
        /// Steps the policy plays from each state (with --policy).
        #[arg(long, default_value_t = 100)]
        steps: usize,
    },
    /// Draw a domain (side view) to a PNG, optionally with a policy's imagined plan overlaid.
    #[cfg(feature = "render")]
    Render {
        domain: String,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long)]
        out: PathBuf,
        /// Steps played before drawing (the policy's, else random actions).
        #[arg(long, default_value_t = 0)]
        steps: u32,
        /// A bundle whose PrAC plan is drawn (predicted states as dots).
        #[arg(long)]
        policy: Option<PathBuf>,
        /// eps coefficient of the drawn plan's session (eps = C x (V_pi - V_rand)); needs
        /// --policy [default: 0, as prac-sim's].
        #[arg(long, requires = "policy", default_value_t = 0.0)]
        epsilon_coef: f64,
        #[arg(long, default_value_t = 800)]
        width: u32,
        /// Picture height; with --policy the lower third shows the committed actions.
        #[arg(long, default_value_t = 640)]
        height: u32,
    },
    /// Serve a built-in domain over DeepMind's dm_env_rpc protocol (each world one environment),
    /// for `prac train --env-server` and Python's `prac_client.envs`. Prints `listening on ADDR`
    /// once it serves.
    EnvServe {
        /// The domain (`prac domains` lists them).
        #[arg(long)]
        domain: String,
        /// HOST:PORT (port 0 picks a free one).
        #[arg(long, default_value = "127.0.0.1:50061", value_parser = prac::serve::socket_address)]
        listen: std::net::SocketAddr,
        /// Seed of each world's first episode unless its settings give one.
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Train a policy with SAC and a dynamics model (Algorithm 1) and write a bundle.
    #[cfg(feature = "train")]
    Train(Box<prac::cli::train::TrainArgs>),
    /// (Re)train a bundle's dynamics model from recorded transitions (obs, action, next_obs).
    #[cfg(feature = "train")]
    FitModel(prac::cli::train::FitArgs),
    /// SAC updates/s ([256, 256], batch 256), model updates/s, env steps/s while training, and
    /// the replay buffer's checkpoint save and load times.
    #[cfg(feature = "train")]
    BenchTrain {
        /// Seconds measured per update kind.
        #[arg(long, default_value_t = 3.0)]
        seconds: f64,
        /// Domain of the short training run.
        #[arg(long, default_value = "hopper")]
        domain: String,
        /// Steps of the short training run.
        #[arg(long, default_value_t = 2000)]
        steps: u64,
        /// Transitions (Humanoid-sized) in the replay buffer whose checkpoint save and load are
        /// timed; 0 skips it.
        #[arg(long, default_value_t = 1_000_000)]
        replay_transitions: usize,
    },
    /// The MLP kernel's GFLOP/s at 1 to 1024 rows per call, and microseconds per Replan for
    /// Hopper-sized networks at plan lengths 1, 8, 32, alone and batched across sessions, against
    /// the machine's matmul rate.
    BenchReplan {
        /// Seconds measured per case.
        #[arg(long, default_value_t = 1.0)]
        seconds: f64,
        /// Plan lengths to measure.
        #[arg(long, value_delimiter = ',', default_value = "1,8,32")]
        lengths: Vec<usize>,
        /// Sessions replanned together (cross-session batch sizes).
        #[arg(long, value_delimiter = ',', default_value = "1,8,64")]
        batches: Vec<usize>,
        /// Instead: Replan on these bundles (repeatable), one session in-process on its domain's
        /// simulated trajectories: microseconds, FLOPs and network calls per step.
        #[arg(long)]
        bundle: Vec<std::path::PathBuf>,
        /// eps coefficient of --bundle's session (eps = coef x (V_pi - V_rand)).
        #[arg(long, default_value_t = 0.005)]
        epsilon_coef: f64,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Serve(args) => serve(*args),
        Command::CopyBundles { from, to } => prac::cli::bundles::copy(&from, &to).map(|names| {
            println!(
                "copied {} bundles to {}: {}",
                names.len(),
                to.display(),
                names.join(", ")
            )
        }),
        Command::Sleep { duration } => {
            std::thread::sleep(duration);
            Ok(())
        }
        Command::Inspect { file, json } => {
            prac::cli::inspect::run(&file, json).map(|text| print!("{text}"))
        }
        Command::Evaluate {
            file,
            episodes,
            seed,
            json,
            json_out,
        } => prac::cli::evaluate::run(&file, episodes, seed).and_then(|e| {
            if let Some(path) = json_out {
                std::fs::write(&path, serde_json::to_string_pretty(&e)? + "\n")
                    .map_err(|err| anyhow::anyhow!("writing {}: {err}", path.display()))?;
            }
            let text = if json {
                serde_json::to_string_pretty(&e)? + "\n"
            } else {
                prac::cli::evaluate::report(&e)
            };
            print!("{text}");
            Ok(())
        }),
        Command::Domains => {
            print!("{}", prac::cli::domains::table());
            Ok(())
        }
        Command::BenchDomains {
            seconds,
            episodes,
            gamma,
            domains,
            json,
        } => {
            let names: Vec<&str> = if domains.is_empty() {
                prac::domains::DOMAINS.to_vec()
            } else {
                domains.iter().map(String::as_str).collect()
            };
            prac::cli::domains::bench(
                &names,
                Duration::from_secs_f64(seconds),
                episodes.max(1),
                gamma,
            )
            .and_then(|rows| {
                print!(
                    "{}",
                    prac::cli::domains::report(&rows, episodes.max(1), gamma)
                );
                match json {
                    Some(path) => std::fs::write(&path, serde_json::to_string_pretty(&rows)?)
                        .with_context(|| format!("writing {}", path.display())),
                    None => Ok(()),
                }
            })
        }
        Command::PlayFromStates {
            input,
            out,
            policy,
            steps,
        } => prac::cli::domains::play_from_states(
            &input,
            &out,
            policy
                .as_deref()
                .map(|bundle| prac::cli::domains::ClosedLoop { bundle, steps }),
        ),
        #[cfg(feature = "render")]
        Command::Render {
            domain,
            seed,
            out,
            steps,
            policy,
            epsilon_coef,
            width,
            height,
        } => prac::cli::render::run(&prac::cli::render::RenderRequest {
            domain: &domain,
            seed,
            out: &out,
            steps,
            policy: policy.as_deref(),
            epsilon_coef,
            size: (width.clamp(64, 4096), height.clamp(64, 4096)),
        })
        .map(|n| println!("wrote {} ({n} planned states drawn)", out.display())),
        Command::EnvServe {
            domain,
            listen,
            seed,
        } => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .map_err(anyhow::Error::from)
            .and_then(|runtime| runtime.block_on(prac::env_rpc::serve(&domain, listen, seed))),
        #[cfg(feature = "train")]
        Command::Train(args) => prac::cli::train::train(*args),
        #[cfg(feature = "train")]
        Command::FitModel(args) => prac::cli::train::fit(args),
        #[cfg(feature = "train")]
        Command::BenchTrain {
            seconds,
            domain,
            steps,
            replay_transitions,
        } => prac::train::bench::run(
            Duration::from_secs_f64(seconds),
            &domain,
            steps,
            replay_transitions,
        )
        .map(|b| print!("{}", prac::train::bench::report(&b))),
        Command::BenchReplan {
            seconds,
            bundle,
            epsilon_coef,
            ..
        } if !bundle.is_empty() => (|| {
            let per_case = Duration::from_secs_f64(seconds);
            let rows = bundle
                .iter()
                .map(|path| prac::cli::bench::bundle_replan(path, epsilon_coef, per_case))
                .collect::<anyhow::Result<Vec<_>>>()?;
            let matmul = prac::cli::bench::matmul_gflops(per_case);
            print!("{}", prac::cli::bench::bundle_report(&rows, matmul));
            Ok(())
        })(),
        Command::BenchReplan {
            seconds,
            lengths,
            batches,
            ..
        } => {
            let per_case = Duration::from_secs_f64(seconds);
            let lengths: Vec<usize> = lengths.into_iter().filter(|&l| l > 0).collect();
            let batches: Vec<usize> = batches.into_iter().filter(|&b| b > 0).collect();
            let rows = prac::cli::bench::run(&lengths, &batches, per_case);
            let kernel = prac::cli::bench::kernel(&[1, 8, 64, 256, 1024], per_case);
            let matmul = prac::cli::bench::matmul_gflops(per_case);
            print!("{}", prac::cli::bench::report(&rows, &kernel, matmul));
            Ok(())
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let config = ServeConfig::resolve(&args)?;
    prac::serve::init_logging(config.log_format);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(prac::serve::run(config))
}
