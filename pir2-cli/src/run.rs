//! `pir2 gr00t run gr00t-xarm-xhand`: the GR00T-N1.7 xArm6 + XHand stack on a robot (feature
//! `gr00t`; with feature `remote` the backbone features may come from `pir2 gr00t serve
//! slow` and the action head may run on `pir2 gr00t serve policy`).
//!
//! Long on purpose: the run's whole wiring (checks before any robot is connected, emulated or
//! real robots, local or remote head and backbone, the signal hooks, the report) reads top to
//! bottom in one place; each piece is a short function.
//!
//! Wiring: `pir2_backends::gr00t::run_gr00t_report` (action head one NFE per 25 Hz tick on
//! the action worker, backbone on the slow worker) on the safety-wrapped xArm6 + XHand
//! composite of `pir2-robots`, either the real devices (`--xarm ADDR --xhand DEVICE`) or
//! the emulators started in-process (`--emulate`). A run is bounded by `--ticks` /
//! `--seconds` or Ctrl-C; the robot is stopped on every exit path of the driver.
//!
//! Cameras: `--camera /dev/videoN` is a live V4L2 camera (`pir2_robots::V4l2Camera`, Linux;
//! `--camera-size WxH`, `--camera-format`), stamped with the driver's capture times;
//! `--emulate` and `--synthetic-camera` use a synthetic 640×480 camera
//! (`gr00t::testing::SyntheticCamera`); `--frames DIR` replays recorded frames
//! (`pir2_robots::FolderCamera`); `--remote-slow ENDPOINT` takes the backbone features
//! (camera + backbone on another machine) from `pir2 gr00t serve slow`. A local camera is
//! opened before any robot is connected, so a wrong device fails while nothing is powered.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::Result;
use serde::{Deserialize, Serialize};

/// Options of `pir2 gr00t run`.
#[derive(Debug, Clone, clap::Args)]
pub struct RunOptions {
    /// The stack to run.
    #[arg(value_parser = ["gr00t-xarm-xhand"])]
    pub stack: String,
    /// Checkpoint directory (export layout in docs/gr00t-contract.md).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Task: a key of the embodiment's tasks (`catch_book`, …) or one of their prompts
    /// verbatim ("catch the book").
    #[arg(long)]
    pub task: String,
    /// Accept a `--task` that is not a configured task and send it as the prompt verbatim.
    #[arg(long)]
    pub free_prompt: bool,
    /// xArm controller address (command port 502 unless given as host:port).
    #[arg(long, required_unless_present = "emulate", conflicts_with = "emulate")]
    pub xarm: Option<String>,
    /// XHand serial device (RS-485 adapter).
    #[arg(long, required_unless_present = "emulate", conflicts_with = "emulate")]
    pub xhand: Option<PathBuf>,
    /// Clear a latched xArm error/warning (collision, emergency stop) at connect instead of
    /// refusing to start.
    #[arg(long)]
    pub clear_errors: bool,
    /// Start the xArm6 and XHand emulators in-process and run against them (synthetic
    /// camera unless --remote-slow).
    #[arg(long)]
    pub emulate: bool,
    /// Use the synthetic camera with real robots.
    #[arg(long)]
    pub synthetic_camera: bool,
    /// A live V4L2 (USB/UVC) camera, e.g. /dev/video0 (Linux): frames are stamped with the
    /// driver's capture time, so the slow channel's age counts from the sensor. Repeat it
    /// once per camera view of the embodiment (`prompt.chat.images`), in its view order.
    #[arg(long, conflicts_with_all = ["frames", "remote_slow", "synthetic_camera"])]
    pub camera: Vec<PathBuf>,
    /// With --camera: frame size WIDTHxHEIGHT, which the camera must offer (default: the
    /// offered size nearest 640x480); the same for every camera.
    #[arg(long, requires = "camera")]
    pub camera_size: Option<String>,
    /// With --camera: pixel format (default: the best the camera offers at the size).
    #[arg(long, requires = "camera", value_parser = ["mjpeg", "yuyv", "rgb24"])]
    pub camera_format: Option<String>,
    /// Replay recorded frames as the camera: every .png/.jpg of this folder in file-name
    /// order, looping (GR00T's preprocessing applies as to a live camera). Repeat it once per
    /// camera view, in the embodiment's view order.
    #[arg(long, conflicts_with_all = ["remote_slow", "synthetic_camera"])]
    pub frames: Vec<PathBuf>,
    /// With --frames: ms between frames.
    #[arg(long, default_value_t = 33)]
    pub frame_ms: u64,
    /// Take backbone features from `pir2 gr00t serve slow` at this Zenoh endpoint
    /// (e.g. `tcp/10.0.0.2:7448`); needs feature `remote`.
    #[arg(long)]
    pub remote_slow: Option<String>,
    /// Run the action head on `pir2 gr00t serve policy` at this Zenoh endpoint
    /// (e.g. `tcp/10.0.0.3:7447`) instead of in this process; needs feature `remote`. The
    /// checkpoint directory is still read here (embodiment, statistics, vocabulary) and the
    /// head is checked before any robot is connected. Each call's round trip is part of the
    /// measured call latency, so `d` grows with the network.
    #[arg(long)]
    pub remote_policy: Option<String>,
    /// Run the fine-tuned action head in candle from this `pir2 gr00t train` step directory
    /// (model.safetensors + config.json) instead of the checkpoint's ONNX head graphs; the
    /// checkpoint still gives the backbone, tokenizer, statistics and embodiment (the step's
    /// run must have the same statistics.json and embodiment.toml).
    #[arg(long, conflicts_with = "remote_policy")]
    pub candle_head: Option<PathBuf>,
    /// With --remote-policy: how long one request may take before it is sent again, ms.
    #[arg(long, default_value_t = 200)]
    pub policy_timeout_ms: u64,
    /// With --remote-policy: requests in a row without a reply before the run stops the
    /// robot (safety stop).
    #[arg(long, default_value_t = 10)]
    pub max_failed_calls: u32,
    /// With --remote-policy: seconds to wait for the policy server at start-up.
    #[arg(long, default_value_t = 10.0)]
    pub connect_timeout: f64,
    /// Stop after this many control ticks.
    #[arg(long, conflicts_with = "seconds")]
    pub ticks: Option<u64>,
    /// Stop after this many seconds (rounded to ticks of the embodiment's rate).
    #[arg(long)]
    pub seconds: Option<f64>,
    /// Seconds to wait for the first backbone features.
    #[arg(long, default_value_t = 60.0)]
    pub slow_timeout: f64,
    /// Stale-slow stop: stop the robot once the backbone features are older than the
    /// checkpoint's d_vis_max ticks for longer than this, ms (default: the embodiment's
    /// `safety.slow_grace_ms`, 200 if unset).
    #[arg(long)]
    pub slow_grace_ms: Option<f64>,
    /// Control watchdog: this long without a clean action (the policy's calls stalled or its
    /// chunks ran out: overruns, holds) stops the robot with a safety stop, ms. At most 5000,
    /// e.g. to ride through a restart of `pir2 gr00t serve policy`.
    #[arg(long, default_value_t = 1000.0)]
    pub stall_limit_ms: f64,
    /// Write the run summary (and the per-call trace) as JSON here; a failed run writes its
    /// error instead. The file must not exist (a report is never replaced).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Deployment (default: the checkpoint's `[policy] mode`, else pir2_async). A mode the
    /// action head was not trained for (`[policy] trained`) is refused.
    #[arg(long, value_parser = ["pir2_async", "pir2_sync", "sync_flow", "naive_async", "inference_rtc", "rtc"])]
    pub mode: Option<String>,
    /// πR²: NFEs per action (must equal the checkpoint's `[policy] nfe`).
    #[arg(long)]
    pub nfe: Option<usize>,
    /// Flow baselines and train-time RTC: Euler steps K per chunk.
    #[arg(long)]
    pub flow_steps: Option<usize>,
    /// Sync flow: actions executed per chunk.
    #[arg(long)]
    pub h: Option<usize>,
    /// Naive async: ACT temporal ensembling with this decay m.
    #[arg(long, conflicts_with = "no_ensemble")]
    pub ensemble: Option<f32>,
    /// Naive async: plain swap even if the checkpoint's `[policy] ensemble` is set.
    #[arg(long)]
    pub no_ensemble: bool,
    /// N1.7 inference-time RTC: slots of each call started from the chunk in flight
    /// (default: the checkpoint's `[policy] rtc_overlap`, else every slot it still covers).
    #[arg(long)]
    pub rtc_overlap: Option<usize>,
    /// N1.7 inference-time RTC: rate of the velocity-strength ramp (default: the
    /// checkpoint's `[policy] rtc_ramp_rate`, else 5).
    #[arg(long)]
    pub rtc_ramp_rate: Option<f32>,
    /// Record the action head's first calls into DIR (diagnostic): for each of the first
    /// --record-calls calls, DIR/nfe-KKKK.safetensors with exactly what the four ONNX graphs
    /// were fed (state, embodiment_id, actions, timesteps, sa_embs, timestep, vl_embs, the VL
    /// masks) and what the head saw and returned (d_vis, tau, x, velocity), to compare with the
    /// training framework (docs/gr00t-contract.md, "Recording the head's calls"). One file
    /// write per recorded call: not for latency runs. DIR must be empty or new (checked before
    /// the robot moves); the checkpoint's ONNX head only (not --candle-head or
    /// --remote-policy).
    #[arg(long, value_name = "DIR")]
    pub record_nfe: Option<PathBuf>,
    /// With --record-nfe: how many calls to record (the first ones).
    #[arg(long, value_name = "N", default_value_t = 1, requires = "record_nfe")]
    pub record_calls: usize,
    /// Mutual TLS for `tls/…` endpoints of --remote-policy / --remote-slow.
    #[command(flatten)]
    pub tls: crate::remote::TlsOptions,
    /// Where ONNX Runtime runs the action head and the backbone.
    #[command(flatten)]
    pub ep: crate::ep::EpOptions,
}

