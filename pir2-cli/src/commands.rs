//! The subcommands of `pir2`, one function each, taking plain option structs (the argument
//! parser lives in `main.rs`). They print what a user reads and return errors to the binary.

use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};

use pir2_backends::candle::CandleModel;
use pir2_runtime::Policy;
use pir2_sim::dataset::WriteMode;

use crate::study::ballplate::{self, DemoConfig};
use crate::study::dataset::{self, DatasetTaskConfig};
use crate::study::pipeline::Models;

/// The tasks the stock pipeline knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TaskName {
    /// The embedded ball-on-plate task.
    BallPlate,
    /// The Leap-hand cube (feature `mujoco`).
    LeapCube,
}

/// `pir2 demo`.
#[derive(Debug, Clone, Default)]
pub struct DemoOptions {
    /// A smaller, faster run.
    pub quick: bool,
    /// TOML config (fields of [`DemoConfig`]).
    pub config: Option<PathBuf>,
    /// Output directory (default `runs/demo-<time>`).
    pub out: Option<PathBuf>,
    /// Test episodes per cell.
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
        cfg.train_steps,
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

/// `pir2 collect`.
#[derive(Debug, Clone)]
pub struct CollectOptions {
    /// Which task.
    pub task: TaskName,
    /// Dataset directory.
    pub out: PathBuf,
    /// Leap cube: expert seeds (episodes stored seed-major).
    pub seeds: Vec<u64>,
    /// Leap cube: episodes per expert seed.
    pub per_seed: usize,
    /// Leap cube: the faster, weaker MPC expert.
    pub fast: bool,
    /// Leap cube: trained expert weights (one for all seeds, or one per seed) instead of the MPC.
    pub expert: Vec<PathBuf>,
    /// Ball-plate: episodes to keep.
    pub episodes: usize,
    /// Ball-plate: seed.
    pub seed: u64,
    /// New, resume or overwrite.
    pub mode: WriteMode,
    /// Ctrl-C: finish the episode in progress, write what was kept, and return.
    pub stop: Arc<AtomicBool>,
}

/// `pir2 collect`: expert demonstrations into a LeRobotDataset v3.0 directory.
pub fn collect(o: &CollectOptions) -> Result<()> {
    match o.task {
        TaskName::LeapCube => {
            let expert = if o.expert.is_empty() {
                crate::leap_cmd::ExpertChoice::Mpc { fast: o.fast }
            } else {
                crate::leap_cmd::ExpertChoice::Weights(o.expert.clone())
            };
            crate::leap_cmd::collect(&o.out, &o.seeds, o.per_seed, o.mode, &expert, &o.stop)
        }
        TaskName::BallPlate => {
            let (stats, summary) =
                ballplate::collect_into(&o.out, o.episodes, o.seed, o.mode, &o.stop)?;
            if stats.stopped {
                println!(
                    "interrupted: {} holds {} of {} episodes ({} written now); \
                     `pir2 collect --resume` adds the rest",
                    o.out.display(),
                    summary.total_episodes,
                    o.episodes,
                    summary.written_episodes
                );
            } else {
                println!(
                    "wrote {} episodes to {}",
                    summary.written_episodes,
                    o.out.display()
                );
            }
            Ok(())
        }
    }
}

/// `pir2 train`.
#[derive(Debug, Clone)]
pub struct TrainOptions {
    /// Which task.
    pub task: TaskName,
    /// Dataset directory.
    pub data: PathBuf,
    /// Which policy (required for ball-plate; Leap cube: all four when absent).
    pub policy: Option<Policy>,
    /// Checkpoint directory (must not exist).
    pub out: PathBuf,
    /// TOML config of the task.
    pub config: Option<PathBuf>,
    /// Seed (ball-plate; the Leap cube trains the config's seeds).
    pub seed: u64,
    /// Leap cube, dataset task: continue an interrupted run in `out`.
    pub resume: bool,
    /// A dataset task file (`task.toml`, [`DatasetTaskConfig`]): train on any state-only
    /// LeRobotDataset v3.0 instead of a stock task.
    pub task_file: Option<PathBuf>,
}

/// `pir2 train`: train a policy (ball-plate) or the study's policies (Leap cube).
pub fn train(o: &TrainOptions) -> Result<()> {
    if let Some(file) = &o.task_file {
        return train_dataset(o, file);
    }
    match o.task {
        TaskName::LeapCube => {
            let args = crate::leap_cmd::LeapArgs {
                config: o.config.as_deref(),
                data: Some(&o.data),
                ..Default::default()
            };
            let policies: Vec<Policy> = o.policy.into_iter().collect();
            crate::leap_cmd::train(&args, &policies, &o.out, o.resume)
        }
        TaskName::BallPlate => {
            if o.resume {
                bail!("--resume is for leap-cube training; ballplate trains in minutes");
            }
            let policy = o.policy.context("--policy is required for ballplate")?;
            if o.resume {
                bail!(
                    "--resume is for leap-cube studies (a ball-plate evaluation is not resumable)"
                );
            }
            let cfg = DemoConfig::load(o.config.as_deref(), false)?;
            let scores = ballplate::train_checkpoint(&o.data, policy, &cfg, o.seed, &o.out)?;
            println!("closed-loop validation (step, success): {scores:?}");
            println!("best checkpoint: {}", o.out.join("best").display());
            Ok(())
        }
    }
}

/// `pir2 train --data DATASET --task task.toml --out DIR`: the dataset task.
fn train_dataset(o: &TrainOptions, file: &Path) -> Result<()> {
    if o.policy.is_some() || o.config.is_some() || o.seed != 0 {
        bail!(
            "--policy, --config and --seed are for the stock tasks; with --task the task file \
             names the policy, the model and the seed"
        );
    }
    let cfg = DatasetTaskConfig::load(file)?;
    let r = dataset::train(&o.data, &cfg, &o.out, o.resume)?;
    println!("held-out episodes: {:?}", r.held_out);
    println!("step      flow loss  open-loop RMSE  (normalised)");
    for c in &r.checkpoints {
        println!(
            "{:<9} {:<10.4} {:<15.4} {:.4}{}",
            c.step,
            c.flow_loss,
            c.open_loop.rmse,
            c.open_loop.nrmse,
            if Some(c.step) == r.best_step {
                "  ← best"
            } else {
                ""
            }
        );
    }
    println!(
        "best checkpoint (lowest {}): {}",
        r.metric,
        o.out.join("best").display()
    );
    Ok(())
}

/// Where `pir2 eval --remote` sends the action-head calls.
#[derive(Debug, Clone)]
pub struct RemoteOptions {
    /// Zenoh endpoint of `pir2 serve policy`.
    pub endpoint: String,
    /// Time a request may take before it is sent again.
    pub timeout: Duration,
    /// Consecutive timeouts before the evaluation stops.
    pub max_failed: u32,
    /// Time to wait for the server at start.
    pub connect_timeout: Duration,
    /// Mutual TLS (for a `tls/…` endpoint).
    pub tls: crate::serve::TlsOptions,
}

/// `pir2 eval`.
#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// Which task.
    pub task: TaskName,
    /// Checkpoint directory (Leap cube: trained policies).
    pub checkpoint: Option<PathBuf>,
    /// Which policy the checkpoint is (ball-plate).
    pub policy: Option<Policy>,
    /// Leap cube: `deployment` or `horizon`.
    pub study: String,
    /// Leap cube: TOML config.
    pub config: Option<PathBuf>,
    /// Leap cube: dataset directory.
    pub data: Option<PathBuf>,
    /// Leap cube: output directory.
    pub out: Option<PathBuf>,
    /// Unit delays (ball-plate).
    pub d0: Vec<usize>,
    /// Episodes per cell.
    pub episodes: Option<usize>,
    /// Seed of the evaluation episodes (ball-plate).
    pub seed: u64,
    /// Write the cells as JSON here (ball-plate).
    pub json: Option<PathBuf>,
    /// Run the action head on a policy server (ball-plate, feature `remote`).
    pub remote: Option<RemoteOptions>,
    /// Leap cube: continue the interrupted evaluation in `out`.
    pub resume: bool,
    /// Leap cube: train the listed policies missing from `checkpoint` instead of refusing.
    pub train_missing: bool,
}

