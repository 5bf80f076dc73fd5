//! The `pir2` binary: parses arguments and makes one call into `pir2_cli::commands` (or
//! `run`, `serve`) per subcommand.
//!
//! Every clap type of the binary lives in this one file on purpose (the library takes plain
//! option structs and never sees clap), which is why it is long.

use std::net::IpAddr;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};

use pir2_cli::commands::{
    self, CollectOptions, DemoOptions, Emulated, EvalOptions, RemoteOptions, TaskName, TrainOptions,
};
use pir2_cli::ep::EpOptions;
use pir2_cli::leap_cmd::{self, LeapArgs};
use pir2_cli::run::{self, RunOptions};
use pir2_cli::serve::{self, ServeOptions, TlsOptions};
use pir2_runtime::Policy;
use pir2_sim::dataset::WriteMode;

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

#[derive(Clone, Copy, Debug, ValueEnum)]
enum PolicyArg {
    Pir2,
    Pir2Hidden,
    Pir2Full,
    Rtc,
    Flow,
}

impl From<PolicyArg> for Policy {
    fn from(p: PolicyArg) -> Self {
        match p {
            PolicyArg::Pir2 => Policy::PiR2,
            PolicyArg::Pir2Hidden => Policy::PiR2Hidden,
            PolicyArg::Pir2Full => Policy::PiR2Full,
            PolicyArg::Rtc => Policy::Rtc,
            PolicyArg::Flow => Policy::Flow,
        }
    }
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// The embedded default end to end: collect → train → evaluate every deployment mode.
    Demo {
        /// A smaller, faster run.
        #[arg(long)]
        quick: bool,
        /// TOML config (fields of `DemoConfig`); flags override it.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Output directory (must not exist or be empty; default: `runs/demo-<time>`).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Test episodes per cell.
        #[arg(long)]
        episodes: Option<usize>,
    },
    /// Collect expert demonstrations into a LeRobotDataset v3.0 directory.
    Collect {
        /// The task (leap-cube needs a build with `--features mujoco`).
        #[arg(value_parser = ["ballplate", "leap-cube"], default_value = "ballplate")]
        task: String,
        /// Dataset directory.
        #[arg(long)]
        out: PathBuf,
        /// leap-cube: expert seeds (episodes are stored seed-major).
        #[arg(long, value_delimiter = ',', default_value = "0,1,2,3")]
        seeds: Vec<u64>,
        /// leap-cube: episodes per expert seed.
        #[arg(long, default_value_t = 50)]
        per_seed: usize,
        /// leap-cube: the faster, weaker MPC expert.
        #[arg(long, conflicts_with = "expert")]
        fast: bool,
        /// leap-cube: demonstrate with trained policy weights (`pir2-ppo-expert-v1`
        /// safetensors, e.g. from `leap_ppo` or `scripts/playground-expert.py`) instead of
        /// the MPC: one file for all seeds, or one per seed (in the order of `--seeds`).
        #[arg(long, value_delimiter = ',')]
        expert: Vec<PathBuf>,
        /// Episodes to keep.
        #[arg(long, default_value_t = 200)]
        episodes: usize,
        /// Seed.
        #[arg(long, default_value_t = 7)]
        seed: u64,
        /// Append the missing episodes to an existing dataset.
        #[arg(long, conflicts_with = "overwrite")]
        resume: bool,
        /// Replace an existing dataset.
        #[arg(long)]
        overwrite: bool,
    },
    /// Train one policy (candle MLP; leap-cube: U-Nets, the config's `policies` unless
    /// --policy) on a dataset; the checkpoint is picked in closed loop. With --task FILE: a
    /// policy on any state-only LeRobotDataset v3.0, picked on held-out episodes. `gr00t`:
    /// πR² fine-tuning of a GR00T N1.7 checkpoint's action head (--checkpoint, --embodiment,
    /// --features; needs a build with `--features gr00t`).
    Train {
        /// The stock task (default ballplate; leap-cube needs a build with `--features mujoco`),
        /// or `gr00t`.
        #[arg(value_parser = ["ballplate", "leap-cube", "gr00t"], conflicts_with = "task_file")]
        task: Option<String>,
        /// A task file (task.toml: fast/slow/action keys, horizon, n_obs, policy, model,
        /// optimiser, held-out episodes) for a user's own dataset.
        #[arg(long = "task", value_name = "TASK_TOML")]
        task_file: Option<PathBuf>,
        /// Dataset directory (LeRobotDataset v3.0).
        #[arg(long)]
        data: PathBuf,
        /// Which policy (required for ballplate).
        #[arg(long, value_enum)]
        policy: Option<PolicyArg>,
        /// Checkpoint directory (must not exist, unless --resume).
        #[arg(long)]
        out: PathBuf,
        /// TOML config (fields of `DemoConfig`: steps, lr, nfe, ...; leap-cube:
        /// `LeapStudyConfig`).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// leap-cube and --task: continue an interrupted `pir2 train … --out DIR` with the same
        /// config (task file) and data (both checked against `DIR/config.toml` and
        /// `DIR/data.json`): finished policies are kept, unfinished ones continue from their
        /// last step checkpoint (bit-identically to an uninterrupted run on the same kind of CPU).
        #[arg(long)]
        resume: bool,
        /// gr00t: the GR00T N1.7 checkpoint directory (config.json + model.safetensors).
        #[arg(long)]
        checkpoint: Option<PathBuf>,
        /// gr00t: the embodiment file (embodiment.toml).
        #[arg(long)]
        embodiment: Option<PathBuf>,
        /// gr00t: the backbone's outputs per frame (safetensors: `embeddings` `[N,T,D_vl]`,
        /// `image_mask` `[N,T]`, optional `attention_mask` `[N,T]`).
        #[arg(long)]
        features: Option<PathBuf>,
        /// gr00t: optimiser steps.
        #[arg(long, default_value_t = 1000)]
        steps: usize,
        /// gr00t: samples per step (the paper: 512).
        #[arg(long, default_value_t = 64)]
        batch_size: usize,
        /// gr00t: peak learning rate.
        #[arg(long, default_value_t = 1e-4)]
        lr: f64,
        /// gr00t: a step checkpoint every this many steps (and at the end).
        #[arg(long)]
        checkpoint_every: Option<usize>,
        /// gr00t: the dataset feature holding the state.
        #[arg(long, default_value = "observation.state")]
        state_key: String,
        /// gr00t: the dataset feature holding the action.
        #[arg(long, default_value = "action")]
        action_key: String,
        /// gr00t: train without GR00T's DiT dropout (by default the checkpoint's
        /// `diffusion_model_cfg.dropout`, 0.2 in N1.7, applies in training only).
        #[arg(long)]
        no_dropout: bool,
        /// gr00t: the candle device: `cpu`, `cuda[:N]` (a build with `--features cuda`) or
        /// `metal[:N]` (`--features metal`).
        #[arg(long, default_value = "cpu")]
        device: String,
    },
    /// Precompute a frozen backbone's features over a dataset's cameras. `gr00t`: GR00T
    /// N1.7's backbone (the checkpoint's ONNX backbone and tokenizer, run as `pir2 run` runs
    /// them) on every frame of a LeRobotDataset v3.0, written as the `--features` file of
    /// `pir2 train gr00t` (needs a build with `--features gr00t`, and the `ffmpeg` program
    /// for video cameras).
    Features {
        /// Which backbone.
        #[arg(value_parser = ["gr00t"])]
        what: String,
        /// The GR00T checkpoint directory (docs/gr00t-contract.md): `onnx/backbone.onnx`, or
        /// `onnx/vit_fp32.onnx` + `onnx/llm_fp32.onnx` + `model.safetensors`, and
        /// `tokenizer.json` (a GR00T N1.7 directory with those added).
        #[arg(long)]
        checkpoint: PathBuf,
        /// Dataset directory (LeRobotDataset v3.0 with camera videos or image features).
        #[arg(long)]
        data: PathBuf,
        /// The embodiment file (default: the checkpoint's embodiment.toml); `cameras` names
        /// the dataset's camera (video or image) features in view order.
        #[arg(long)]
        embodiment: Option<PathBuf>,
        /// Output safetensors file (`embeddings` `[N,T,D_vl]`, `image_mask`, `attention_mask`).
        #[arg(long)]
        out: PathBuf,
        /// Continue an interrupted run (OUT.partial and OUT.partial.json).
        #[arg(long)]
        resume: bool,
        /// Replace an existing output file.
        #[arg(long)]
        overwrite: bool,
        /// Largest distance between a frame's timestamp and the decoded video frame, s
        /// (LeRobot's tolerance_s).
        #[arg(long, default_value_t = 1e-4)]
        tolerance_s: f64,
        /// ONNX Runtime intra-op threads of the backbone.
        #[arg(long, default_value_t = 1)]
        threads: usize,
    },
    /// Evaluate a checkpoint in every mode that fits it, at each unit delay; leap-cube: run
    /// the deployment or horizon study (table, PNG, JSON).
    Eval {
        /// The task (leap-cube needs a build with `--features mujoco`).
        #[arg(value_parser = ["ballplate", "leap-cube"], default_value = "ballplate")]
        task: String,
        /// Checkpoint directory (leap-cube: the output of `pir2 train leap-cube`; a listed
        /// policy × seed without a `best/` there is an error, unless --train-missing).
        #[arg(long)]
        checkpoint: Option<PathBuf>,
        /// leap-cube: train the listed policies missing from --checkpoint (into --out) instead
        /// of refusing them.
        #[arg(long)]
        train_missing: bool,
        /// Which policy the checkpoint is (ballplate).
        #[arg(long, value_enum)]
        policy: Option<PolicyArg>,
        /// leap-cube: which study.
        #[arg(long, value_parser = ["deployment", "horizon"], default_value = "deployment")]
        study: String,
        /// leap-cube: TOML config (fields of `LeapStudyConfig`).
        #[arg(long)]
        config: Option<PathBuf>,
        /// leap-cube: dataset directory (overrides the config's).
        #[arg(long)]
        data: Option<PathBuf>,
        /// leap-cube: output directory (must not exist or be empty, unless --resume).
        #[arg(long)]
        out: Option<PathBuf>,
        /// leap-cube: continue an interrupted evaluation in --out with the same config: the
        /// cells in its `cells.jsonl` are reused, the rest are measured (the config's seed
        /// list may grow, e.g. from a one-seed table to three seeds). SIGINT or SIGTERM ends an
        /// evaluation after the cell being measured (a second signal at once); every finished
        /// cell is in the log.
        #[arg(long)]
        resume: bool,
        /// Unit delays.
        #[arg(long, value_delimiter = ',', default_value = "1,2,3")]
        d0: Vec<usize>,
        /// Episodes per cell (default 100; leap-cube: the config's).
        #[arg(long)]
        episodes: Option<usize>,
        /// Seed of the evaluation episodes.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Write the cells as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Send the action-head calls to `pir2 serve policy` at this Zenoh endpoint
        /// (e.g. `tcp/10.0.0.2:7447`; feature `remote`). The server must run the same
        /// checkpoint; locally only its normalisation is used.
        #[arg(long)]
        remote: Option<String>,
        /// With --remote: ms a request may take before it is sent again.
        #[arg(long, default_value_t = 200)]
        remote_timeout_ms: u64,
        /// With --remote: consecutive timeouts before the evaluation stops.
        #[arg(long, default_value_t = 25)]
        remote_max_failed: u32,
        /// With --remote: seconds to wait for the server at start.
        #[arg(long, default_value_t = 5.0)]
        connect_timeout: f64,
        /// With --remote: mutual TLS for a `tls/…` endpoint.
        #[command(flatten)]
        tls: TlsArgs,
    },
    /// A study's tables from its cell log alone (`cells.jsonl` of `pir2 eval leap-cube`): the
    /// chosen checkpoints and the best checkpoint per cell, mean ± std over the config's seeds
    /// and per seed, as the evaluation computes them, without the checkpoints and without
    /// simulating; the log is only read.
    Report {
        /// The task (leap-cube needs a build with `--features mujoco`).
        #[arg(value_parser = ["leap-cube"])]
        task: String,
        /// Which study.
        #[arg(long, value_parser = ["deployment", "horizon"], default_value = "deployment")]
        study: String,
        /// TOML config (fields of `LeapStudyConfig`): the rows, seeds and columns to report,
        /// and the settings the cells were measured with.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Dataset directory (overrides the config's): the one the evaluation was given, since
        /// the config's fingerprint, under which the cells are logged, includes it.
        #[arg(long)]
        data: Option<PathBuf>,
        /// The cell log.
        #[arg(long)]
        cells: PathBuf,
        /// Also write `report.json`, `table.md` and the plots here (must not exist or be
        /// empty).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Report what the log holds when cells are missing (listed), instead of refusing.
        #[arg(long)]
        partial: bool,
    },
    /// Run a policy stack on a robot (or its emulators).
    Run(Box<RunArgs>),
    /// Servers for the remote slow channel and the remote action head (feature `remote`).
    Serve {
        #[command(subcommand)]
        cmd: ServeCmd,
    },
    /// Plot a demo result (`result.json`) or a run trace (`trace.json`) to PNG.
    Plot {
        /// Input JSON.
        input: PathBuf,
        /// Output PNG (default: next to the input).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Export a candle checkpoint (MLP or U-Net) to ONNX for ONNX Runtime deployment, or
    /// (`--gr00t`) a `pir2 train gr00t` step directory to the GR00T checkpoint layout.
    Export {
        /// Checkpoint directory (config.json, stats.json, model.safetensors), or with
        /// `--gr00t` a `pir2 train gr00t` step directory (model.safetensors + config.json;
        /// statistics.json and embodiment.toml in the run directory above it).
        checkpoint: PathBuf,
        /// Output ONNX file (must not exist).
        #[arg(long, required_unless_present = "gr00t", conflicts_with = "gr00t")]
        onnx: Option<PathBuf>,
        /// Output GR00T checkpoint directory (docs/gr00t-contract.md: the four action-head
        /// graphs, pir2_gr00t.safetensors, statistics.json, embodiment.toml); must not exist
        /// or be empty. Needs a build with `--features gr00t`.
        #[arg(long)]
        gr00t: Option<PathBuf>,
    },
    /// Benchmarks printed side by side (schedule, runtime).
    Bench {
        /// What to measure (`gr00t`: a GR00T export's action head and backbone, feature
        /// `gr00t`; not part of `all`).
        #[arg(value_parser = ["schedule", "runtime", "all", "gr00t"], default_value = "all")]
        what: String,
        /// Seconds per real-time run (`gr00t`: seconds of calls per graph).
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
        /// gr00t: the export directory (docs/gr00t-contract.md).
        #[arg(long, required_if_eq("what", "gr00t"))]
        checkpoint: Option<PathBuf>,
        /// gr00t: the task (key or prompt) whose prompt layout the head is fed.
        #[arg(long, required_if_eq("what", "gr00t"))]
        task: Option<String>,
        /// gr00t: where ONNX Runtime runs the graphs.
        #[command(flatten)]
        ep: EpArgs,
    },
    /// Robot tools: check a connection, run the emulators.
    Robot {
        #[command(subcommand)]
        cmd: RobotCmd,
    },
}

/// Arguments of `pir2 run`.
#[derive(Args, Debug, Clone)]
struct RunArgs {
    /// The stack to run.
    #[arg(value_parser = ["gr00t-xarm-xhand"])]
    stack: String,
    /// Checkpoint directory (export layout in docs/gr00t-contract.md).
    #[arg(long)]
    checkpoint: PathBuf,
    /// Task: a key of the embodiment's tasks (`catch_book`, …) or one of their prompts
    /// verbatim ("catch the book").
    #[arg(long)]
    task: String,
    /// Accept a `--task` that is not a configured task and send it as the prompt verbatim.
    #[arg(long)]
    free_prompt: bool,
    /// xArm controller address (command port 502 unless given as host:port).
    #[arg(long, required_unless_present = "emulate", conflicts_with = "emulate")]
    xarm: Option<String>,
    /// XHand serial device (RS-485 adapter).
    #[arg(long, required_unless_present = "emulate", conflicts_with = "emulate")]
    xhand: Option<PathBuf>,
    /// Clear a latched xArm error/warning (collision, emergency stop) at connect instead of
    /// refusing to start.
    #[arg(long)]
    clear_errors: bool,
    /// Start the xArm6 and XHand emulators in-process and run against them (synthetic
    /// camera unless --remote-slow).
    #[arg(long)]
    emulate: bool,
    /// Use the synthetic camera with real robots.
    #[arg(long)]
    synthetic_camera: bool,
    /// A live V4L2 (USB/UVC) camera, e.g. /dev/video0 (Linux): frames are stamped with the
    /// driver's capture time, so the slow channel's age counts from the sensor. Repeat it
    /// once per camera view of the embodiment (`prompt.chat.images`), in its view order.
    #[arg(long, conflicts_with_all = ["frames", "remote_slow", "synthetic_camera"])]
    camera: Vec<PathBuf>,
    /// With --camera: frame size WIDTHxHEIGHT, which the camera must offer (default: the
    /// offered size nearest 640x480); the same for every camera.
    #[arg(long, requires = "camera")]
    camera_size: Option<String>,
    /// With --camera: pixel format (default: the best the camera offers at the size).
    #[arg(long, requires = "camera", value_parser = ["mjpeg", "yuyv", "rgb24"])]
    camera_format: Option<String>,
    /// Replay recorded frames as the camera: every .png/.jpg of this folder in file-name
    /// order, looping (GR00T's preprocessing applies as to a live camera). Repeat it once per
    /// camera view, in the embodiment's view order.
    #[arg(long, conflicts_with_all = ["remote_slow", "synthetic_camera"])]
    frames: Vec<PathBuf>,
    /// With --frames: ms between frames.
    #[arg(long, default_value_t = 33)]
    frame_ms: u64,
    /// Take backbone features from `pir2 serve slow` at this Zenoh endpoint
    /// (e.g. `tcp/10.0.0.2:7448`); needs feature `remote`.
    #[arg(long)]
    remote_slow: Option<String>,
    /// Run the action head on `pir2 serve policy --gr00t-checkpoint` at this Zenoh endpoint
    /// (e.g. `tcp/10.0.0.3:7447`) instead of in this process; needs feature `remote`. The
    /// checkpoint directory is still read here (embodiment, statistics, vocabulary) and the
    /// head is checked before any robot is connected. Each call's round trip is part of the
    /// measured call latency, so `d` grows with the network.
    #[arg(long)]
    remote_policy: Option<String>,
    /// Run the fine-tuned action head in candle from this `pir2 train gr00t` step directory
    /// (model.safetensors + config.json) instead of the checkpoint's ONNX head graphs; the
    /// checkpoint still gives the backbone, tokenizer, statistics and embodiment (the step's
    /// run must have the same statistics.json and embodiment.toml).
    #[arg(long, conflicts_with = "remote_policy")]
    candle_head: Option<PathBuf>,
    /// With --remote-policy: how long one request may take before it is sent again, ms.
    #[arg(long, default_value_t = 200)]
    policy_timeout_ms: u64,
    /// With --remote-policy: requests in a row without a reply before the run stops the
    /// robot (safety stop).
    #[arg(long, default_value_t = 10)]
    max_failed_calls: u32,
    /// With --remote-policy: seconds to wait for the policy server at start-up.
    #[arg(long, default_value_t = 10.0)]
    connect_timeout: f64,
    /// Stop after this many control ticks.
    #[arg(long, conflicts_with = "seconds")]
    ticks: Option<u64>,
    /// Stop after this many seconds (rounded to ticks of the embodiment's rate).
    #[arg(long)]
    seconds: Option<f64>,
    /// Seconds to wait for the first backbone features.
    #[arg(long, default_value_t = 60.0)]
    slow_timeout: f64,
    /// Stale-slow stop: stop the robot once the backbone features are older than the
    /// checkpoint's d_vis_max ticks for longer than this, ms (default: the embodiment's
    /// `safety.slow_grace_ms`, 200 if unset).
    #[arg(long)]
    slow_grace_ms: Option<f64>,
    /// Write the run summary (and the per-call trace) as JSON here; a failed run writes its
    /// error instead. The file must not exist (a report is never replaced).
    #[arg(long)]
    json: Option<PathBuf>,
    /// Deployment (default: the checkpoint's `[policy] mode`, else pir2_async). A mode the
    /// action head was not trained for (`[policy] trained`) is refused.
    #[arg(long, value_parser = ["pir2_async", "pir2_sync", "sync_flow", "naive_async", "rtc"])]
    mode: Option<String>,
    /// πR²: NFEs per action (must equal the checkpoint's `[policy] nfe`).
    #[arg(long)]
    nfe: Option<usize>,
    /// Flow baselines and train-time RTC: Euler steps K per chunk.
    #[arg(long)]
    flow_steps: Option<usize>,
    /// Sync flow: actions executed per chunk.
    #[arg(long)]
    h: Option<usize>,
    /// Naive async: ACT temporal ensembling with this decay m.
    #[arg(long, conflicts_with = "no_ensemble")]
    ensemble: Option<f32>,
    /// Naive async: plain swap even if the checkpoint's `[policy] ensemble` is set.
    #[arg(long)]
    no_ensemble: bool,
    /// Mutual TLS for `tls/…` endpoints of --remote-policy / --remote-slow.
    #[command(flatten)]
    tls: TlsArgs,
    /// Where ONNX Runtime runs the action head and the backbone.
    #[command(flatten)]
    ep: EpArgs,
}

/// `--ep`, `--ep-device`, `--trt-cache` (→ `EpOptions`).
#[derive(Args, Debug, Clone)]
struct EpArgs {
    /// ONNX Runtime execution provider for the GR00T graphs. `cuda` and `tensorrt` need the
    /// GPU build of ONNX Runtime (PyPI `onnxruntime-gpu`, same version) in ORT_DYLIB_PATH;
    /// a library without the provider is one error at start, never a CPU fallback.
    #[arg(long, value_parser = ["cpu", "cuda", "tensorrt"], default_value = "cpu")]
    ep: String,
    /// CUDA device id for --ep cuda|tensorrt.
    #[arg(long, default_value_t = 0)]
    ep_device: i32,
    /// --ep tensorrt: keep built engines and the timing cache here (the first start builds
    /// them, which takes minutes; later starts load them).
    #[arg(long)]
    trt_cache: Option<PathBuf>,
}

impl From<EpArgs> for EpOptions {
    fn from(a: EpArgs) -> Self {
        EpOptions {
            name: a.ep,
            device: a.ep_device,
            trt_cache: a.trt_cache,
        }
    }
}

impl From<RunArgs> for RunOptions {
    fn from(a: RunArgs) -> Self {
        RunOptions {
            stack: a.stack,
            checkpoint: a.checkpoint,
            task: a.task,
            free_prompt: a.free_prompt,
            xarm: a.xarm,
            xhand: a.xhand,
            clear_errors: a.clear_errors,
            emulate: a.emulate,
            synthetic_camera: a.synthetic_camera,
            frames: a.frames,
            frame_ms: a.frame_ms,
            camera: a.camera,
            camera_size: a.camera_size,
            camera_format: a.camera_format,
            remote_slow: a.remote_slow,
            remote_policy: a.remote_policy,
            candle_head: a.candle_head,
            policy_timeout_ms: a.policy_timeout_ms,
            max_failed_calls: a.max_failed_calls,
            connect_timeout: a.connect_timeout,
            ticks: a.ticks,
            seconds: a.seconds,
            slow_timeout: a.slow_timeout,
            slow_grace_ms: a.slow_grace_ms,
            json: a.json,
            mode: a.mode,
            nfe: a.nfe,
            flow_steps: a.flow_steps,
            h: a.h,
            ensemble: a.ensemble,
            no_ensemble: a.no_ensemble,
            tls: a.tls.into(),
            ep: a.ep.into(),
        }
    }
}

/// `--tls-ca/--tls-cert/--tls-key` (all three or none) and `--insecure` (→ `TlsOptions`).
#[derive(Args, Debug, Clone, Default)]
struct TlsArgs {
    /// The CA (PEM) both sides trust; with --tls-cert and --tls-key, endpoints are
    /// `tls/HOST:PORT` and both sides verify each other (mutual TLS).
    #[arg(long, requires_all = ["tls_cert", "tls_key"])]
    tls_ca: Option<PathBuf>,
    /// This side's certificate (PEM), signed by --tls-ca.
    #[arg(long, requires_all = ["tls_ca", "tls_key"])]
    tls_cert: Option<PathBuf>,
    /// This side's private key (PEM).
    #[arg(long, requires_all = ["tls_ca", "tls_cert"])]
    tls_key: Option<PathBuf>,
    /// Servers: listen on a non-loopback address without TLS. Anyone on that network can
    /// then read the features, query the policy or impersonate the server.
    #[arg(long)]
    insecure: bool,
}

impl From<TlsArgs> for TlsOptions {
    fn from(a: TlsArgs) -> Self {
        TlsOptions {
            ca: a.tls_ca,
            cert: a.tls_cert,
            key: a.tls_key,
            insecure: a.insecure,
        }
    }
}

/// `pir2 serve …` (→ `ServeOptions`).
#[derive(Subcommand, Debug, Clone)]
enum ServeCmd {
    /// Answer action-head (one-NFE) requests until Ctrl-C: a candle checkpoint
    /// (`--checkpoint`, for `pir2 eval --remote`) or a GR00T export's ONNX action head
    /// (`--gr00t-checkpoint --task`, for `pir2 run … --remote-policy`).
    Policy {
        /// Candle checkpoint directory (config.json, stats.json, model.safetensors), e.g. the
        /// `best/` directory `pir2 train` writes.
        #[arg(
            long,
            required_unless_present = "gr00t_checkpoint",
            conflicts_with = "gr00t_checkpoint"
        )]
        checkpoint: Option<PathBuf>,
        /// A GR00T export (docs/gr00t-contract.md): its action head (four ONNX graphs + side
        /// weights + statistics) is served; feature `gr00t`.
        #[arg(long, requires = "task")]
        gr00t_checkpoint: Option<PathBuf>,
        /// With --gr00t-checkpoint: the task (key or prompt) whose prompt layout (image and
        /// text token masks) the DiT is fed; must be the robot's `--task`.
        #[arg(long)]
        task: Option<String>,
        /// Hold every reply this many ms: a stand-in for a slow network (tests, measuring how
        /// `d` follows the round trip). Zero in deployment.
        #[arg(long, default_value_t = 0)]
        inject_delay_ms: u64,
        /// Zenoh endpoint to listen on.
        #[arg(long, default_value = "tcp/127.0.0.1:7447")]
        listen: String,
        /// Key the requests arrive on.
        #[arg(long, default_value = "pir2/policy")]
        key: String,
        #[command(flatten)]
        tls: TlsArgs,
        /// Where ONNX Runtime runs the GR00T graphs.
        #[command(flatten)]
        ep: EpArgs,
    },
    /// Publish slow-channel features (camera → backbone) with capture times until Ctrl-C.
    Slow {
        /// Zenoh endpoint to listen on.
        #[arg(long, default_value = "tcp/127.0.0.1:7448")]
        listen: String,
        /// Key the features are published on (clock pings on `<key>/clock`).
        #[arg(long, default_value = "pir2/slow")]
        key: String,
        /// The GR00T ONNX backbone of this checkpoint (feature `gr00t`) on a synthetic camera.
        #[arg(long, required_unless_present = "stub", conflicts_with = "stub")]
        gr00t_checkpoint: Option<PathBuf>,
        /// Task (key or prompt) whose prompt the GR00T backbone encodes.
        #[arg(long, requires = "gr00t_checkpoint")]
        task: Option<String>,
        /// A stub: a counter camera of this many values and a pass-through encoder.
        #[arg(long)]
        stub: Option<usize>,
        /// Camera frame period, ms.
        #[arg(long, default_value_t = 60)]
        frame_ms: u64,
        #[command(flatten)]
        tls: TlsArgs,
        /// Where ONNX Runtime runs the GR00T graphs.
        #[command(flatten)]
        ep: EpArgs,
    },
}

