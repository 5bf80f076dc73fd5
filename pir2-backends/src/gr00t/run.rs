//! [`run_gr00t`]: the `pir2 run gr00t-xarm-xhand` pipeline as a library function.
//!
//! Loads a checkpoint directory (layout in [`CheckpointFiles::in_dir`] and
//! `docs/gr00t-contract.md`), builds the [`Gr00tActionHead`] and the backbone, and runs the
//! runtime's real-time driver: the action head makes one πR² call per tick on the action
//! worker, the backbone runs on the slow worker (`SlowChannel::Async`) and its features are
//! cached with the frame's capture time, so each call sees `d_vis = round((t_state − t_image)/T)`.
//!
//! Wiring for `pir2 run gr00t-xarm-xhand --checkpoint DIR --task "catch the book"` (the robot
//! from `pir2-robots`, any camera implementing [`SlowSource`] on the same clock):
//!
//! ```ignore
//! let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
//! let robot = pir2_robots::connect_arm_hand(/* addresses, safety config */, clock.clone())?;
//! let (source, actuator) = pir2_robots::split(robot);
//! let opts = Gr00tRunOptions { clock: clock.clone(), stop: ctrl_c_flag, ..Default::default() };
//! let metrics = run_gr00t(&dir, "catch the book", source, actuator, camera, opts)?;
//! ```

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::realtime::{run, RealtimeConfig, SlowChannel};
use pir2_runtime::{
    ActionHead, Actuator, CallPolicy, Clock, ControlConfig, FastSource, HeadMode, HeadSpec,
    LatencyWindow, RunMetrics, SlowEncoder, SlowSource, SystemClock,
};
use pir2_schedule::{Alignment, FrontMode};

use super::backbone::{Gr00tBackbone, PromptTokenizer, VocabTokenizer};
use super::config::{read_embodiment_id, CheckpointFiles, EmbodimentConfig, Normalizer};
use super::error::{Gr00tError, Result};
use super::head::{Gr00tActionHead, VlLayout};
use crate::ort::OrtOptions;

/// Where the backbone features come from.
pub enum BackboneChoice {
    /// `backbone.onnx` (+ `vl_self_attention.onnx`) from the checkpoint, prompt tokenised by
    /// `tokenizer` (default: [`VocabTokenizer`] on the checkpoint's `vocab.txt`).
    Onnx {
        /// The tokenizer; `None` reads `vocab.txt`.
        tokenizer: Option<Box<dyn PromptTokenizer>>,
    },
    /// Any other encoder (e.g. a remote backbone client) producing `[T, D_vl]` tokens whose
    /// token layout is `layout`.
    Custom {
        /// The encoder.
        encoder: Box<dyn SlowEncoder>,
        /// Its token layout (length `T`).
        layout: VlLayout,
    },
}

impl std::fmt::Debug for BackboneChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BackboneChoice::Onnx { tokenizer } => f
                .debug_struct("Onnx")
                .field("custom_tokenizer", &tokenizer.is_some())
                .finish(),
            BackboneChoice::Custom { layout, .. } => f
                .debug_struct("Custom")
                .field("tokens", &layout.image_mask.len())
                .finish(),
        }
    }
}

/// Options of [`run_gr00t`].
#[derive(Debug)]
pub struct Gr00tRunOptions {
    /// Embodiment; `None` reads `embodiment.toml` from the checkpoint if present, else the
    /// built-in [`EmbodimentConfig::xarm6_xhand`].
    pub embodiment: Option<EmbodimentConfig>,
    /// ONNX Runtime options (threads, library path).
    pub ort: OrtOptions,
    /// The backbone.
    pub backbone: BackboneChoice,
    /// NFEs per action (`None` = full ramp; DESIGN.md §1 recommends a short ramp).
    pub nfe: Option<usize>,
    /// Staircase alignment.
    pub alignment: Alignment,
    /// Front visibility.
    pub front: FrontMode,
    /// Euler steps of the warm start.
    pub warm_start_steps: usize,
    /// Latency window length `W` (calls).
    pub window: usize,
    /// Stop after this many ticks (`None`: until `stop`).
    pub max_ticks: Option<u64>,
    /// Stop flag (e.g. Ctrl-C).
    pub stop: Arc<AtomicBool>,
    /// The clock.
    pub clock: Arc<dyn Clock>,
    /// Noise seed.
    pub seed: u64,
    /// How long to wait for the first backbone features.
    pub slow_timeout: Duration,
}

impl Default for Gr00tRunOptions {
    fn default() -> Self {
        Gr00tRunOptions {
            embodiment: None,
            ort: OrtOptions::default(),
            backbone: BackboneChoice::Onnx { tokenizer: None },
            nfe: Some(2),
            alignment: Alignment::Fresh,
            front: FrontMode::Visible,
            warm_start_steps: 4,
            window: 20,
            max_ticks: None,
            stop: Arc::new(AtomicBool::new(false)),
            clock: Arc::new(SystemClock::new()),
            seed: 0,
            slow_timeout: Duration::from_secs(60),
        }
    }
}

/// What [`run_gr00t_report`] returns.
#[derive(Debug)]
pub struct Gr00tRunReport {
    /// The runtime's metrics (ticks, swaps, overruns, per-call `d`, `d_vis`, latencies).
    pub metrics: RunMetrics,
    /// Calls of the action head per `d_vis` value fed through the delay embedding.
    pub d_vis_counts: Vec<u64>,
    /// The prompt used.
    pub prompt: String,
    /// The embodiment used.
    pub embodiment: EmbodimentConfig,
}