/// What a run reports (printed, and written by `--json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunSummary {
    /// The prompt sent to the backbone.
    pub prompt: String,
    /// The deployment mode and its schedule.
    pub mode: pir2_runtime::Mode,
    /// Where the robot was (`emulated` or the devices).
    pub robot: String,
    /// Where the backbone features came from.
    pub slow: String,
    /// Where the action head ran.
    pub head: String,
    /// Calls per `d_vis` value fed through the delay embedding.
    pub d_vis_counts: Vec<u64>,
    /// Action groups the policy predicts relative to the robot's state, as `group → state
    /// group` (each chunk decoded against the state at its snapshot; empty: all absolute).
    #[serde(default)]
    pub relative_actions: Vec<String>,
    /// Commands the emulated hand received (emulated runs).
    pub hand_commands: Option<u64>,
    /// Motion state of the emulated arm at the end (emulated runs; 4 = stopped, as the run's
    /// `SET_STATE 4` leaves it).
    #[serde(default)]
    pub arm_state: Option<u8>,
    /// Frames the local camera delivered (synthetic, replayed or live; local camera runs).
    pub camera_frames: Option<u64>,
    /// Remote slow-channel counters (`--remote-slow` runs).
    #[cfg(feature = "remote")]
    pub remote_slow: Option<pir2_runtime::remote::RemoteCounters>,
    /// Remote action-head counters (`--remote-policy` runs).
    #[cfg(feature = "remote")]
    pub remote_policy: Option<pir2_runtime::remote::RemoteCounters>,
    /// The run's trace (ticks, swaps, overruns, latencies, per-call `d` and `d_vis`).
    pub trace: pir2_runtime::RunTrace,
    /// The safety limits the run enforced.
    #[serde(default)]
    pub limits: Option<LimitsInForce>,
}

/// The safety envelope a run enforces, printed at its start and written by `--json`: the
/// robot's limits as tightened by the checkpoint's `[safety]` table, the control rate and the
/// stale-slow grace (as tightened by `--slow-grace-ms`). Vectors have one entry per action
/// dimension, in the action vector's order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LimitsInForce {
    /// Control rate, Hz.
    pub control_hz: f64,
    /// Stale-slow grace, ms.
    pub slow_grace_ms: f64,
    /// Control watchdog: the longest run of ticks without a clean action, ms.
    #[serde(default = "default_stall_limit_ms")]
    pub stall_limit_ms: f64,
    /// The action groups, `name` and width, in order.
    pub groups: Vec<(String, usize)>,
    /// Lower joint limits, rad.
    pub lower: Vec<f32>,
    /// Upper joint limits, rad.
    pub upper: Vec<f32>,
    /// Joint speed limits, rad/s.
    pub max_velocity: Vec<f32>,
    /// Joint acceleration limits, rad/s².
    pub max_accel: Vec<f32>,
    /// Tracking-error bounds, rad.
    pub tracking_error: Vec<f32>,
}

fn default_stall_limit_ms() -> f64 {
    1000.0
}

impl std::fmt::Display for LimitsInForce {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let range = |v: &[f32]| {
            let lo = v.iter().copied().fold(f32::INFINITY, f32::min);
            let hi = v.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            if lo == hi {
                format!("{lo}")
            } else {
                format!("{lo}..{hi}")
            }
        };
        write!(
            f,
            "control {} Hz, stale-slow grace {} ms, stall limit {} ms",
            self.control_hz, self.slow_grace_ms, self.stall_limit_ms
        )?;
        let mut at = 0;
        for (name, width) in &self.groups {
            let r = at..(at + width).min(self.lower.len());
            at += width;
            write!(
                f,
                "; {name}: joints {} rad, speed ≤ {} rad/s, accel ≤ {} rad/s², tracking ≤ {} rad",
                self.lower[r.clone()]
                    .iter()
                    .zip(&self.upper[r.clone()])
                    .map(|(l, u)| format!("[{l}, {u}]"))
                    .collect::<Vec<_>>()
                    .join(" "),
                range(&self.max_velocity[r.clone()]),
                range(&self.max_accel[r.clone()]),
                range(&self.tracking_error[r]),
            )?;
        }
        Ok(())
    }
}

