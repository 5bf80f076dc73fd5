//! [`run_gr00t`]: the `pir2 gr00t run gr00t-xarm-xhand` pipeline as a library function.
//!
//! Loads a checkpoint directory (layout in [`CheckpointFiles::in_dir`] and
//! `docs/gr00t-contract.md`), builds the [`Gr00tActionHead`] and the backbone, and runs the
//! runtime's real-time driver in the deployment the embodiment's `[policy]` table names
//! ([`PolicySection`](super::config::PolicySection), overridable per run): in πR² async (the
//! default) the action head makes one πR² call per tick on the action worker, the backbone
//! runs on the slow worker (`SlowChannel::Async`) and its features are cached with the frame's
//! capture time, so each call sees `d_vis = round((t_state − t_image)/T)`; the other rows of
//! the paper's robot table (sync flow with `h`, naive async ± temporal ensembling, train-time
//! RTC, πR² without async) run the backbone inside each call (`SlowChannel::Inline`).
//!
//! Wiring for `pir2 gr00t run gr00t-xarm-xhand --checkpoint DIR --task "catch the book"` (the robot
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
use std::sync::{Arc, Mutex};
use std::time::Duration;

use pir2_runtime::realtime::{run_keeping_metrics, RealtimeConfig, SlowChannel};
use pir2_runtime::{
    ActionHead, Actuator, Clock, ControlConfig, FastSource, HeadMode, HeadSpec, LatencyWindow,
    Mode, ModelInput, Nanos, RunMetrics, SlowEncoder, SlowSource, SystemClock, VelocityModel,
};

use super::backbone::Gr00tBackbone;
use super::config::{
    read_embodiment_id, CheckpointFiles, EmbodimentConfig, ModeOverrides, Normalizer,
};
use super::head::{Gr00tActionHead, VlLayout};
use super::prompt::PromptTokenizer;
use super::tokenizer::load_tokenizer;
use crate::error::{Error, Result};
use crate::ort::OrtOptions;

/// Where the backbone features come from.
pub enum BackboneChoice {
    /// `backbone.onnx` (+ `vl_self_attention.onnx`) from the checkpoint, prompt tokenised by
    /// `tokenizer` (default: the checkpoint's, see [`load_tokenizer`]: `tokenizer.json` with
    /// the chat template, else `vocab.txt`).
    Onnx {
        /// The tokenizer; `None`: the checkpoint's ([`load_tokenizer`]).
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

/// Where the action head runs.
pub enum HeadChoice {
    /// The checkpoint's four ONNX graphs, loaded here.
    Local,
    /// The checkpoint's action head, already loaded (e.g. by a pre-flight check before any
    /// robot was connected); its VL layout is set by the run.
    Loaded(Box<Gr00tActionHead>),
    /// The fine-tuned head in candle ([`super::Gr00tCandleHead`], from a `pir2 gr00t train`
    /// step directory, see [`load_candle_head`]) instead of the checkpoint's ONNX head
    /// graphs; its VL layout is set by the run.
    #[cfg(feature = "candle")]
    Candle(Box<super::Gr00tCandleHead>),
    /// Any other model with the checkpoint's interface, e.g. a
    /// `pir2_runtime::remote::RemoteModel` talking to `pir2 gr00t serve policy`
    /// on another machine. The checkpoint's embodiment and statistics are still read here
    /// (the executed actions are denormalised on the robot side); `d_vl` is the backbone
    /// token width the model expects. The runtime measures each call as a whole, so network
    /// round trips enter the latency window and `d`.
    Custom {
        /// The model.
        model: Box<dyn VelocityModel>,
        /// Backbone token width `D_vl` the model takes.
        d_vl: usize,
    },
}

impl std::fmt::Debug for HeadChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HeadChoice::Local => f.write_str("Local"),
            HeadChoice::Loaded(h) => f.debug_tuple("Loaded").field(h.dims()).finish(),
            #[cfg(feature = "candle")]
            HeadChoice::Candle(h) => f.debug_tuple("Candle").field(&h.path()).finish(),
            HeadChoice::Custom { model, d_vl } => f
                .debug_struct("Custom")
                .field("backend", &model.backend())
                .field("d_vl", d_vl)
                .finish(),
        }
    }
}

