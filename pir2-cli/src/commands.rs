//! The subcommands of `pir2` that are not a task's (`pir2 collect|train|eval|report` are
//! [`crate::tasks`]'s, `pir2 gr00t` is [`crate::gr00t`]'s): one options struct (its fields
//! are the command's arguments) and one function each. They print what a user reads and
//! return errors to the binary.

use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};

use crate::study::ballplate::{self, DemoConfig};

/// `pir2 demo`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct DemoOptions {
    /// A smaller, faster run.
    #[arg(long)]
    pub quick: bool,
    /// TOML config (fields of `DemoConfig`: steps, lr, nfe, ...); flags override it.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Output directory (must not exist or be empty; default: `runs/demo-<time>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Test episodes per cell.
    #[arg(long)]
    pub episodes: Option<usize>,
}

/// `pir2 demo`: collect → train → evaluate every deployment mode; prints the table.
pub fn demo(o: &DemoOptions) -> Result<()> {
    let mut cfg = DemoConfig::load(o.config.as_deref(), o.quick)?;
    if let Some(e) = o.episodes {
        cfg.episodes = e;
    }
    let out = o.out.clone().unwrap_or_else(ballplate::default_out_dir);
    println!(
        "pir2 demo → {}  ({} demos, {} steps/policy, {} episodes/cell, seeds {:?})",
        out.display(),
        cfg.demos,
        cfg.steps,
        cfg.episodes,
        cfg.seeds
    );
    let r = ballplate::run(&cfg, &out)?;
    println!("\n{}", r.table());
    for (stage, s) in &r.timings {
        println!("{stage:>9}: {s:6.1} s");
    }
    println!(
        "wrote {}/result.json, table.md, success.png, dataset/, checkpoints/",
        out.display()
    );
    Ok(())
}

/// `pir2 plot`.
#[derive(Debug, Clone, clap::Args)]
pub struct PlotOptions {
    /// Input JSON.
    pub input: PathBuf,
    /// Output PNG (default: next to the input).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// `pir2 plot`: a study result (`result.json`) or a run trace (`trace.json`) to PNG
/// (`out` default: next to the input).
pub fn plot(o: &PlotOptions) -> Result<()> {
    let (input, out) = (o.input.as_path(), o.out.as_deref());
    let text =
        std::fs::read_to_string(input).with_context(|| format!("reading {}", input.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", input.display()))?;
    let out = out
        .map(Path::to_path_buf)
        .unwrap_or_else(|| input.with_extension("png"));
    if out.exists() {
        bail!(
            "{} already exists; choose another path with --out",
            out.display()
        );
    }
    if v.get("cells").is_some() {
        crate::study::cells::plot_result(&v, &out)?;
    } else if v.get("calls").is_some() {
        let t: pir2_runtime::RunTrace = serde_json::from_value(v)?;
        crate::plot::plot_trace(&out, &t)?;
    } else {
        bail!(
            "{} is neither a study result (cells) nor a run trace (calls)",
            input.display()
        );
    }
    println!("wrote {}", out.display());
    Ok(())
}

/// `pir2 export`.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportOptions {
    /// Checkpoint directory (config.json, stats.json, model.safetensors).
    pub checkpoint: PathBuf,
    /// Output ONNX file (must not exist).
    #[arg(long)]
    pub onnx: PathBuf,
}

/// `pir2 export`: a candle checkpoint (MLP or U-Net) to ONNX.
pub fn export(o: &ExportOptions) -> Result<()> {
    let (checkpoint, onnx) = (o.checkpoint.as_path(), o.onnx.as_path());
    if onnx.exists() {
        bail!(
            "{} already exists; choose another --onnx path",
            onnx.display()
        );
    }
    let ck = pir2_backends::checkpoint::Checkpoint::load(checkpoint)
        .with_context(|| format!("loading checkpoint {}", checkpoint.display()))?;
    pir2_backends::candle::export::export_checkpoint(&ck, onnx)
        .with_context(|| format!("exporting {} to ONNX", checkpoint.display()))?;
    println!("wrote {}", onnx.display());
    Ok(())
}

/// `pir2 bench`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchOptions {
    /// What to measure (a GR00T export: `pir2 gr00t bench`).
    #[arg(value_parser = ["schedule", "runtime", "all"], default_value = "all")]
    pub what: String,
    /// Seconds per real-time run.
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
}

/// `pir2 bench`: `schedule`, `runtime` or `all`, real-time runs of `seconds`.
pub fn bench(o: &BenchOptions) -> Result<()> {
    if o.what == "schedule" || o.what == "all" {
        print!("{}", crate::bench::schedule()?);
    }
    if o.what == "runtime" || o.what == "all" {
        print!("{}", crate::bench::runtime(o.seconds)?);
    }
    Ok(())
}

/// `pir2 robot …`.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum RobotCmd {
    /// Connect, read state, report.
    Check {
        /// xArm controller address (command port 502 unless given as host:port).
        #[arg(long)]
        xarm: Option<String>,
        /// XHand serial device.
        #[arg(long)]
        xhand: Option<PathBuf>,
        /// Clear a latched xArm error/warning (collision, emergency stop) after reporting it.
        #[arg(long)]
        clear_errors: bool,
    },
    /// Run an emulator until Ctrl-C.
    Emulate {
        /// Which robot.
        #[arg(value_parser = ["xarm", "xhand"])]
        robot: String,
        /// Host to listen on (xarm).
        #[arg(long, default_value = "127.0.0.1")]
        host: IpAddr,
        /// Use a pseudo-terminal (xhand).
        #[arg(long)]
        pty: bool,
    },
}