impl std::fmt::Display for RunSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let t = &self.trace;
        let us = |n: u64| n as f64 / 1e3;
        writeln!(f, "prompt: {:?}", self.prompt)?;
        writeln!(f, "mode: {}", self.mode.describe())?;
        writeln!(f, "robot: {}; slow features: {}", self.robot, self.slow)?;
        writeln!(f, "action head: {}", self.head)?;
        writeln!(
            f,
            "ticks {} calls {} swaps {} overruns {} holds {}",
            t.ticks,
            t.calls.len(),
            t.swaps,
            t.overruns,
            t.holds
        )?;
        writeln!(
            f,
            "call latency p50 {:.0} µs p99 {:.0} µs; tick jitter p99 {:.0} µs",
            us(t.call_latency.p50),
            us(t.call_latency.p99),
            us(t.tick_jitter.p99)
        )?;
        let mut d = [0u64; 8];
        for c in &t.calls {
            d[c.d.min(7)] += 1;
        }
        writeln!(f, "calls per d: {d:?}; per d_vis: {:?}", self.d_vis_counts)?;
        if !self.relative_actions.is_empty() {
            writeln!(f, "relative actions: {}", self.relative_actions.join(", "))?;
        }
        if let Some(n) = self.camera_frames {
            writeln!(f, "camera frames: {n}")?;
        }
        if let Some(n) = self.hand_commands {
            writeln!(f, "hand commands (emulator): {n}")?;
        }
        if let Some(n) = self.arm_state {
            writeln!(f, "arm state at the end (emulator): {n}")?;
        }
        #[cfg(feature = "remote")]
        if let Some(c) = &self.remote_slow {
            writeln!(
                f,
                "remote slow: frames {} stale polls {} reconnects {} clock syncs {} offset {} ns (±{} ns)",
                c.frames,
                c.stale_polls,
                c.reconnects,
                c.clock_syncs,
                c.offset_ns,
                c.offset_rtt_ns / 2
            )?;
        }
        #[cfg(feature = "remote")]
        if let Some(c) = &self.remote_policy {
            writeln!(
                f,
                "remote policy: calls {} attempts {} timeouts {} reconnects {} failed calls {} \
                 server errors {} last rtt {} µs",
                c.calls,
                c.attempts,
                c.timeouts,
                c.reconnects,
                c.failed_calls,
                c.server_errors,
                c.last_rtt_ns / 1000
            )?;
        }
        if let Some(l) = &self.limits {
            writeln!(f, "limits in force: {l}")?;
        }
        for e in &t.events {
            writeln!(f, "event: {e}")?;
        }
        Ok(())
    }
}

/// Run the stack (see the module docs); `stop` ends the run early (Ctrl-C).
#[cfg(feature = "gr00t")]
pub fn run(args: &RunOptions, stop: Arc<AtomicBool>) -> Result<RunSummary> {
    imp::run(args, stop, None)
}

/// Where a run that fails after its control loop started leaves the metrics of the ticks it
/// ran, for the trace of its failure report.
pub type FailedMetrics = Arc<std::sync::Mutex<Option<pir2_runtime::RunMetrics>>>;

#[cfg(feature = "gr00t")]
fn run_keeping_metrics(
    args: &RunOptions,
    stop: Arc<AtomicBool>,
    failed: &FailedMetrics,
) -> Result<RunSummary> {
    imp::run(args, stop, Some(failed.clone()))
}

#[cfg(not(feature = "gr00t"))]
fn run_keeping_metrics(
    args: &RunOptions,
    stop: Arc<AtomicBool>,
    _failed: &FailedMetrics,
) -> Result<RunSummary> {
    run(args, stop)
}

/// What `--json` holds when a run fails: the error (its whole chain) and what was run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunFailure {
    /// The error that ended the run, with its causes (`anyhow`'s `{:#}`).
    pub error: String,
    /// The stack that was run.
    pub stack: String,
    /// The checkpoint directory.
    pub checkpoint: PathBuf,
    /// The task.
    pub task: String,
    /// The safety limits the run would have enforced, when the checkpoint got that far.
    #[serde(default)]
    pub limits: Option<LimitsInForce>,
    /// The trace of the ticks the run made before it failed (absent when it failed before
    /// its control loop started).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trace: Option<pir2_runtime::RunTrace>,
}

/// `pir2 gr00t run`: run, print the summary, and write it as JSON to `args.json` when set: the
/// [`RunSummary`] after a run that ended normally, a [`RunFailure`] (with the error) after
/// one that failed. An existing `--json` file is never replaced: the run refuses to start.
pub fn run_command(args: &RunOptions, stop: Arc<AtomicBool>) -> Result<()> {
    use anyhow::Context;
    if let Some(p) = &args.json {
        check_report_path(p)?;
    }
    let failed = FailedMetrics::default();
    let result = run_keeping_metrics(args, stop, &failed);
    if let Ok(summary) = &result {
        print!("{summary}");
    }
    if let Some(p) = &args.json {
        let text = match &result {
            Ok(summary) => serde_json::to_string_pretty(summary)?,
            Err(e) => {
                let limits = limits_in_force(args).ok();
                // The ticks the run made before the failure (a safety stop's post-mortem).
                let trace = failed
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .take()
                    .zip(limits.as_ref())
                    .map(|(m, l)| m.trace((1e9 / l.control_hz).round() as u64));
                serde_json::to_string_pretty(&RunFailure {
                    error: format!("{e:#}"),
                    stack: args.stack.clone(),
                    checkpoint: args.checkpoint.clone(),
                    task: args.task.clone(),
                    limits,
                    trace,
                })?
            }
        };
        let written = write_new(p, &text).with_context(|| format!("writing {}", p.display()));
        match (&result, written) {
            (Ok(_), w) => w?,
            // The run's own error is returned below; say that its report is missing too.
            (Err(_), Err(w)) => eprintln!("error: {w:#}"),
            (Err(_), Ok(())) => eprintln!("the failure is recorded in {}", p.display()),
        }
    }
    result.map(|_| ())
}