impl From<ServeCmd> for ServeOptions {
    fn from(c: ServeCmd) -> Self {
        match c {
            ServeCmd::Policy {
                checkpoint,
                gr00t_checkpoint,
                task,
                inject_delay_ms,
                listen,
                key,
                tls,
                ep,
            } => ServeOptions::Policy {
                checkpoint,
                gr00t_checkpoint,
                task,
                inject_delay_ms,
                listen,
                key,
                tls: tls.into(),
                ep: ep.into(),
            },
            ServeCmd::Slow {
                listen,
                key,
                gr00t_checkpoint,
                task,
                stub,
                frame_ms,
                tls,
                ep,
            } => ServeOptions::Slow {
                listen,
                key,
                gr00t_checkpoint,
                task,
                stub,
                frame_ms,
                tls: tls.into(),
                ep: ep.into(),
            },
        }
    }
}

#[derive(Subcommand, Debug)]
enum RobotCmd {
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

/// The stop flag of SIGINT and SIGTERM (a second signal runs the registered emergency stop
/// and exits at once; see `pir2_cli::signals`).
/// The arguments of `pir2 train gr00t`.
#[cfg_attr(not(feature = "gr00t"), allow(dead_code))]
struct Gr00tArgs {
    data: PathBuf,
    out: PathBuf,
    seed: u64,
    resume: bool,
    checkpoint: Option<PathBuf>,
    embodiment: Option<PathBuf>,
    features: Option<PathBuf>,
    steps: usize,
    batch_size: usize,
    lr: f64,
    checkpoint_every: Option<usize>,
    state_key: String,
    action_key: String,
    no_dropout: bool,
    device: String,
    /// Options of the other tasks were given.
    unused: bool,
}

#[cfg(feature = "gr00t")]
fn train_gr00t(a: Gr00tArgs) -> Result<()> {
    use pir2_cli::study::gr00t::{train, Gr00tTrainOptions};
    if a.unused {
        anyhow::bail!("--policy, --config and --task are not options of `pir2 train gr00t`");
    }
    let need = |v: Option<PathBuf>, flag: &str| {
        v.ok_or_else(|| anyhow::anyhow!("`pir2 train gr00t` needs --{flag}"))
    };
    let mut o = Gr00tTrainOptions::new(
        &need(a.checkpoint, "checkpoint")?,
        &a.data,
        &need(a.embodiment, "embodiment")?,
        &need(a.features, "features")?,
        &a.out,
    );
    o.steps = a.steps;
    o.batch_size = a.batch_size;
    o.lr = a.lr;
    o.checkpoint_every = a.checkpoint_every;
    o.seed = a.seed;
    o.resume = a.resume;
    o.state_key = a.state_key;
    o.action_key = a.action_key;
    o.dropout = !a.no_dropout;
    o.device = a.device;
    o.stop = Some(ctrl_c_flag());
    let steps = o.steps;
    let s = train(&o, |p| {
        if p.step % 10 == 0 || p.step == steps {
            eprintln!(
                "step {}/{}  loss {:.5}  lr {:.2e}",
                p.step, p.steps, p.loss, p.lr
            );
        }
    })?;
    let (cache, built) = &s.cache;
    println!(
        "VL-token cache: {} ({})",
        cache.display(),
        if *built { "built" } else { "reused" }
    );
    if let Some((step, loss)) = s.report.losses.last() {
        println!("step {step}: loss {loss:.5}");
    }
    for c in &s.report.checkpoints {
        if let Some(d) = &c.dir {
            println!("checkpoint: {}", d.display());
        }
    }
    Ok(())
}

#[cfg(not(feature = "gr00t"))]
fn train_gr00t(_: Gr00tArgs) -> Result<()> {
    anyhow::bail!("`pir2 train gr00t` needs a build with `--features gr00t`")
}

/// The arguments of `pir2 features gr00t`.
#[cfg_attr(not(feature = "gr00t"), allow(dead_code))]
struct FeaturesArgs {
    checkpoint: PathBuf,
    data: PathBuf,
    embodiment: Option<PathBuf>,
    out: PathBuf,
    resume: bool,
    overwrite: bool,
    tolerance_s: f64,
    threads: usize,
}

#[cfg(feature = "gr00t")]
fn features_gr00t(a: FeaturesArgs) -> Result<()> {
    use pir2_cli::study::gr00t_features::{extract, Gr00tFeaturesOptions};
    let mut o = Gr00tFeaturesOptions::new(&a.checkpoint, &a.data, &a.out);
    o.embodiment = a.embodiment;
    o.resume = a.resume;
    o.overwrite = a.overwrite;
    o.tolerance_s = a.tolerance_s;
    o.ort.intra_threads = a.threads.max(1);
    o.stop = Some(ctrl_c_flag());
    let mut last = std::time::Instant::now();
    let s = extract(&o, |p| {
        if p.done == p.total || last.elapsed().as_secs_f64() >= 2.0 {
            last = std::time::Instant::now();
            let rate = p.this_run as f64 / p.elapsed.max(1e-9);
            let eta = (p.total - p.done) as f64 / rate.max(1e-9);
            eprintln!(
                "features: {}/{} frames ({:.1} %), episode {}, {:.2} frames/s, {:.0} s left",
                p.done,
                p.total,
                100.0 * p.done as f64 / p.total as f64,
                p.episode,
                rate,
                eta
            );
        }
    })?;
    let (n, t, d) = s.shape;
    println!("backbone: {}", s.backbone);
    println!("decoder: {}", s.decoder);
    if s.resumed_from > 0 {
        println!("resumed at frame {}", s.resumed_from);
    }
    if s.complete {
        println!(
            "features: {} (embeddings [{n}, {t}, {d}], image_mask, attention_mask)",
            s.path.display()
        );
    } else {
        println!(
            "interrupted after {} of {n} frames; {} is kept: run again with --resume",
            s.done,
            s.path.display()
        );
    }
    Ok(())
}

#[cfg(not(feature = "gr00t"))]
fn features_gr00t(_: FeaturesArgs) -> Result<()> {
    anyhow::bail!("`pir2 features gr00t` needs a build with `--features gr00t`")
}

fn ctrl_c_flag() -> Arc<AtomicBool> {
    pir2_cli::signals::stop_flag()
}

fn task(name: &str) -> TaskName {
    match name {
        "leap-cube" => TaskName::LeapCube,
        _ => TaskName::BallPlate,
    }
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

fn run() -> Result<()> {
    let cli = Cli::parse();
    match cli.cmd {
        Cmd::Demo {
            quick,
            config,
            out,
            episodes,
        } => commands::demo(&DemoOptions {
            quick,
            config,
            out,
            episodes,
        }),
        Cmd::Collect {
            task: t,
            out,
            episodes,
            seed,
            resume,
            overwrite,
            seeds,
            per_seed,
            fast,
            expert,
        } => commands::collect(&CollectOptions {
            task: task(&t),
            out,
            seeds,
            per_seed,
            fast,
            expert,
            episodes,
            seed,
            mode: if resume {
                WriteMode::Resume
            } else if overwrite {
                WriteMode::Overwrite
            } else {
                WriteMode::New
            },
            stop: ctrl_c_flag(),
        }),
        Cmd::Features {
            what: _,
            checkpoint,
            data,
            embodiment,
            out,
            resume,
            overwrite,
            tolerance_s,
            threads,
        } => features_gr00t(FeaturesArgs {
            checkpoint,
            data,
            embodiment,
            out,
            resume,
            overwrite,
            tolerance_s,
            threads,
        }),
        Cmd::Train {
            task: t,
            task_file,
            data,
            policy,
            out,
            config,
            seed,
            resume,
            checkpoint,
            embodiment,
            features,
            steps,
            batch_size,
            lr,
            checkpoint_every,
            state_key,
            action_key,
            no_dropout,
            device,
        } if t.as_deref() == Some("gr00t") => train_gr00t(Gr00tArgs {
            data,
            out,
            seed,
            resume,
            checkpoint,
            embodiment,
            features,
            steps,
            batch_size,
            lr,
            checkpoint_every,
            state_key,
            action_key,
            no_dropout,
            device,
            unused: policy.is_some() || config.is_some() || task_file.is_some(),
        }),
        Cmd::Train {
            task: t,
            task_file,
            data,
            policy,
            out,
            config,
            seed,
            resume,
            device,
            ..
        } => {
            if device != "cpu" {
                anyhow::bail!(
                    "--device is an option of `pir2 train gr00t`; the other tasks train on the cpu"
                );
            }
            commands::train(&TrainOptions {
                task: task(t.as_deref().unwrap_or("ballplate")),
                task_file,
                data,
                policy: policy.map(Into::into),
                out,
                config,
                seed,
                resume,
            })
        }
        Cmd::Eval {
            task: t,
            checkpoint,
            policy,
            study,
            config,
            data,
            out,
            d0,
            episodes,
            seed,
            json,
            remote,
            remote_timeout_ms,
            remote_max_failed,
            connect_timeout,
            tls,
            resume,
            train_missing,
        } => commands::eval(&EvalOptions {
            task: task(&t),
            checkpoint,
            policy: policy.map(Into::into),
            study,
            config,
            data,
            out,
            d0,
            episodes,
            seed,
            json,
            remote: remote.map(|endpoint| RemoteOptions {
                endpoint,
                timeout: Duration::from_millis(remote_timeout_ms.max(1)),
                max_failed: remote_max_failed.max(1),
                connect_timeout: Duration::from_secs_f64(connect_timeout.max(0.0)),
                tls: tls.into(),
            }),
            resume,
            train_missing,
        }),
        Cmd::Report {
            task: _,
            study,
            config,
            data,
            cells,
            out,
            partial,
        } => leap_cmd::report(
            &study,
            &LeapArgs {
                config: config.as_deref(),
                data: data.as_deref(),
                ..Default::default()
            },
            &cells,
            out.as_deref(),
            partial,
        ),
        Cmd::Run(args) => run::run_command(&(*args).into(), ctrl_c_flag()),
        Cmd::Serve { cmd } => serve::serve(&cmd.into(), ctrl_c_flag()),
        Cmd::Plot { input, out } => commands::plot(&input, out.as_deref()),
        Cmd::Export {
            checkpoint,
            onnx,
            gr00t,
        } => match (onnx, gr00t) {
            (Some(onnx), None) => commands::export(&checkpoint, &onnx),
            (None, Some(out)) => commands::export_gr00t(&checkpoint, &out),
            _ => Err(anyhow::anyhow!("give exactly one of --onnx and --gr00t")),
        },
        Cmd::Bench {
            what,
            seconds,
            checkpoint,
            task,
            ep,
        } => commands::bench(
            &what,
            seconds,
            checkpoint.as_deref().zip(task.as_deref()),
            &ep.into(),
        ),
        Cmd::Robot { cmd } => match cmd {
            RobotCmd::Check {
                xarm,
                xhand,
                clear_errors,
            } => commands::robot_check(xarm.as_deref(), xhand.as_deref(), clear_errors),
            RobotCmd::Emulate { robot, host, pty } => {
                let which = if robot == "xarm" {
                    Emulated::XArm(host)
                } else if pty {
                    Emulated::XHandPty
                } else {
                    bail!("the XHand emulator needs --pty (a pseudo-terminal other programs can open)");
                };
                commands::robot_emulate(which, ctrl_c_flag())
            }
        },
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