/// `pir2 eval`: a checkpoint in every mode that fits it at each unit delay (ball-plate,
/// locally or through a policy server), or a Leap-cube study.
pub fn eval(o: &EvalOptions) -> Result<()> {
    if o.task == TaskName::LeapCube {
        let args = crate::leap_cmd::LeapArgs {
            config: o.config.as_deref(),
            data: o.data.as_deref(),
            pretrained: o.checkpoint.as_deref(),
            episodes: o.episodes,
            train_missing: o.train_missing,
        };
        let out = o
            .out
            .as_deref()
            .context("--out is required for leap-cube")?;
        return crate::leap_cmd::eval(&o.study, &args, out, o.resume);
    }
    let checkpoint = o
        .checkpoint
        .as_deref()
        .context("--checkpoint is required for ballplate")?;
    let policy = o.policy.context("--policy is required for ballplate")?;
    if let Some(p) = o.json.as_ref().filter(|p| p.exists()) {
        bail!("{} already exists; choose another --json path", p.display());
    }
    let model = CandleModel::load(checkpoint)
        .with_context(|| format!("loading {}", checkpoint.display()))?;
    let episodes = o.episodes.unwrap_or(100);
    let (cells, labels) = match &o.remote {
        None => {
            let models = Models::local(&model)?;
            ballplate::eval_checkpoint(&models, policy, &o.d0, episodes, o.seed)?
        }
        Some(r) => {
            let remote = crate::serve::RemotePolicy::connect(
                &r.endpoint,
                &r.tls,
                r.timeout,
                r.connect_timeout,
                r.max_failed,
            )?;
            eprintln!("connected to the policy server at {}", r.endpoint);
            let models = remote.models(&model);
            let res = ballplate::eval_checkpoint(&models, policy, &o.d0, episodes, o.seed)
                .with_context(|| remote.context());
            eprintln!("{}", remote.report());
            res?
        }
    };
    println!("{}", crate::study::table(&cells, &labels, &o.d0));
    if let Some(p) = &o.json {
        std::fs::write(p, serde_json::to_string_pretty(&cells)?)?;
    }
    Ok(())
}