/// Before any robot moves: `--json`'s file must not exist and its folder must exist and take
/// a new file, so the report of a run is never lost after the run (before: `--json
/// nodir/x.json` ran the robot and then failed to write the trace).
fn check_report_path(p: &std::path::Path) -> Result<()> {
    use anyhow::Context;
    if p.exists() {
        anyhow::bail!(
            "--json {} already exists; choose another path (a run report is never replaced)",
            p.display()
        );
    }
    let dir = match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if !dir.is_dir() {
        anyhow::bail!(
            "--json {}: the folder {} does not exist; create it first (checked before the \
             robot moves, so the run's report cannot be lost)",
            p.display(),
            dir.display()
        );
    }
    let probe = dir.join(format!(".pir2-json-probe-{}", std::process::id()));
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
        .and_then(|_| std::fs::remove_file(&probe))
        .with_context(|| {
            format!(
                "--json {}: cannot create a file in {}",
                p.display(),
                dir.display()
            )
        })
}

/// The limits a run of `args` enforces (see [`LimitsInForce`]).
#[cfg(feature = "gr00t")]
pub fn limits_in_force(args: &RunOptions) -> Result<LimitsInForce> {
    imp::limits_in_force(args)
}

/// Without feature `gr00t` there is no stack and no limits.
#[cfg(not(feature = "gr00t"))]
pub fn limits_in_force(_args: &RunOptions) -> Result<LimitsInForce> {
    anyhow::bail!("this pir2 was built without the GR00T stack")
}

/// Write `text` to a file that must not exist yet (created exclusively) and fsync it.
fn write_new(path: &std::path::Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)?;
    f.write_all(text.as_bytes())?;
    f.write_all(b"\n")?;
    f.sync_all()
}

/// Without feature `gr00t` there is no stack to run.
#[cfg(not(feature = "gr00t"))]
pub fn run(_args: &RunOptions, _stop: Arc<AtomicBool>) -> Result<RunSummary> {
    anyhow::bail!(
        "this pir2 was built without the GR00T stack: rebuild with \
         `cargo build --release -p pir2-cli --features gr00t` (add `remote` for --remote-slow), \
         then `source .native/env.sh` for ONNX Runtime"
    )
}

#[cfg(feature = "gr00t")]
mod imp {
    use std::net::{IpAddr, SocketAddr};
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::{Arc, TryLockError};
    use std::time::Duration;

    use anyhow::{bail, Context, Result};

    use pir2_backends::gr00t::testing::SyntheticCamera;
    use pir2_backends::gr00t::{
        load_action_head, load_candle_head, run_gr00t_report, CheckpointFiles, DeployKind,
        EmbodimentConfig, Gr00tActionHead, Gr00tRunOptions, HeadChoice, ModeOverrides,
    };
    use pir2_robots::emu::{EmulatedArmHand, EmulatedArmHandConfig};
    use pir2_robots::robot::SharedRobot;
    use pir2_robots::{split, Robot, SafetyConfig, XArm6Config, XHandConfig, ARM_DOF, HAND_DOF};
    use pir2_runtime::{Actuator, Clock, FastSource, SystemClock};

    use super::{RunOptions, RunSummary};

    /// Frame period of the synthetic camera (a 30 fps camera with a slow backbone is
    /// slower than one 40 ms tick; this keeps `d_vis` moving).
    const CAMERA_PERIOD: Duration = Duration::from_millis(60);

    /// The embodiment the run will use (the checkpoint's `embodiment.toml` or the paper's).
    fn embodiment(args: &RunOptions) -> Result<EmbodimentConfig> {
        let dir = &args.checkpoint;
        if !dir.is_dir() {
            bail!(
                "checkpoint directory {} does not exist (expected the layout of \
                 docs/gr00t-contract.md: onnx/*.onnx, statistics.json, pir2_gr00t.safetensors, …)",
                dir.display()
            );
        }
        CheckpointFiles::in_dir(dir)
            .embodiment_config()
            .with_context(|| format!("checkpoint {}", dir.display()))
    }

    /// Check `--task` against the configured tasks (keys or prompts). An embodiment without
    /// `[tasks]` (what `pir2 gr00t import` writes) has nothing to check it against: the task
    /// is the prompt itself, as docs/gr00t-import.md says.
    fn check_task(cfg: &EmbodimentConfig, task: &str, free: bool) -> Result<()> {
        let known = cfg.tasks.contains_key(task) || cfg.tasks.values().any(|p| p == task);
        if known || free || cfg.tasks.is_empty() {
            return Ok(());
        }
        let list: Vec<String> = cfg
            .tasks
            .iter()
            .map(|(k, p)| format!("{k} ({p:?})"))
            .collect();
        bail!(
            "unknown task {task:?}: known tasks are {}; pass --free-prompt to send it verbatim",
            list.join(", ")
        )
    }

    /// The safety limits of the run: the xArm6 + XHand defaults at the embodiment's control
    /// rate, overridden by its `[safety.limits]`, which may only tighten the robot's ceiling
    /// ([`SafetyConfig::xarm6_xhand_ceiling_at`]); its action groups must be the robot's, by
    /// name, width and order.
    fn safety_config(cfg: &EmbodimentConfig) -> Result<SafetyConfig> {
        cfg.check_action_groups(&[("arm_joints", ARM_DOF), ("hand_joints", HAND_DOF)])?;
        let ceiling = SafetyConfig::xarm6_xhand_ceiling_at(cfg.control_hz);
        let mut c = SafetyConfig::xarm6_xhand_at(cfg.control_hz);
        let l = cfg.action_limits();
        let set = |dst: &mut Vec<f32>, src: &[Option<f32>]| {
            for (d, s) in dst.iter_mut().zip(src) {
                if let Some(s) = s {
                    *d = *s;
                }
            }
        };
        set(&mut c.lower, &l.lower);
        set(&mut c.upper, &l.upper);
        set(&mut c.max_velocity, &l.max_velocity);
        set(&mut c.max_accel, &l.max_accel);
        set(&mut c.tracking_error, &l.tracking_error);
        c.validate(c.lower.len())
            .context("the embodiment's [safety.limits]")?;
        if let Some(w) = c.widening(&ceiling) {
            let (mut group, mut k) = (String::from("?"), w.joint);
            for g in &cfg.action {
                if k < g.dim {
                    group.clone_from(&g.name);
                    break;
                }
                k -= g.dim;
            }
            bail!(
                "the embodiment's safety.limits.{group}.{}[{k}] = {} is beyond the xArm6 + \
                 XHand ceiling {}: a checkpoint may only tighten the robot's limits",
                w.field,
                w.value,
                w.limit
            );
        }
        Ok(c)
    }

    /// The stale-slow grace of the run, ms: the embodiment's, or `--slow-grace-ms`, which
    /// may only shorten it.
    fn slow_grace_ms(args: &RunOptions, cfg: &EmbodimentConfig) -> Result<f64> {
        let own = cfg.safety.slow_grace_ms;
        match args.slow_grace_ms {
            None => Ok(own),
            Some(g) if !(g.is_finite() && g > 0.0) => bail!("--slow-grace-ms must be > 0, got {g}"),
            Some(g) if g > own => bail!(
                "--slow-grace-ms {g} is longer than the checkpoint's safety.slow_grace_ms = \
                 {own}: a flag may only shorten the grace"
            ),
            Some(g) => Ok(g),
        }
    }

