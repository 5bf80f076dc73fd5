//! The `pir2` binary: parses arguments and makes one call into the library per subcommand.
//! Every command's options are a struct of the library (`pir2_cli::commands`, `tasks`,
//! `gr00t`, `run`, `serve`) whose fields are its arguments. The old spellings `pir2 run …`
//! and `pir2 serve policy|slow --gr00t-checkpoint …` still run, as `pir2 gr00t run|serve`
//! (`pir2_cli::gr00t::new_spelling`), with a note on stderr.

use clap::{Parser, Subcommand};

use pir2_cli::commands::{self, BenchOptions, DemoOptions, ExportOptions, PlotOptions, RobotCmd};
use pir2_cli::gr00t::{self, Gr00tCmd};
use pir2_cli::serve::{self, ServeOptions};
use pir2_cli::signals::stop_flag;
use pir2_cli::tasks::{self, CollectOptions, EvalOptions, ReportOptions, TrainOptions};

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
    /// The embedded default end to end: collect → train → evaluate every deployment mode.
    Demo(DemoOptions),
    /// Collect expert demonstrations into a LeRobotDataset v3.0 directory.
    Collect(CollectOptions),
    /// Train one policy (candle MLP; leap-cube: U-Nets, the config's `policies` unless
    /// --policy) on a dataset; the checkpoint is picked in closed loop. With --task FILE: a
    /// policy on any state-only LeRobotDataset v3.0, picked on held-out episodes. (GR00T:
    /// `pir2 gr00t train`.)
    Train(TrainOptions),
    /// Evaluate a checkpoint in every mode that fits it, at each unit delay; leap-cube: run
    /// the deployment or horizon study (table, PNG, JSON).
    Eval(EvalOptions),
    /// A study's tables from its cell log alone (`cells.jsonl` of `pir2 eval leap-cube`): the
    /// chosen checkpoints and the best checkpoint per cell, mean ± std over the config's seeds
    /// and per seed, as the evaluation computes them, without the checkpoints and without
    /// simulating; the log is only read.
    Report(ReportOptions),
    /// Servers for `pir2 eval --remote`'s action head and a stub slow channel (feature
    /// `remote`; GR00T's: `pir2 gr00t serve`).
    Serve {
        #[command(subcommand)]
        cmd: ServeOptions,
    },
    /// Plot a demo result (`result.json`) or a run trace (`trace.json`) to PNG.
    Plot(PlotOptions),
    /// Export a candle checkpoint (MLP or U-Net) to ONNX for ONNX Runtime deployment (a GR00T
    /// step: `pir2 gr00t export`).
    Export(ExportOptions),
    /// Benchmarks printed side by side (schedule, runtime).
    Bench(BenchOptions),
    /// GR00T N1.7 with πR² (needs a build with `--features gr00t`): backbone features, action
    /// head fine-tuning, export, latency, a run on a robot and its servers.
    Gr00t {
        #[command(subcommand)]
        cmd: Gr00tCmd,
    },
    /// Robot tools: check a connection, run the emulators.
    Robot {
        #[command(subcommand)]
        cmd: RobotCmd,
    },
}

/// Runs the command; an error ends the process with exit status 1 and one message on stderr:
/// the error and its causes, as anyhow writes them, but never a stack backtrace (an expected
/// error such as "training interrupted" is not a crash, even with `RUST_BACKTRACE` set; panics
/// still print theirs).
fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{}", error_report(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// `Error: <message>` and, if any, the causes, numbered as anyhow numbers them.
fn error_report(e: &anyhow::Error) -> String {
    let mut out = format!("Error: {e}");
    let causes: Vec<String> = e.chain().skip(1).map(|c| c.to_string()).collect();
    match causes.len() {
        0 => {}
        1 => out.push_str(&format!("\n\nCaused by:\n    {}", causes[0])),
        _ => {
            out.push_str("\n\nCaused by:");
            for (i, c) in causes.iter().enumerate() {
                out.push_str(&format!("\n    {i}: {c}"));
            }
        }
    }
    out
}

/// The SIGINT/SIGTERM stop flag (`pir2_cli::signals`) is installed only for the commands
/// that stop on it; `gr00t` and `robot` install it for the verbs that do.
fn run() -> anyhow::Result<()> {
    let (args, note) = gr00t::new_spelling(std::env::args_os().collect());
    if let Some(note) = note {
        eprintln!("{note}");
    }
    match Cli::parse_from(args).cmd {
        Cmd::Demo(o) => commands::demo(&o),
        Cmd::Collect(o) => tasks::collect(&o, &stop_flag()),
        Cmd::Train(o) => tasks::train(&o),
        Cmd::Eval(o) => tasks::eval(&o),
        Cmd::Report(o) => tasks::report(&o),
        Cmd::Serve { cmd } => serve::serve(&cmd, stop_flag()),
        Cmd::Plot(o) => commands::plot(&o),
        Cmd::Export(o) => commands::export(&o),
        Cmd::Bench(o) => commands::bench(&o),
        Cmd::Gr00t { cmd } => gr00t::gr00t(cmd),
        Cmd::Robot { cmd } => commands::robot(&cmd),
    }
}

#[cfg(test)]
mod error_report_tests {
    use super::error_report;
    use anyhow::Context;

    #[test]
    fn the_report_is_the_message_and_its_numbered_causes() {
        let one: anyhow::Result<()> = Err(anyhow::anyhow!("disk full")).context("writing x");
        assert_eq!(
            error_report(&one.unwrap_err()),
            "Error: writing x\n\nCaused by:\n    disk full"
        );
        let two: anyhow::Result<()> = Err(anyhow::anyhow!("disk full"))
            .context("writing x")
            .context("saving step 3");
        assert_eq!(
            error_report(&two.unwrap_err()),
            "Error: saving step 3\n\nCaused by:\n    0: writing x\n    1: disk full"
        );
        assert_eq!(error_report(&anyhow::anyhow!("bad")), "Error: bad");
    }
}