/// Counts the calls per clamped `d_vis` of a model that does not count them itself.
struct CountDvis {
    inner: Box<dyn VelocityModel>,
    counts: Vec<u64>,
}

impl VelocityModel for CountDvis {
    fn backend(&self) -> &'static str {
        self.inner.backend()
    }
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        let last = self.counts.len() - 1;
        for &d in input.d_vis {
            self.counts[(d as usize).min(last)] += 1;
        }
        self.inner.velocity(input, out)
    }
    fn watch_stop(&mut self, stop: pir2_runtime::StopSignal) {
        self.inner.watch_stop(stop)
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
    /// The action head.
    pub head: HeadChoice,
    /// The deployment: the embodiment's `[policy]` table (what the head was trained as, and
    /// its default mode) with these overrides. A mode the head was not trained for is an
    /// error before anything is loaded onto the robot.
    pub mode: ModeOverrides,
    /// Euler steps of the warm start (πR² modes).
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
    /// Stale-slow stop (always on): once the backbone features are older than `d_vis_max`
    /// ticks for longer than this grace, the robot stops with a safety stop
    /// (`ActionHead::set_slow_grace`). `None`: the embodiment's `safety.slow_grace_ms`
    /// (200 ms when its `[safety]` table does not set it).
    pub slow_grace: Option<Duration>,
    /// Control watchdog: this long without a clean action (overruns, holds, ticks past the
    /// chunk) stops the robot with a safety stop; in `(0, MAX_STALL_LIMIT]`
    /// ([`pir2_runtime::realtime::MAX_STALL_LIMIT`]), default one second.
    pub stall_limit: Duration,
    /// Where a run that fails after its control loop started leaves the metrics of the ticks
    /// it ran (the trace of a safety stop), if given.
    pub failed_metrics: Option<Arc<Mutex<Option<RunMetrics>>>>,
}