    /// The control watchdog's bound, ms: `--stall-limit-ms`, within
    /// `(0, MAX_STALL_LIMIT]`.
    fn stall_limit_ms(args: &RunOptions) -> Result<f64> {
        let max = pir2_runtime::realtime::MAX_STALL_LIMIT.as_secs_f64() * 1e3;
        let l = args.stall_limit_ms;
        if !(l.is_finite() && l > 0.0 && l <= max) {
            bail!("--stall-limit-ms must be in (0, {max}] ms, got {l}");
        }
        Ok(l)
    }

    /// See [`super::limits_in_force`].
    pub(super) fn limits_in_force(args: &RunOptions) -> Result<super::LimitsInForce> {
        let cfg = embodiment(args)?;
        let c = safety_config(&cfg)?;
        limits_of(args, &cfg, c)
    }

    /// The limits of a run of `args` on `cfg` with the safety limits `c` in force.
    fn limits_of(
        args: &RunOptions,
        cfg: &EmbodimentConfig,
        c: SafetyConfig,
    ) -> Result<super::LimitsInForce> {
        Ok(super::LimitsInForce {
            control_hz: cfg.control_hz,
            slow_grace_ms: slow_grace_ms(args, cfg)?,
            stall_limit_ms: stall_limit_ms(args)?,
            groups: cfg.action.iter().map(|g| (g.name.clone(), g.dim)).collect(),
            lower: c.lower,
            upper: c.upper,
            max_velocity: c.max_velocity,
            max_accel: c.max_accel,
            tracking_error: c.tracking_error,
        })
    }

    fn xarm_config(addr: &str, clock_hz: f64) -> Result<XArm6Config> {
        let mut c = match addr.parse::<SocketAddr>() {
            Ok(a) => {
                let mut c = XArm6Config::new(a.ip());
                c.cmd_addr = a;
                c
            }
            Err(_) => XArm6Config::new(
                addr.parse::<IpAddr>()
                    .with_context(|| format!("bad --xarm address {addr:?}"))?,
            ),
        };
        if clock_hz > c.stream_hz {
            bail!(
                "control_hz = {clock_hz} is above the xArm driver's servo rate stream_hz = {}: \
                 the arm cannot take actions faster than it streams them",
                c.stream_hz
            );
        }
        c.action_period = Duration::from_secs_f64(1.0 / clock_hz);
        Ok(c)
    }

    /// Validate the checkpoint's action head (every graph against the contract, the side
    /// weights, the statistics, the task's prompt layout) before any robot is connected: a
    /// bad export must fail while nothing is powered. The loaded head is the one the run
    /// uses (local head), or the source of the backbone width (remote head).
    fn preflight(args: &RunOptions) -> Result<Gr00tActionHead> {
        let (head, _) = load_action_head(&args.checkpoint, &args.task, &args.ep.ort()?)
            .with_context(|| format!("checking checkpoint {}", args.checkpoint.display()))?;
        Ok(head)
    }

    /// The run's overrides of the checkpoint's `[policy]` table.
    pub(super) fn mode_overrides(args: &RunOptions) -> Result<ModeOverrides> {
        let mode = match &args.mode {
            Some(m) => Some(DeployKind::parse(m).with_context(|| {
                let names: Vec<&str> = DeployKind::ALL.iter().map(|k| k.name()).collect();
                format!("--mode {m}: not one of {}", names.join(", "))
            })?),
            None => None,
        };
        Ok(ModeOverrides {
            mode,
            nfe: args.nfe,
            flow_steps: args.flow_steps,
            h: args.h,
            ensemble: if args.no_ensemble {
                Some(None)
            } else {
                args.ensemble.map(Some)
            },
            rtc_overlap: args.rtc_overlap,
            rtc_ramp_rate: args.rtc_ramp_rate,
        })
    }

    /// The action head of the run and how to report it.
    struct Head {
        choice: HeadChoice,
        what: String,
        #[cfg(feature = "remote")]
        stats: Option<Arc<pir2_runtime::remote::RemoteStats>>,
    }

    impl Head {
        fn local(head: Gr00tActionHead, ep: &crate::ep::EpOptions) -> Result<Self> {
            Ok(Head {
                choice: HeadChoice::Loaded(Box::new(head)),
                what: format!(
                    "the checkpoint's ONNX graphs, in this process, on {}",
                    ep.ort()?.provider.describe()
                ),
                #[cfg(feature = "remote")]
                stats: None,
            })
        }
    }

    #[cfg(not(feature = "remote"))]
    fn head(args: &RunOptions, head: Gr00tActionHead) -> Result<Head> {
        if args.remote_policy.is_some() {
            bail!("--remote-policy needs a pir2 built with feature `remote` (--features gr00t,remote)")
        }
        Head::local(head, &args.ep)
    }

    /// Connect to the policy server (before any robot is connected: an unreachable server
    /// fails while nothing is powered).
    #[cfg(feature = "remote")]
    fn head(args: &RunOptions, head: Gr00tActionHead) -> Result<Head> {
        use pir2_runtime::remote::{Link, RemoteModel, RemoteModelConfig};
        let Some(endpoint) = &args.remote_policy else {
            return Head::local(head, &args.ep);
        };
        if !args.connect_timeout.is_finite() || args.connect_timeout <= 0.0 {
            bail!(
                "--connect-timeout must be > 0, got {}",
                args.connect_timeout
            );
        }
        let d_vl = head.dims().d_vl;
        drop(head);
        let cfg = RemoteModelConfig {
            link: args.tls.apply(Link::connect(endpoint.clone()))?,
            timeout: Duration::from_millis(args.policy_timeout_ms),
            max_failed_calls: args.max_failed_calls,
            connect_timeout: Duration::from_secs_f64(args.connect_timeout),
            ..Default::default()
        };
        let model = RemoteModel::connect(cfg).with_context(|| {
            format!(
                "connecting to the policy server at {endpoint} (is `pir2 gr00t serve policy \
                 --checkpoint …` running there?)"
            )
        })?;
        eprintln!("connected to the policy server at {endpoint}");
        Ok(Head {
            stats: Some(model.stats()),
            choice: HeadChoice::Custom {
                model: Box::new(model),
                d_vl,
            },
            what: format!("pir2 gr00t serve policy at {endpoint}"),
        })
    }