/// `pir2 plot`: a study result (`result.json`) or a run trace (`trace.json`) to PNG
/// (`out` default: next to the input).
pub fn plot(input: &Path, out: Option<&Path>) -> Result<()> {
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
        crate::plot::plot_result(&v, &out)?;
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

/// `pir2 export`: a candle checkpoint (MLP or U-Net) to ONNX.
pub fn export(checkpoint: &Path, onnx: &Path) -> Result<()> {
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

/// `pir2 export STEP_DIR --gr00t OUT` (see `pir2_cli::study::gr00t::export`).
pub fn export_gr00t(step: &Path, out: &Path) -> Result<()> {
    #[cfg(feature = "gr00t")]
    {
        let s = crate::study::gr00t::export(step, out)?;
        println!(
            "wrote {} (H = {}, d_vis_max = {}, trained as {}): {}",
            s.out.display(),
            s.horizon,
            s.d_vis_max,
            s.trained,
            s.files.join(", ")
        );
        println!(
            "add the backbone (onnx/backbone.onnx) and the VLM's tokenizer.json to run it \
             (docs/gr00t-contract.md)"
        );
        Ok(())
    }
    #[cfg(not(feature = "gr00t"))]
    {
        let _ = (step, out);
        bail!("export --gr00t needs a pir2 built with feature `gr00t` (--features gr00t)")
    }
}

/// `pir2 bench`: `schedule`, `runtime` or `all`, real-time runs of `seconds`.
pub fn bench(
    what: &str,
    seconds: f64,
    gr00t: Option<(&Path, &str)>,
    ep: &crate::ep::EpOptions,
) -> Result<()> {
    if what == "schedule" || what == "all" {
        print!("{}", crate::bench::schedule()?);
    }
    if what == "runtime" || what == "all" {
        print!("{}", crate::bench::runtime(seconds)?);
    }
    if what == "gr00t" {
        let (checkpoint, task) = gr00t.context("bench gr00t needs --checkpoint and --task")?;
        #[cfg(feature = "gr00t")]
        print!(
            "{}",
            crate::bench::gr00t(checkpoint, task, ep, seconds)
                .with_context(|| format!("benchmarking {}", checkpoint.display()))?
        );
        #[cfg(not(feature = "gr00t"))]
        {
            let _ = (checkpoint, task, ep);
            bail!("bench gr00t needs a pir2 built with feature `gr00t` (--features gr00t)");
        }
    }
    Ok(())
}

/// `pir2 robot check`: connect to an xArm (`host` or `host:port`, port 502 by default)
/// and/or an XHand serial device, read state, print a report.
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
