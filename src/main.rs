use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

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
    Serve(ServeArgs),
    /// Validate a bundle, print its manifest and run one forward pass.
    Inspect {
        file: PathBuf,
        /// Print only the manifest, as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Microseconds per Replan for Hopper-sized networks at plan lengths 1, 8, 32, alone and
    /// batched across sessions, against the machine's matmul rate.
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
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Serve(args) => serve(args),
        Command::Inspect { file, json } => {
            prac::cli::inspect::run(&file, json).map(|text| print!("{text}"))
        }
        Command::BenchReplan {
            seconds,
            lengths,
            batches,
        } => {
            let per_case = Duration::from_secs_f64(seconds);
            let lengths: Vec<usize> = lengths.into_iter().filter(|&l| l > 0).collect();
            let batches: Vec<usize> = batches.into_iter().filter(|&b| b > 0).collect();
            let rows = prac::cli::bench::run(&lengths, &batches, per_case);
            let matmul = prac::cli::bench::matmul_gflops(per_case);
            print!("{}", prac::cli::bench::report(&rows, matmul));
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