    pub(super) fn run(
        args: &RunOptions,
        stop: Arc<AtomicBool>,
        failed: Option<super::FailedMetrics>,
    ) -> Result<RunSummary> {
        let cfg = embodiment(args)?;
        check_task(&cfg, &args.task, args.free_prompt)?;
        // The deployment against what the head was trained as, before anything is loaded.
        cfg.policy
            .mode(&mode_overrides(args)?)
            .with_context(|| format!("checkpoint {}", args.checkpoint.display()))?;
        if args.record_nfe.is_some() {
            if args.record_calls == 0 {
                bail!("--record-calls must be >= 1 (nothing was started)");
            }
            if args.candle_head.is_some() {
                bail!(
                    "--record-nfe records the checkpoint's ONNX action head (what the four graphs \
                     are fed); the candle head of --candle-head is not recorded: drop one of \
                     the two (nothing was started)"
                );
            }
            if args.remote_policy.is_some() {
                bail!(
                    "--record-nfe records the action head in this process; with \
                     --remote-policy it runs on the policy server: drop one of the two \
                     (nothing was started)"
                );
            }
        }
        let head = match &args.candle_head {
            Some(step) => {
                let (h, _) = load_candle_head(&args.checkpoint, step, &args.task)
                    .with_context(|| format!("checking the candle head {}", step.display()))?;
                Head {
                    choice: HeadChoice::Candle(Box::new(h)),
                    what: format!("candle (CPU), from {}", step.display()),
                    #[cfg(feature = "remote")]
                    stats: None,
                }
            }
            None => {
                let mut h = preflight(args)?;
                if let Some(dir) = &args.record_nfe {
                    h.record_nfe(dir, args.record_calls)
                        .context("--record-nfe (nothing was started)")?;
                }
                head(args, h)?
            }
        };
        let max_ticks = match (args.ticks, args.seconds) {
            (Some(t), _) => Some(t),
            (None, Some(s)) if s > 0.0 => Some((s * cfg.control_hz).round().max(1.0) as u64),
            (None, Some(s)) => bail!("--seconds must be > 0, got {s}"),
            (None, None) => None,
        };
        if args.remote_slow.is_none()
            && !args.emulate
            && !args.synthetic_camera
            && args.frames.is_empty()
            && args.camera.is_empty()
        {
            bail!(
                "no camera: use --camera /dev/videoN for a live camera, --remote-slow ENDPOINT \
                 (camera and backbone behind `pir2 gr00t serve slow`), --frames DIR to replay \
                 recorded frames, or --synthetic-camera to run the real robot on a synthetic \
                 image"
            );
        }
        let sources = [
            !args.frames.is_empty(),
            args.remote_slow.is_some(),
            !args.camera.is_empty(),
            args.synthetic_camera,
        ];
        if sources.iter().filter(|&&s| s).count() > 1 {
            bail!(
                "--camera, --frames, --remote-slow and --synthetic-camera each give the camera: \
                 choose one"
            );
        }
        let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
        // The camera before any robot: a wrong device fails while nothing is powered.
        let camera = local_camera(args, cfg.prompt.chat.images, clock.clone())?;
        let slow_timeout = Duration::from_secs_f64(args.slow_timeout.max(0.1));
        let safety = safety_config(&cfg)?;
        let limits = limits_of(args, &cfg, safety.clone())?;
        let slow_grace = Duration::from_secs_f64(limits.slow_grace_ms / 1e3);
        eprintln!("limits in force: {limits}");

        if args.emulate {
            let (rig, layer) = EmulatedArmHand::start(
                &EmulatedArmHandConfig {
                    action_period: Some(Duration::from_secs_f64(1.0 / cfg.control_hz)),
                    clear_errors: args.clear_errors,
                    safety: safety.clone(),
                    ..Default::default()
                },
                clock.clone(),
            )
            .context("starting the xArm6 + XHand emulators")?;
            let (source, actuator) = split(layer);
            emergency_stop_on_second_signal(
                source.robot().clone(),
                second_signal_report(args, &limits),
            );
            let r = drive(
                args,
                head,
                camera,
                max_ticks,
                slow_timeout,
                slow_grace,
                source,
                actuator,
                clock,
                stop,
                failed.clone(),
                "emulated xArm6 + XHand (in-process)",
            );
            crate::signals::clear_second_signal();
            let commands = rig.hand_commands();
            let arm_state = rig.arm.handle().sim().state;
            drop(rig);
            let mut s = r?;
            s.hand_commands = Some(commands);
            s.arm_state = Some(arm_state);
            s.limits = Some(limits);
            return Ok(s);
        }

        let (Some(xarm), Some(xhand)) = (&args.xarm, &args.xhand) else {
            bail!("--xarm and --xhand are required unless --emulate");
        };
        let mut acfg = xarm_config(xarm, cfg.control_hz)?;
        acfg.clear_errors = args.clear_errors;
        let cmd = acfg.cmd_addr;
        let layer = pir2_robots::connect_arm_hand(
            acfg,
            xhand,
            XHandConfig::default(),
            safety,
            clock.clone(),
        )
        .with_context(|| {
            format!(
                "connecting to the xArm at {cmd} and the XHand on {} (check cables, power and \
                 `pir2 robot check --xarm {xarm} --xhand {}`)",
                xhand.display(),
                xhand.display()
            )
        })?;
        let (source, actuator) = split(layer);
        emergency_stop_on_second_signal(
            source.robot().clone(),
            second_signal_report(args, &limits),
        );
        let robot = format!("xArm6 at {cmd} + XHand on {}", xhand.display());
        let r = drive(
            args,
            head,
            camera,
            max_ticks,
            slow_timeout,
            slow_grace,
            source,
            actuator,
            clock,
            stop,
            failed,
            &robot,
        );
        crate::signals::clear_second_signal();
        let mut s = r?;
        s.limits = Some(limits);
        Ok(s)
    }

    /// What `--json` gets when a second signal ends the process at once: the failure, the
    /// limits in force (the trace stays with the control loop, which is not waited for).
    fn second_signal_report(
        args: &RunOptions,
        limits: &super::LimitsInForce,
    ) -> Option<(std::path::PathBuf, String)> {
        let path = args.json.clone()?;
        let text = serde_json::to_string_pretty(&super::RunFailure {
            error: "a second SIGINT/SIGTERM: the robot was stopped (emergency stop) and the \
                    process exited at once, without waiting for the control loop"
                .into(),
            stack: args.stack.clone(),
            checkpoint: args.checkpoint.clone(),
            task: args.task.clone(),
            limits: Some(limits.clone()),
            trace: None,
        })
        .ok()?;
        Some((path, text))
    }

