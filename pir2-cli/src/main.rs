//! The `pir2` binary: a thin argument parser over `pir2_cli`.

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "pir2",
    version,
    about = "Reactive real-time flow policies (πR²)"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// Benchmarks printed side by side (schedule, runtime).
    Bench {
        /// What to measure.
        #[arg(value_parser = ["schedule", "runtime", "all"], default_value = "all")]
        what: String,
        /// Seconds per real-time run.
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.cmd {
        Cmd::Bench { what, seconds } => {
            if what == "schedule" || what == "all" {
                print!("{}", pir2_cli::bench::schedule()?);
            }
            if what == "runtime" || what == "all" {
                print!("{}", pir2_cli::bench::runtime(seconds)?);
            }
        }
    }
    Ok(())
}