impl Default for Gr00tRunOptions {
    fn default() -> Self {
        Gr00tRunOptions {
            embodiment: None,
            ort: OrtOptions::default(),
            backbone: BackboneChoice::Onnx { tokenizer: None },
            head: HeadChoice::Local,
            mode: ModeOverrides::default(),
            warm_start_steps: 4,
            window: 20,
            max_ticks: None,
            stop: Arc::new(AtomicBool::new(false)),
            clock: Arc::new(SystemClock::new()),
            seed: 0,
            slow_timeout: Duration::from_secs(60),
            slow_grace: None,
            stall_limit: pir2_runtime::realtime::DEFAULT_STALL_LIMIT,
            failed_metrics: None,
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
    /// The tokenizer the prompt went through (empty with a custom backbone).
    pub tokenizer: String,
    /// The backbone graphs run (fused `backbone.onnx` or GR00T's split export; "a custom
    /// encoder" with [`BackboneChoice::Custom`]).
    pub backbone: String,
    /// The embodiment used.
    pub embodiment: EmbodimentConfig,
    /// The deployment mode run (mode and schedule).
    pub mode: Mode,
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

/// Load the checkpoint's action head (embodiment, statistics, embodiment id, the four
/// graphs and side weights, all checked against the contract) with the VL token layout of
/// `task`'s prompt (from the checkpoint's tokenizer and the embodiment's prompt layout) set, so it answers
/// calls on its own: what `pir2 gr00t serve policy` serves, and what the
/// pre-flight check of `pir2 gr00t run` loads before any robot is connected. Returns the head and
/// the prompt.
pub fn load_action_head(
    checkpoint_dir: &Path,
    task: &str,
    ort: &OrtOptions,
) -> Result<(Gr00tActionHead, String)> {
    let files = CheckpointFiles::in_dir(checkpoint_dir);
    let cfg = files.embodiment_config()?;
    cfg.validate()?;
    let prompt = cfg.prompt_for(task).to_string();
    if prompt.trim().is_empty() {
        return Err(Error::Gr00tConfig("empty task prompt".to_string()));
    }
    let norm = Normalizer::load(&files.statistics, &cfg)?;
    let embodiment_id =
        read_embodiment_id(&files.embodiment_id, &cfg.embodiment_tag)?.unwrap_or(cfg.embodiment_id);
    let mut head = Gr00tActionHead::load(&files, &cfg, norm, embodiment_id, ort)?;
    let tok = load_tokenizer(&files, &cfg.prompt)?;
    let layout = super::tokenizer::build_sequence(tok.as_ref(), &prompt, &cfg.prompt)?.layout;
    if let Some(t) = head.dims().vl_tokens {
        if t != layout.image_mask.len() {
            return Err(Error::Gr00tContract {
                path: files.dit.clone(),
                tensor: "vl_embs".to_string(),
                problem: format!(
                    "fixes T = {t} tokens but the prompt layout has {} \
                     (prompt.image_tokens + prompt.text_tokens)",
                    layout.image_mask.len()
                ),
            });
        }
    }
    head.set_vl_layout(layout);
    Ok((head, prompt))
}

/// [`load_action_head`] for the candle head of `step` (a `pir2 gr00t train` step directory)
/// in place of the checkpoint's ONNX head graphs; the embodiment, statistics, slot and
/// tokenizer are the checkpoint's. If the step's run (the step directory or the one above it)
/// has a `statistics.json` or `embodiment.toml`, it must equal the checkpoint's: the head
/// was trained on those normalisations, and another one would be silently wrong.
#[cfg(feature = "candle")]
pub fn load_candle_head(
    checkpoint_dir: &Path,
    step: &Path,
    task: &str,
) -> Result<(super::Gr00tCandleHead, String)> {
    let files = CheckpointFiles::in_dir(checkpoint_dir);
    let cfg = files.embodiment_config()?;
    cfg.validate()?;
    let prompt = cfg.prompt_for(task).to_string();
    if prompt.trim().is_empty() {
        return Err(Error::Gr00tConfig("empty task prompt".to_string()));
    }
    let root = step.parent().unwrap_or(step);
    for (name, mine) in [
        ("statistics.json", &files.statistics),
        ("embodiment.toml", &files.embodiment),
    ] {
        for dir in [step, root] {
            let theirs = dir.join(name);
            if !theirs.is_file() {
                continue;
            }
            let a = std::fs::read(&theirs).map_err(|source| Error::Read {
                path: theirs.clone(),
                source,
            })?;
            let same = match name {
                // The run's TOML may differ in layout: compare the parsed configurations.
                "embodiment.toml" => EmbodimentConfig::load(&theirs)? == cfg,
                _ => std::fs::read(mine).map(|b| b == a).unwrap_or(false),
            };
            if !same {
                return Err(Error::Gr00tConfig(format!(
                    "`{}` differs from the checkpoint's `{}`: the candle head was trained with the former",
                    theirs.display(),
                    mine.display()
                )));
            }
            break;
        }
    }
    let norm = Normalizer::load(&files.statistics, &cfg)?;
    let embodiment_id =
        read_embodiment_id(&files.embodiment_id, &cfg.embodiment_tag)?.unwrap_or(cfg.embodiment_id);
    let mut head = super::Gr00tCandleHead::load(step, &cfg, norm, embodiment_id)?;
    let tok = load_tokenizer(&files, &cfg.prompt)?;
    let layout = super::tokenizer::build_sequence(tok.as_ref(), &prompt, &cfg.prompt)?.layout;
    head.set_vl_layout(layout);
    Ok((head, prompt))
}

/// The action head a run drives.
enum RunHead {
    Onnx(Box<Gr00tActionHead>),
    #[cfg(feature = "candle")]
    Candle(Box<super::Gr00tCandleHead>),
    Custom(Box<dyn VelocityModel>, usize),
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
        None => files.embodiment_config()?,
    };
    cfg.validate()?;
    let run_mode = cfg.policy.mode(&opts.mode)?;
    let prompt = cfg.prompt_for(task).to_string();
    if prompt.trim().is_empty() {
        return Err(Error::Gr00tConfig("empty task prompt".to_string()));
    }
    let norm = Normalizer::load(&files.statistics, &cfg)?;
    let mut local: RunHead = match opts.head {
        HeadChoice::Local => {
            let embodiment_id = read_embodiment_id(&files.embodiment_id, &cfg.embodiment_tag)?
                .unwrap_or(cfg.embodiment_id);
            RunHead::Onnx(Box::new(Gr00tActionHead::load(
                &files,
                &cfg,
                norm.clone(),
                embodiment_id,
                &opts.ort,
            )?))
        }
        HeadChoice::Loaded(h) => RunHead::Onnx(h),
        #[cfg(feature = "candle")]
        HeadChoice::Candle(h) => RunHead::Candle(h),
        HeadChoice::Custom { model, d_vl } => RunHead::Custom(model, d_vl),
    };
    let (d_vl, vl_tokens) = match &local {
        RunHead::Onnx(h) => (h.dims().d_vl, h.dims().vl_tokens),
        #[cfg(feature = "candle")]
        RunHead::Candle(h) => (h.d_vl(), None),
        RunHead::Custom(_, d_vl) => (*d_vl, None),
    };
    let mut tokenizer_used = String::new();
    let mut backbone_used = String::from("a custom encoder");
    let (encoder, layout): (Box<dyn SlowEncoder>, VlLayout) = match opts.backbone {
        BackboneChoice::Onnx { tokenizer } => {
            let tok: Box<dyn PromptTokenizer> = match tokenizer {
                Some(t) => t,
                None => load_tokenizer(&files, &cfg.prompt)?,
            };
            tokenizer_used = tok.describe();
            let d_vl_source = match &local {
                RunHead::Onnx(_) => files.dit.clone(),
                #[cfg(feature = "candle")]
                RunHead::Candle(h) => h.path().join("config.json"),
                RunHead::Custom(..) => "<the custom action head's D_vl>".into(),
            };
            let bb = Gr00tBackbone::load(
                &files,
                &cfg.image,
                &cfg.prompt,
                &cfg.vision,
                tok.as_ref(),
                &prompt,
                Some((d_vl, d_vl_source)),
                &opts.ort,
            )?;
            backbone_used = bb.describe();
            let layout = bb.layout().clone();
            (Box::new(bb), layout)
        }
        BackboneChoice::Custom { encoder, layout } => (encoder, layout),
    };
    let tokens = layout.image_mask.len();
    if tokens == 0 || layout.attention_mask.len() != tokens {
        return Err(Error::input(
            "VL layout (image and attention masks of one length T > 0)",
            tokens,
            layout.attention_mask.len(),
        ));
    }
    if let Some(t) = vl_tokens {
        if t != tokens {
            return Err(Error::Gr00tContract {
                path: files.dit.clone(),
                tensor: "vl_embs".to_string(),
                problem: format!(
                    "fixes T = {t} tokens but the backbone layout has {tokens} \
                     (prompt.image_tokens + prompt.text_tokens)"
                ),
            });
        }
    }
    match &mut local {
        RunHead::Onnx(h) => h.set_vl_layout(layout),
        #[cfg(feature = "candle")]
        RunHead::Candle(h) => h.set_vl_layout(layout),
        RunHead::Custom(..) => {}
    }
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
    let mode = run_mode.head_mode(opts.warm_start_steps);
    let control = ControlConfig {
        horizon: cfg.horizon,
        action_dim: cfg.action_dim(),
        policy: run_mode.call_policy(),
        ensemble: run_mode.ensemble(),
        output: norm.action_output_map(),
    };
    let rt = RealtimeConfig {
        period,
        max_ticks: opts.max_ticks,
        initial_delay: 1,
        slow_timeout: opts.slow_timeout,
        rt_priority: None,
        stall_limit: Some(opts.stall_limit),
    };
    // Only πR² async runs the backbone on its own worker; every other row of the paper's
    // table runs it inside each call, so its time counts in the call's `d`.
    let slow = if matches!(run_mode, Mode::PiR2Async { .. }) {
        SlowChannel::Async {
            source: Box::new(camera),
            encoder,
        }
    } else {
        SlowChannel::Inline {
            source: Box::new(camera),
            encoder,
        }
    };
    if opts.stall_limit.is_zero() || opts.stall_limit > pir2_runtime::realtime::MAX_STALL_LIMIT {
        return Err(Error::Gr00tConfig(format!(
            "the control watchdog's stall limit must be in (0, {:?}], got {:?}",
            pir2_runtime::realtime::MAX_STALL_LIMIT,
            opts.stall_limit
        )));
    }
    let slow_grace = opts.slow_grace.unwrap_or(cfg.slow_grace());
    if slow_grace.is_zero() {
        return Err(Error::Gr00tConfig(
            "the stale-slow grace must be > 0".into(),
        ));
    }
    let setup = Setup {
        slow_grace: u64::try_from(slow_grace.as_nanos()).unwrap_or(u64::MAX),
        spec,
        mode,
        window: LatencyWindow::new(opts.window.max(1), 2, period, cfg.d_max),
        seed: opts.seed,
        control,
        rt,
        slow,
        clock: opts.clock,
        stop: opts.stop,
        failed_metrics: opts.failed_metrics,
    };
    let (metrics, d_vis_counts) = match local {
        RunHead::Onnx(model) => {
            let (m, model) = drive(*model, setup, fast, actuator)?;
            (m, model.d_vis_counts().to_vec())
        }
        #[cfg(feature = "candle")]
        RunHead::Candle(model) => {
            let (m, model) = drive(*model, setup, fast, actuator)?;
            (m, model.d_vis_counts().to_vec())
        }
        RunHead::Custom(inner, _) => {
            let model = CountDvis {
                inner,
                counts: vec![0; cfg.d_vis_max + 1],
            };
            let (m, model) = drive(model, setup, fast, actuator)?;
            (m, model.counts)
        }
    };
    Ok(Gr00tRunReport {
        metrics,
        d_vis_counts,
        prompt,
        tokenizer: tokenizer_used,
        backbone: backbone_used,
        embodiment: cfg,
        mode: run_mode,
    })
}

/// Everything of a run but the model and the robot.
struct Setup {
    slow_grace: Nanos,
    spec: HeadSpec,
    mode: HeadMode,
    window: LatencyWindow,
    seed: u64,
    control: ControlConfig,
    rt: RealtimeConfig,
    slow: SlowChannel,
    clock: Arc<dyn Clock>,
    stop: Arc<AtomicBool>,
    failed_metrics: Option<Arc<Mutex<Option<RunMetrics>>>>,
}

fn drive<M: VelocityModel + 'static, F: FastSource, A: Actuator>(
    model: M,
    s: Setup,
    fast: F,
    actuator: A,
) -> Result<(RunMetrics, M)> {
    let mut head = ActionHead::new(model, s.spec, s.mode, s.window, s.seed)?;
    head.set_slow_grace(Some(s.slow_grace));
    match run_keeping_metrics(
        head, s.control, fast, actuator, s.slow, s.clock, s.rt, s.stop,
    ) {
        Ok((metrics, head)) => Ok((metrics, head.into_model())),
        Err(f) => {
            if let (Some(sink), Some(m)) = (&s.failed_metrics, f.metrics) {
                *sink.lock().unwrap_or_else(|p| p.into_inner()) = Some(*m);
            }
            Err(f.error.into())
        }
    }
}
