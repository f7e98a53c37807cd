//! `prac`: the server (`prac serve`) and the commands around it, each in its own file in `cli/`.

mod cli;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

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
    Serve(Box<prac::serve::ServeArgs>),
    /// Wait, then exit: the Kubernetes preStop pause (deploy/k8s) in an image that carries no
    /// shell, so that endpoints stop routing to a pod before its SIGTERM.
    Sleep(cli::sleep::SleepArgs),
    /// Check every bundle of FROM as the server loads it, then copy them all into TO (each
    /// renamed into place); copies nothing if any is bad: the init container that moves bundles
    /// from an image into a server's volume (deploy/k8s).
    CopyBundles(cli::copy_bundles::CopyBundlesArgs),
    /// Write a bundle's actor, critics and dynamics model as ONNX files (environment units,
    /// normalisation inside) with prac.json, the contract of what they take and give.
    #[cfg(feature = "onnx")]
    ExportOnnx(cli::export_onnx::ExportOnnxArgs),
    /// Validate a bundle, print its manifest and run one forward pass.
    Inspect(cli::inspect::InspectArgs),
    /// A bundle's deterministic policy against random actions on its domain: return, falls,
    /// forward distance.
    Evaluate(cli::evaluate::EvaluateArgs),
    /// The domains: name, obs and act dims, episode length, control period, physics engine.
    Domains(cli::domains::DomainsArgs),
    /// Env steps/s per domain under random actions (one thread), and random-policy returns.
    BenchDomains(cli::bench_domains::BenchDomainsArgs),
    /// Plays given actions from given states of a planar walker (PyBullet's states, as
    /// scripts/conformance records them) and writes each step's observation, reward terms and
    /// end as JSON: our physics against PyBullet's from matched states.
    PlayFromStates(cli::play_from_states::PlayFromStatesArgs),
    /// Draw a domain (side view) to a PNG, optionally with a policy's imagined plan overlaid.
    #[cfg(feature = "render")]
    Render(cli::render::RenderArgs),
    /// Serve a built-in domain over DeepMind's dm_env_rpc protocol (each world one environment),
    /// for `prac train --env-server` and Python's `prac_client.envs`. Prints `listening on ADDR`
    /// once it serves.
    EnvServe(cli::env_serve::EnvServeArgs),
    /// Train a policy with SAC and a dynamics model (Algorithm 1) and write a bundle.
    #[cfg(feature = "train")]
    Train(Box<cli::train::TrainArgs>),
    /// (Re)train a bundle's dynamics model from recorded transitions (obs, action, next_obs).
    #[cfg(feature = "train")]
    FitModel(cli::fit_model::FitModelArgs),
    /// SAC updates/s ([256, 256], batch 256), model updates/s, env steps/s while training, and
    /// the replay buffer's checkpoint save and load times.
    #[cfg(feature = "train")]
    BenchTrain(cli::bench_train::BenchTrainArgs),
    /// The MLP kernel's GFLOP/s at 1 to 1024 rows per call, and microseconds per Replan for
    /// Hopper-sized networks at plan lengths 1, 8, 32, alone and batched across sessions, against
    /// the machine's matmul rate.
    BenchReplan(cli::bench_replan::BenchReplanArgs),
    /// The dynamics model's forecasts against what followed on the bundle's own domain, at each
    /// eps coefficient: k-step errors of held plans and along the executed actions, predictions
    /// against the observation bounds, and what the plan held before each fall.
    ModelError(cli::model_error::ModelErrorArgs),
    /// Write each bundle's domain observation space into it as `obs_bounds` (format 4), which
    /// keeps the model's forecasts inside it: for bundles of prac's domains made before bundles
    /// carried them.
    ObsBounds(cli::obs_bounds::ObsBoundsArgs),
    /// Set the plan guard a bundle's sessions get when they ask for none (`default_guard`,
    /// format 5), or remove it with --none.
    DefaultGuard(cli::default_guard::DefaultGuardArgs),
}

fn main() -> ExitCode {
    let result = match Cli::parse().command {
        Command::Serve(args) => cli::serve::run(*args),
        Command::Sleep(args) => args.run(),
        Command::CopyBundles(args) => args.run(),
        #[cfg(feature = "onnx")]
        Command::ExportOnnx(args) => args.run(),
        Command::Inspect(args) => args.run(),
        Command::Evaluate(args) => args.run(),
        Command::Domains(args) => args.run(),
        Command::BenchDomains(args) => args.run(),
        Command::PlayFromStates(args) => args.run(),
        #[cfg(feature = "render")]
        Command::Render(args) => args.run(),
        Command::EnvServe(args) => args.run(),
        #[cfg(feature = "train")]
        Command::Train(args) => args.run(),
        #[cfg(feature = "train")]
        Command::FitModel(args) => args.run(),
        #[cfg(feature = "train")]
        Command::BenchTrain(args) => args.run(),
        Command::BenchReplan(args) => args.run(),
        Command::ModelError(args) => args.run(),
        Command::ObsBounds(args) => args.run(),
        Command::DefaultGuard(args) => args.run(),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