/// Run the GR00T-N1.7 xArm6 + XHand stack on `fast`/`actuator` (the robot's proprioception
/// source and command sink, e.g. `pir2_robots::split` of the safety-wrapped composite) and
/// `camera`, with the task `task` (a key of the embodiment's `tasks` or a prompt verbatim).
///
/// The robot's state timestamps and the camera's capture times must be on `opts.clock`
/// (`d_vis` is their difference). The robot is stopped (`Actuator::stop`) on every exit path
/// of the driver; loading errors return before anything is sent.
pub fn run_gr00t<F, A, C>(
    checkpoint_dir: &Path,
    task: &str,
    fast: F,
    actuator: A,
    camera: C,
    opts: Gr00tRunOptions,
) -> Result<RunMetrics>
where
    F: FastSource,
    A: Actuator,
    C: SlowSource + 'static,
{
    run_gr00t_report(checkpoint_dir, task, fast, actuator, camera, opts).map(|r| r.metrics)
}

/// [`run_gr00t`] with the per-`d_vis` call counts and the resolved configuration.
pub fn run_gr00t_report<F, A, C>(
    checkpoint_dir: &Path,
    task: &str,
    fast: F,
    actuator: A,
    camera: C,
    opts: Gr00tRunOptions,
) -> Result<Gr00tRunReport>
where
    F: FastSource,
    A: Actuator,
    C: SlowSource + 'static,
{
    let files = CheckpointFiles::in_dir(checkpoint_dir);
    let cfg = match opts.embodiment {
        Some(c) => c,
        None if files.embodiment.exists() => EmbodimentConfig::load(&files.embodiment)?,
        None => EmbodimentConfig::xarm6_xhand(),
    };
    cfg.validate()?;
    let prompt = cfg.prompt_for(task).to_string();
    if prompt.trim().is_empty() {
        return Err(Gr00tError::Config("empty task prompt".to_string()));
    }
    let norm = Normalizer::load(&files.statistics, &cfg)?;
    let embodiment_id =
        read_embodiment_id(&files.embodiment_id, &cfg.embodiment_tag)?.unwrap_or(cfg.embodiment_id);
    let mut model = Gr00tActionHead::load(&files, &cfg, norm.clone(), embodiment_id, &opts.ort)?;
    let d_vl = model.dims().d_vl;
    let (encoder, layout): (Box<dyn SlowEncoder>, VlLayout) = match opts.backbone {
        BackboneChoice::Onnx { tokenizer } => {
            let tok: Box<dyn PromptTokenizer> = match tokenizer {
                Some(t) => t,
                None => Box::new(VocabTokenizer::load(&files.vocab)?),
            };
            let bb = Gr00tBackbone::load(
                &files,
                &cfg.image,
                &cfg.prompt,
                tok.as_ref(),
                &prompt,
                Some((d_vl, files.dit.clone())),
                &opts.ort,
            )?;
            let layout = bb.layout().clone();
            (Box::new(bb), layout)
        }
        BackboneChoice::Custom { encoder, layout } => (encoder, layout),
    };
    let tokens = layout.image_mask.len();
    if tokens == 0 || layout.attention_mask.len() != tokens {
        return Err(Gr00tError::input(
            "VL layout (image and attention masks of one length T > 0)",
            tokens,
            layout.attention_mask.len(),
        ));
    }
    if let Some(t) = model.dims().vl_tokens {
        if t != tokens {
            return Err(Gr00tError::Contract {
                path: files.dit.clone(),
                tensor: "vl_embs".to_string(),
                problem: format!(
                    "fixes T = {t} tokens but the backbone layout has {tokens} \
                     (prompt.image_tokens + prompt.text_tokens)"
                ),
            });
        }
    }
    model.set_vl_layout(layout);

    let period = cfg.period_ns();
    let spec = HeadSpec {
        horizon: cfg.horizon,
        action_dim: cfg.action_dim(),
        n_obs: cfg.n_obs,
        fast_dim: cfg.state_dim(),
        slow_dim: tokens * d_vl,
        period,
        d_max: cfg.d_max,
        d_vis_max: cfg.d_vis_max,
    };
    let mode = HeadMode::PiR2 {
        nfe: opts.nfe,
        alignment: opts.alignment,
        front: opts.front,
        warm_start_steps: opts.warm_start_steps,
    };
    let head = ActionHead::new(
        model,
        spec,
        mode,
        LatencyWindow::new(opts.window.max(1), 2, period, cfg.d_max),
        opts.seed,
    )?;
    let control = ControlConfig {
        horizon: cfg.horizon,
        action_dim: cfg.action_dim(),
        policy: CallPolicy::Async,
        ensemble: None,
        output: norm.action_output_map(),
    };
    let rt = RealtimeConfig {
        period,
        max_ticks: opts.max_ticks,
        initial_delay: 1,
        slow_timeout: opts.slow_timeout,
        rt_priority: None,
    };
    let slow = SlowChannel::Async {
        source: Box::new(camera),
        encoder,
    };
    let (metrics, head) = run(
        head, control, fast, actuator, slow, opts.clock, rt, opts.stop,
    )?;
    Ok(Gr00tRunReport {
        metrics,
        d_vis_counts: head.model().d_vis_counts().to_vec(),
        prompt,
        embodiment: cfg,
    })
}