    /// What a second SIGINT/SIGTERM runs before the process exits: the robot's `stop`, if
    /// its lock comes free within 300 ms (a driver call in progress holds it), then the
    /// failure report for `--json` (`report`), so that file is never left missing.
    fn emergency_stop_on_second_signal<R: Robot + Send + 'static>(
        robot: SharedRobot<R>,
        report: Option<(std::path::PathBuf, String)>,
    ) {
        crate::signals::on_second_signal(move || {
            let t0 = std::time::Instant::now();
            let mut stopped = false;
            while t0.elapsed() < Duration::from_millis(300) {
                match robot.try_lock() {
                    Ok(mut r) => {
                        let _ = r.stop();
                        stopped = true;
                        break;
                    }
                    Err(TryLockError::Poisoned(p)) => {
                        let _ = p.into_inner().stop();
                        stopped = true;
                        break;
                    }
                    Err(TryLockError::WouldBlock) => std::thread::sleep(Duration::from_millis(1)),
                }
            }
            if !stopped {
                eprintln!("emergency stop: the robot stayed busy for 300 ms; exiting without it");
            }
            if let Some((path, text)) = report {
                match super::write_new(&path, &text) {
                    Ok(()) => eprintln!("the failure is recorded in {}", path.display()),
                    Err(e) => eprintln!("error: writing {}: {e}", path.display()),
                }
            }
        });
    }

    /// An actuator that says on stderr when the first command goes to the robot: the end of
    /// the warm-up (first features, warm-start chunk), i.e. when the robot starts to move.
    struct AnnounceFirst<A> {
        inner: A,
        clock: Arc<dyn Clock>,
        t_start: u64,
        announced: bool,
    }

    impl<A: Actuator> AnnounceFirst<A> {
        fn new(inner: A, clock: Arc<dyn Clock>) -> Self {
            let t_start = clock.now();
            Self {
                inner,
                clock,
                t_start,
                announced: false,
            }
        }
    }

    impl<A: Actuator> Actuator for AnnounceFirst<A> {
        fn dim(&self) -> usize {
            self.inner.dim()
        }
        fn send(&mut self, action: &[f32]) -> pir2_runtime::Result<()> {
            let r = self.inner.send(action);
            if !self.announced && r.is_ok() {
                self.announced = true;
                let ms = self.clock.now().saturating_sub(self.t_start) as f64 / 1e6;
                eprintln!("warm-up done after {ms:.0} ms: the robot is under control");
            }
            r
        }
        fn stop(&mut self) -> pir2_runtime::Result<()> {
            self.inner.stop()
        }
    }

    /// The run's local camera: what gives the frames, its delivered-frames counter and how
    /// the summary names it.
    struct Camera {
        source: Box<dyn pir2_runtime::SlowSource>,
        frames: Arc<std::sync::atomic::AtomicU64>,
        what: String,
    }

    /// Open the local cameras, one per camera view of the embodiment (`views`), joined into
    /// one multi-view source (`None` when the features come from `pir2 gr00t serve slow`).
    /// Another number of `--camera` or `--frames` than views is one error naming both.
    fn local_camera(
        args: &RunOptions,
        views: usize,
        clock: Arc<dyn Clock>,
    ) -> Result<Option<Camera>> {
        if args.remote_slow.is_some() {
            return Ok(None);
        }
        let given = [
            ("--camera", args.camera.len()),
            ("--frames", args.frames.len()),
        ]
        .into_iter()
        .find(|&(_, n)| n > 0);
        if let Some((flag, n)) = given {
            if n != views {
                bail!(
                    "{n} {flag} given, but the embodiment has {views} camera view(s) \
                     (prompt.chat.images): give one {flag} per view, in its view order"
                );
            }
        }
        let mut cams = Vec::with_capacity(views);
        for dev in &args.camera {
            cams.push(v4l2_camera(args, dev, clock.clone())?);
        }
        for dir in &args.frames {
            let cam = pir2_robots::FolderCamera::open(
                dir,
                Duration::from_millis(args.frame_ms.max(1)),
                clock.clone(),
            )
            .with_context(|| format!("--frames {}", dir.display()))?;
            let what = format!(
                "{} recorded frames from {} (one per {} ms, looping)",
                cam.len(),
                dir.display(),
                args.frame_ms.max(1)
            );
            cams.push(Camera {
                frames: cam.frames(),
                source: Box::new(cam),
                what,
            });
        }
        if cams.is_empty() {
            let cam = SyntheticCamera::with_views(clock, CAMERA_PERIOD, views);
            return Ok(Some(Camera {
                frames: cam.frames(),
                source: Box::new(cam),
                what: format!("a synthetic camera ({views} view(s))"),
            }));
        }
        if cams.len() == 1 {
            return Ok(cams.pop());
        }
        let frames = cams[0].frames.clone();
        let what = cams
            .iter()
            .enumerate()
            .map(|(k, c)| format!("view {k}: {}", c.what))
            .collect::<Vec<_>>()
            .join("; ");
        let joined = pir2_runtime::Views::new(cams.into_iter().map(|c| c.source).collect())?;
        Ok(Some(Camera {
            source: Box::new(joined),
            frames,
            what,
        }))
    }

    /// How long one V4L2 capture may wait for a frame (a UVC camera's first frame after
    /// starting can take most of a second while its exposure settles).
    const CAMERA_TIMEOUT: Duration = Duration::from_secs(2);

    #[cfg(target_os = "linux")]
    fn v4l2_camera(
        args: &RunOptions,
        dev: &std::path::Path,
        clock: Arc<dyn Clock>,
    ) -> Result<Camera> {
        use pir2_robots::v4l2::{parse_size, FormatRequest, V4l2Camera, V4l2Config};
        let request = FormatRequest {
            format: args.camera_format.as_deref().map(str::parse).transpose()?,
            size: args.camera_size.as_deref().map(parse_size).transpose()?,
        };
        let cfg = V4l2Config {
            request,
            timeout: CAMERA_TIMEOUT,
            ..V4l2Config::new(dev)
        };
        let cam =
            V4l2Camera::open(&cfg, clock).with_context(|| format!("--camera {}", dev.display()))?;
        let what = format!(
            "the camera {} ({}, {}, {}; asked {request})",
            dev.display(),
            cam.card(),
            cam.format(),
            cam.timestamps()
        );
        eprintln!("camera: {what}");
        Ok(Camera {
            frames: cam.frames(),
            source: Box::new(cam),
            what,
        })
    }

    #[cfg(not(target_os = "linux"))]
    fn v4l2_camera(_: &RunOptions, dev: &std::path::Path, _: Arc<dyn Clock>) -> Result<Camera> {
        bail!(
            "--camera {}: live V4L2 cameras need Linux; use --frames or --remote-slow",
            dev.display()
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn drive<F: FastSource, A: Actuator>(
        args: &RunOptions,
        head: Head,
        camera: Option<Camera>,
        max_ticks: Option<u64>,
        slow_timeout: Duration,
        slow_grace: Duration,
        source: F,
        actuator: A,
        clock: Arc<dyn Clock>,
        stop: Arc<AtomicBool>,
        failed: Option<super::FailedMetrics>,
        robot: &str,
    ) -> Result<RunSummary> {
        let actuator = AnnounceFirst::new(actuator, clock.clone());
        #[cfg(feature = "remote")]
        let head_stats = head.stats.clone();
        let what = head.what.clone();
        let opts = Gr00tRunOptions {
            mode: mode_overrides(args)?,
            head: head.choice,
            max_ticks,
            clock: clock.clone(),
            stop,
            slow_timeout,
            slow_grace: Some(slow_grace),
            stall_limit: Duration::from_secs_f64(args.stall_limit_ms / 1e3),
            failed_metrics: failed,
            ort: args.ep.ort()?,
            ..Default::default()
        };
        let ctx = || {
            #[allow(unused_mut)]
            let mut m = format!(
                "running gr00t-xarm-xhand from {}",
                args.checkpoint.display()
            );
            #[cfg(feature = "remote")]
            if let Some(s) = &head_stats {
                m += &format!(
                    " with the action head at {} (remote policy counters: {:?})",
                    args.remote_policy.as_deref().unwrap_or("?"),
                    s.counters()
                );
            }
            m
        };
        let mut summary = if let Some(endpoint) = &args.remote_slow {
            remote_slow(args, endpoint, source, actuator, clock, opts, robot).with_context(ctx)?
        } else {
            let Some(Camera {
                source: camera,
                frames,
                what: camera_what,
            }) = camera
            else {
                bail!("no local camera was opened")
            };
            let report =
                run_gr00t_report(&args.checkpoint, &args.task, source, actuator, camera, opts)
                    .with_context(ctx)?;
            let period = (1e9 / report.embodiment.control_hz).round() as u64;
            RunSummary {
                prompt: report.prompt,
                mode: report.mode,
                robot: robot.to_string(),
                slow: format!(
                    "{} on {camera_what} (local slow worker), prompt tokenised by {}",
                    report.backbone, report.tokenizer
                ),
                head: String::new(),
                d_vis_counts: report.d_vis_counts,
                relative_actions: report.embodiment.relative_groups(),
                hand_commands: None,
                arm_state: None,
                camera_frames: Some(frames.load(Ordering::Relaxed)),
                #[cfg(feature = "remote")]
                remote_slow: None,
                #[cfg(feature = "remote")]
                remote_policy: None,
                trace: report.metrics.trace(period),
                limits: None,
            }
        };
        summary.head = what;
        #[cfg(feature = "remote")]
        {
            summary.remote_policy = head_stats.map(|s| s.counters());
        }
        Ok(summary)
    }

    /// A remote slow source that says "connected" only once the slow server's first
    /// features arrived (before: it said so when the session opened, whether or not anything
    /// answered).
    #[cfg(feature = "remote")]
    struct FirstFrameAnnounced<S> {
        inner: S,
        endpoint: String,
        announced: bool,
    }

    #[cfg(feature = "remote")]
    #[async_trait::async_trait]
    impl<S: pir2_runtime::SlowSource> pir2_runtime::SlowSource for FirstFrameAnnounced<S> {
        async fn capture(&mut self) -> pir2_runtime::Result<pir2_runtime::SlowFrame> {
            let frame = self.inner.capture().await?;
            if !self.announced {
                self.announced = true;
                eprintln!(
                    "connected to the slow server at {}: first features received",
                    self.endpoint
                );
            }
            Ok(frame)
        }
    }

    #[cfg(not(feature = "remote"))]
    fn remote_slow<F: FastSource, A: Actuator>(
        _: &RunOptions,
        _: &str,
        _: F,
        _: A,
        _: Arc<dyn Clock>,
        _: Gr00tRunOptions,
        _: &str,
    ) -> Result<RunSummary> {
        bail!("--remote-slow needs a pir2 built with feature `remote` (--features gr00t,remote)")
    }

    /// The backbone on another machine: features from `pir2 gr00t serve slow`, the VL token
    /// layout from the local checkpoint (its tokenizer and prompt layout), the action head
    /// here.
    #[cfg(feature = "remote")]
    fn remote_slow<F: FastSource, A: Actuator>(
        args: &RunOptions,
        endpoint: &str,
        source: F,
        actuator: A,
        clock: Arc<dyn Clock>,
        mut opts: Gr00tRunOptions,
        robot: &str,
    ) -> Result<RunSummary> {
        use pir2_backends::gr00t::{build_sequence, load_tokenizer, BackboneChoice};
        use pir2_runtime::remote::{Link, RemoteSlowConfig, RemoteSlowSource};

        let cfg = embodiment(args)?;
        let files = CheckpointFiles::in_dir(&args.checkpoint);
        let tok = load_tokenizer(&files, &cfg.prompt)
            .with_context(|| format!("checkpoint {}", args.checkpoint.display()))?;
        let seq = build_sequence(tok.as_ref(), cfg.prompt_for(&args.task), &cfg.prompt)?;
        let rcfg = RemoteSlowConfig {
            link: args.tls.apply(Link::connect(endpoint))?,
            first_timeout: opts.slow_timeout,
            ..Default::default()
        };
        let src = RemoteSlowSource::connect(rcfg, clock)
            .with_context(|| format!("opening a session to the slow server at {endpoint}"))?;
        eprintln!("waiting for the first features from the slow server at {endpoint}");
        let stats = src.stats();
        opts.backbone = BackboneChoice::Custom {
            encoder: Box::new(src.encoder()),
            layout: seq.layout.clone(),
        };
        let src = FirstFrameAnnounced {
            inner: src,
            endpoint: endpoint.to_string(),
            announced: false,
        };
        let r = run_gr00t_report(&args.checkpoint, &args.task, source, actuator, src, opts);
        let counters = stats.counters();
        let report = r.with_context(|| {
            format!(
                "running gr00t-xarm-xhand with backbone features from {endpoint} (is `pir2 gr00t \
                 serve slow` running there? remote counters: {counters:?})"
            )
        })?;
        let period = (1e9 / report.embodiment.control_hz).round() as u64;
        Ok(RunSummary {
            prompt: report.prompt,
            mode: report.mode,
            robot: robot.to_string(),
            slow: format!("pir2 gr00t serve slow at {endpoint}"),
            head: String::new(),
            d_vis_counts: report.d_vis_counts,
            relative_actions: report.embodiment.relative_groups(),
            hand_commands: None,
            arm_state: None,
            camera_frames: None,
            remote_slow: Some(counters),
            remote_policy: None,
            trace: report.metrics.trace(period),
            limits: None,
        })
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn a_task_is_checked_only_against_a_tasks_table() {
            let paper = EmbodimentConfig::xarm6_xhand();
            check_task(&paper, "catch_book", false).unwrap();
            check_task(&paper, "catch the book", false).unwrap();
            let e = check_task(&paper, "catch the bok", false)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("unknown task") && e.contains("--free-prompt"),
                "{e}"
            );
            check_task(&paper, "catch the bok", true).unwrap();
            // An imported embodiment has no [tasks]: the task is the prompt.
            let mut imported = paper;
            imported.tasks.clear();
            check_task(&imported, "pick the cube", false).unwrap();
        }
    }
}
