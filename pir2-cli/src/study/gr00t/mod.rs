//! GR00T N1.7 with πR² (`pir2 gr00t …`): the frozen backbone's features over a dataset
//! (`features`), fine-tuning of a checkpoint's action head on them (`train`), and the export
//! of a fine-tuned step to the checkpoint layout `pir2 gr00t run` runs (`export`).
//!
//! The options are here, compiled in every build (the command line offers them everywhere);
//! the work needs feature `gr00t`.

#[cfg(feature = "gr00t")]
mod bench;
#[cfg(feature = "gr00t")]
mod export;
#[cfg(feature = "gr00t")]
pub mod features;
#[cfg(feature = "gr00t")]
mod train;

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use pir2_sim::dataset::DEFAULT_TOLERANCE_S;

#[cfg(feature = "gr00t")]
pub use bench::{bench_train, Gr00tTrainBench};
#[cfg(feature = "gr00t")]
pub use export::{export, Gr00tExportSummary};
#[cfg(feature = "gr00t")]
pub use train::{train, Gr00tTargets, Gr00tTrainSummary};

/// Options of `pir2 gr00t train`.
#[derive(Debug, Clone, clap::Args)]
pub struct Gr00tTrainOptions {
    /// The GR00T N1.7 checkpoint directory (config.json + model.safetensors).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Dataset directory (LeRobotDataset v3.0).
    #[arg(long)]
    pub data: PathBuf,
    /// The embodiment file (embodiment.toml).
    #[arg(long)]
    pub embodiment: PathBuf,
    /// The backbone's outputs per frame (safetensors: `embeddings` `[N,T,D_vl]`,
    /// `image_mask` `[N,T]`, optional `attention_mask` `[N,T]`), from `pir2 gr00t features`.
    #[arg(long)]
    pub features: PathBuf,
    /// Output directory (must not exist, unless --resume).
    #[arg(long)]
    pub out: PathBuf,
    /// Optimiser steps.
    #[arg(long, default_value_t = 1000)]
    pub steps: usize,
    /// Samples per step (the paper: 512).
    #[arg(long, default_value_t = 64)]
    pub batch_size: usize,
    /// Peak learning rate.
    #[arg(long, default_value_t = 1e-4)]
    pub lr: f64,
    /// A step checkpoint every this many steps (and at the end).
    #[arg(long)]
    pub checkpoint_every: Option<usize>,
    /// Seed of every draw.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Continue the interrupted run in --out.
    #[arg(long)]
    pub resume: bool,
    /// The dataset feature holding the state.
    #[arg(long, default_value = "observation.state")]
    pub state_key: String,
    /// The dataset feature holding the action.
    #[arg(long, default_value = "action")]
    pub action_key: String,
    /// Train without GR00T's DiT dropout (`dropout: false`; by default the checkpoint's
    /// `diffusion_model_cfg.dropout`, 0.2 in N1.7, applies in training only; inference and
    /// export never drop).
    #[arg(long = "no-dropout", action = clap::ArgAction::SetFalse)]
    pub dropout: bool,
    /// The candle device: `cpu`, `cuda[:N]` (a build with `--features cuda`) or
    /// `metal[:N]` (`--features metal`).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Stop flag (Ctrl-C): the state is saved as `interrupted-*`.
    #[arg(skip)]
    pub stop: Option<Arc<AtomicBool>>,
    /// Return after this many steps as if interrupted (tests, time slicing).
    #[arg(skip)]
    pub stop_after: Option<usize>,
}

impl Gr00tTrainOptions {
    /// The paper's robot recipe with the given inputs (batch 512 as in the paper: set a
    /// smaller one on a CPU).
    pub fn new(
        checkpoint: &Path,
        data: &Path,
        embodiment: &Path,
        features: &Path,
        out: &Path,
    ) -> Self {
        Self {
            checkpoint: checkpoint.to_path_buf(),
            data: data.to_path_buf(),
            embodiment: embodiment.to_path_buf(),
            features: features.to_path_buf(),
            out: out.to_path_buf(),
            state_key: "observation.state".into(),
            action_key: "action".into(),
            steps: 1000,
            batch_size: 512,
            lr: 1e-4,
            checkpoint_every: None,
            seed: 0,
            resume: false,
            stop: None,
            stop_after: None,
            dropout: true,
            device: "cpu".into(),
        }
    }
}

/// Options of `pir2 gr00t features`.
#[derive(Debug, Clone, clap::Args)]
pub struct Gr00tFeaturesOptions {
    /// The GR00T checkpoint directory (docs/gr00t-contract.md): `onnx/backbone.onnx`, or
    /// `onnx/vit_fp32.onnx` + `onnx/llm_fp32.onnx` + `model.safetensors`, and
    /// `tokenizer.json` (a GR00T N1.7 directory with those added).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Dataset directory (LeRobotDataset v3.0 with camera videos or image features).
    #[arg(long)]
    pub data: PathBuf,
    /// The embodiment file (default: the checkpoint's embodiment.toml); `cameras` names
    /// the dataset's camera (video or image) features in view order.
    #[arg(long)]
    pub embodiment: Option<PathBuf>,
    /// Output safetensors file (`embeddings` `[N,T,D_vl]`, `image_mask`, `attention_mask`).
    #[arg(long)]
    pub out: PathBuf,
    /// Continue an interrupted run (OUT.partial and OUT.partial.json).
    #[arg(long)]
    pub resume: bool,
    /// Replace an existing output file.
    #[arg(long)]
    pub overwrite: bool,
    /// Largest distance between a frame's timestamp and the decoded video frame, s
    /// (LeRobot's tolerance_s).
    #[arg(long, default_value_t = DEFAULT_TOLERANCE_S)]
    pub tolerance_s: f64,
    /// ONNX Runtime intra-op threads of the backbone.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Where ONNX Runtime runs the backbone graphs (a bfloat16 LLM graph needs `cuda` or
    /// `tensorrt`, or a float32 copy: `pir2 gr00t import --backbone-onnx`).
    #[command(flatten)]
    pub ep: crate::ep::EpOptions,
    /// Stop flag (Ctrl-C): the rows written so far are kept for `--resume`.
    #[arg(skip)]
    pub stop: Option<Arc<AtomicBool>>,
    /// Return after this many new frames as if interrupted (tests).
    #[arg(skip)]
    pub stop_after: Option<usize>,
}

impl Gr00tFeaturesOptions {
    /// Defaults for the given inputs (LeRobot's tolerance, ONNX Runtime on one CPU thread).
    pub fn new(checkpoint: &Path, data: &Path, out: &Path) -> Self {
        Self {
            checkpoint: checkpoint.to_path_buf(),
            data: data.to_path_buf(),
            embodiment: None,
            out: out.to_path_buf(),
            resume: false,
            overwrite: false,
            tolerance_s: DEFAULT_TOLERANCE_S,
            threads: 1,
            ep: crate::ep::EpOptions::default(),
            stop: None,
            stop_after: None,
        }
    }
}