/// `pir2 robot check|emulate`; an emulator runs until SIGINT/SIGTERM
/// ([`crate::signals::stop_flag`]).
pub fn robot(cmd: &RobotCmd) -> Result<()> {
    match cmd {
        RobotCmd::Check {
            xarm,
            xhand,
            clear_errors,
        } => robot_check(xarm.as_deref(), xhand.as_deref(), *clear_errors),
        RobotCmd::Emulate { robot, host, pty } => {
            let which = if robot == "xarm" {
                Emulated::XArm(*host)
            } else if *pty {
                Emulated::XHandPty
            } else {
                bail!("the XHand emulator needs --pty (a pseudo-terminal other programs can open)");
            };
            robot_emulate(which, crate::signals::stop_flag())
        }
    }
}

/// `pir2 robot check`: connect to an xArm (`host` or `host:port`, port 502 by default)
/// and/or an XHand serial device, read state, print a report; an error (exit status 1) when
/// the report lists a problem (a latched error, a failed report stream, an arm in motion, a
/// finger error), so scripts can gate a run on it.
pub fn robot_check(xarm: Option<&str>, xhand: Option<&Path>, clear_errors: bool) -> Result<()> {
    let addr = match xarm {
        None => None,
        Some(s) => Some(match s.parse::<SocketAddr>() {
            Ok(a) => a,
            Err(_) => SocketAddr::new(
                s.parse::<IpAddr>()
                    .with_context(|| format!("bad --xarm address {s}"))?,
                502,
            ),
        }),
    };
    let mut opts = pir2_robots::CheckOptions::new(addr, xhand);
    opts.clear_errors = clear_errors;
    let report = pir2_robots::check_with(&opts)?;
    println!("{report}");
    if !report.healthy() {
        bail!("the robot check found problems (listed above): fix them before a run");
    }
    Ok(())
}

/// Which emulator `pir2 robot emulate` runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Emulated {
    /// The xArm controller on `host` (ports 502, 30001–30003).
    XArm(IpAddr),
    /// The XHand on a pseudo-terminal.
    XHandPty,
}

/// `pir2 robot emulate`: run an emulator until `stop`.
pub fn robot_emulate(which: Emulated, stop: Arc<AtomicBool>) -> Result<()> {
    match which {
        Emulated::XArm(host) => {
            println!("xArm emulator on {host}: ports 502, 30001-30003 (Ctrl-C to stop)");
            pir2_robots::run_xarm_emulator(host, pir2_robots::XArmPorts::standard(), stop)?;
        }
        Emulated::XHandPty => {
            let path = pir2_robots::run_xhand_emulator_pty(stop.clone())?;
            println!("XHand emulator on {} (Ctrl-C to stop)", path.display());
            while !stop.load(Ordering::SeqCst) {
                std::thread::sleep(Duration::from_millis(200));
            }
        }
    }
    Ok(())
}
