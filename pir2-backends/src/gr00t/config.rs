//! The embodiment configuration (serde TOML/JSON) and GR00T's normalisation statistics.
//!
//! [`EmbodimentConfig::xarm6_xhand`] is the paper's real-robot setup: 45-d proprioception
//! (6 arm joints, 12 hand joints, 12 hand torques, 15 fingertip forces), 18-d absolute joint
//! targets, `H = 50` at 25 Hz, `d_max = d_vis_max = 5`, and the four task prompts of the
//! paper's task-prompt table.
//!
//! Statistics come from the checkpoint's `statistics.json` in GR00T's layout
//! `{embodiment_tag: {"state"|"action": {group: {"min","max","mean","std","q01","q99": [..]}}}}`.
//! Per group, [`Norm`] picks the map (GR00T's `StateActionProcessor`):
//! - `min_max`: `2·(x − min)/max(max − min, 1e-8) − 1`, clipped to `[-1, 1]` for states;
//! - `q01_q99`: the same with `q01`/`q99` in place of `min`/`max`;
//! - `mean_std`: `(x − mean)/std` (`std` floored at `1e-8`);
//! - `none`: identity.
//!
//! Actions are denormalised by the runtime's output map (`scale·x + offset`), see
//! [`Normalizer::action_output_map`].

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::error::{Gr00tError, Result};
use super::tokenizer::ChatTemplate;

/// The four task prompts of the paper (Table "Real-world task prompts"): `(task, prompt)`.
pub const PAPER_TASKS: [(&str, &str); 4] = [
    (
        "dont_spill",
        "put the ball in the bowl and put them on the cutting board",
    ),
    ("tidy_up_book", "put the books in the basket"),
    ("insert_box", "put the box in the basket"),
    ("catch_book", "catch the book"),
];

/// A normalisation map for one joint group.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Norm {
    /// Min/max to `[-1, 1]` (GR00T's default).
    #[default]
    MinMax,
    /// Percentiles `q01`/`q99` to `[-1, 1]` (GR00T's `use_percentiles`).
    Q01Q99,
    /// Mean/std.
    MeanStd,
    /// No normalisation.
    None,
}

/// One named slice of the state or action vector.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Group {
    /// The key in `statistics.json` (GR00T's modality key).
    pub name: String,
    /// Width of the slice.
    pub dim: usize,
    /// Normalisation.
    #[serde(default)]
    pub norm: Norm,
}

impl Group {
    fn new(name: &str, dim: usize) -> Self {
        Group {
            name: name.to_string(),
            dim,
            norm: Norm::MinMax,
        }
    }
}

/// How camera frames become the backbone's `pixel_values` (see [`super::image`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImagePipeline {
    /// GR00T N1.7's processor: letterbox, `INTER_AREA` resize of the shorter side to
    /// `shortest_edge`, centre crop `crop_fraction`, resize back; `pixel_values` is
    /// `[N, 3, shortest_edge, shortest_edge]`.
    #[default]
    Gr00tN17,
    /// pir2's earlier approximation: bilinear resize of the shorter side to `resize`, centre
    /// crop `crop`; `pixel_values` is `[N, 3, crop, crop]`. Kept for checkpoints exported
    /// with it; not what GR00T N1.7 was trained on.
    ResizeCrop,
}

/// Camera preprocessing, then `(x/255 − mean)/std` per channel.
///
/// ```toml
/// [image]
/// pipeline = "gr00t_n17"  # or "resize_crop"
/// letterbox = true        # GR00T: processor_config.json `letter_box_transform`
/// shortest_edge = 256     # GR00T: `shortest_image_edge`
/// crop_fraction = 0.95    # GR00T: `crop_fraction`
/// mean = [0.5, 0.5, 0.5]  # the VLM image processor's (Qwen3-VL: 0.5)
/// std = [0.5, 0.5, 0.5]
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImageConfig {
    /// Which preprocessing (default GR00T N1.7's).
    pub pipeline: ImagePipeline,
    /// `gr00t_n17`: pad to a square with black first (a non-square frame without it is an
    /// error).
    pub letterbox: bool,
    /// `gr00t_n17`: the shorter side after each resize (GR00T N1.7: 256).
    pub shortest_edge: usize,
    /// `gr00t_n17`: centre-crop fraction between the resizes (GR00T N1.7: 0.95).
    pub crop_fraction: f64,
    /// `resize_crop`: shorter side after resizing.
    pub resize: usize,
    /// `resize_crop`: side of the square centre crop.
    pub crop: usize,
    /// Per-channel mean subtracted after scaling to `[0, 1]` (RGB).
    pub mean: [f32; 3],
    /// Per-channel std divided by (RGB).
    pub std: [f32; 3],
}

impl Default for ImageConfig {
    fn default() -> Self {
        // Qwen-VL image processors normalise with mean = std = 0.5 per channel.
        ImageConfig {
            pipeline: ImagePipeline::Gr00tN17,
            letterbox: true,
            shortest_edge: 256,
            crop_fraction: 0.95,
            resize: 256,
            crop: 230,
            mean: [0.5; 3],
            std: [0.5; 3],
        }
    }
}

impl ImageConfig {
    /// Side of the square image the backbone receives (`pixel_values` `[N, 3, s, s]`).
    pub fn pixel_side(&self) -> usize {
        match self.pipeline {
            ImagePipeline::Gr00tN17 => self.shortest_edge,
            ImagePipeline::ResizeCrop => self.crop,
        }
    }
}

/// Prompt layout of the backbone input (see [`super::backbone`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PromptConfig {
    /// Image placeholder tokens in the sequence (the ViT's merged patch count).
    pub image_tokens: usize,
    /// Text tokens: with a chat template, every non-image token (template and instruction;
    /// padded to this length, a longer prompt is an error); without one, the prompt's tokens
    /// after the image, padded/truncated to this length.
    pub text_tokens: usize,
    /// The chat template around the images and the instruction (GR00T N1.7's by default);
    /// used with the VLM's `tokenizer.json`, not with a `vocab.txt`.
    #[serde(default)]
    pub chat: ChatTemplate,
}

impl Default for PromptConfig {
    fn default() -> Self {
        PromptConfig {
            image_tokens: 64,
            text_tokens: 32,
            chat: ChatTemplate::default(),
        }
    }
}

/// The embodiment: sizes, timing, groups, prompts and the GR00T-specific constants.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EmbodimentConfig {
    /// A name for logs.
    pub name: String,
    /// The top-level key in `statistics.json` and `embodiment_id.json`.
    pub embodiment_tag: String,
    /// Embodiment slot fed as `embodiment_id` (overridden by `embodiment_id.json` if present).
    pub embodiment_id: i64,
    /// Control rate, Hz.
    pub control_hz: f64,
    /// Chunk length `H`.
    pub horizon: usize,
    /// Largest action-head delay trained for.
    pub d_max: usize,
    /// Largest slow-feature age trained for (the delay table has `d_vis_max + 1` rows).
    pub d_vis_max: usize,
    /// Proprioception history length (GR00T's `state_history_length`).
    pub n_obs: usize,
    /// Timestep buckets (GR00T: 1000): `t = floor(τ · buckets)`, clamped to `buckets − 1`.
    pub num_timestep_buckets: i64,
    /// Timestep of the state token in the per-position `timestep [B, 1+H]`
    /// (default `buckets − 1`: the state is an observation, i.e. clean).
    pub state_token_timestep: Option<i64>,
    /// State groups, in vector order.
    pub state: Vec<Group>,
    /// Action groups, in vector order.
    pub action: Vec<Group>,
    /// Named task prompts.
    pub tasks: BTreeMap<String, String>,
    /// Camera preprocessing.
    #[serde(default)]
    pub image: ImageConfig,
    /// Prompt layout.
    #[serde(default)]
    pub prompt: PromptConfig,
    /// Robot-side safety settings (the stale-slow grace, per action group limits).
    #[serde(default)]
    pub safety: SafetySection,
    /// How the action head was fine-tuned and how it is deployed by default.
    #[serde(default)]
    pub policy: PolicySection,
}

/// How a deployment runs the action head: the rows of the paper's real-robot table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum DeployKind {
    /// πR² with the slow channel on its own worker (the cached backbone features carry
    /// their age `d_vis`); one call costs one NFE.
    #[serde(rename = "pir2_async")]
    PiR2Async,
    /// πR² without async: each call runs the backbone first, so its time counts in `d`.
    #[serde(rename = "pir2_sync")]
    PiR2Sync,
    /// Standard flow, synchronous: the robot holds while a call runs, then executes `h`
    /// actions of the new chunk.
    #[serde(rename = "sync_flow")]
    SyncFlow,
    /// Standard flow, asynchronous: the next chunk is computed while the current one runs
    /// and swapped in when ready (optionally with ACT temporal ensembling).
    #[serde(rename = "naive_async")]
    NaiveAsync,
    /// Train-time RTC: the in-flight actions are the clean front of the next chunk.
    #[serde(rename = "rtc")]
    Rtc,
}

impl DeployKind {
    /// Every kind, in the paper's table order.
    pub const ALL: [DeployKind; 5] = [
        DeployKind::SyncFlow,
        DeployKind::NaiveAsync,
        DeployKind::Rtc,
        DeployKind::PiR2Sync,
        DeployKind::PiR2Async,
    ];

    /// The name used in `embodiment.toml` and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            DeployKind::PiR2Async => "pir2_async",
            DeployKind::PiR2Sync => "pir2_sync",
            DeployKind::SyncFlow => "sync_flow",
            DeployKind::NaiveAsync => "naive_async",
            DeployKind::Rtc => "rtc",
        }
    }

    /// Parse [`DeployKind::name`].
    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == s)
    }

    /// Whether the slow channel runs on its own worker (only πR² async).
    pub fn async_slow(self) -> bool {
        self == DeployKind::PiR2Async
    }
}

/// The `[policy]` table of an embodiment: what the action head was fine-tuned as (the
/// checkpoint's declaration) and the deployment `pir2 run` uses unless told otherwise. A
/// deployment the head was not trained for is refused ([`PolicySection::mode`]).
///
/// ```toml
/// [policy]
/// trained = "pi_r2"      # pi_r2 | pi_r2_hidden | pi_r2_full | rtc | flow
/// nfe = 2                # πR²: NFEs per action (n)
/// flow_steps = 4         # flow and train-time RTC: Euler steps K per chunk
/// mode = "pir2_async"    # pir2_async | pir2_sync | sync_flow | naive_async | rtc
/// h = 10                 # sync flow: actions executed per chunk
/// # ensemble = 0.1       # naive async: ACT temporal ensembling decay (absent: plain swap)
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PolicySection {
    /// What the action head was fine-tuned as.
    pub trained: pir2_runtime::Policy,
    /// πR² NFEs per action `n` (policies `pi_r2`, `pi_r2_hidden`; `pi_r2_full` uses the
    /// full ramp).
    pub nfe: usize,
    /// Euler steps `K` per chunk of the flow baselines (the paper's robot table: 4).
    pub flow_steps: usize,
    /// The deployment used unless a run overrides it.
    pub mode: DeployKind,
    /// Sync flow: actions executed per chunk (the paper's robot table: 10).
    pub h: usize,
    /// Naive async: ACT temporal ensembling decay `m` (`None`: plain swap).
    pub ensemble: Option<f32>,
}

impl Default for PolicySection {
    fn default() -> Self {
        PolicySection {
            trained: pir2_runtime::Policy::PiR2,
            nfe: 2,
            flow_steps: 4,
            mode: DeployKind::PiR2Async,
            h: 10,
            ensemble: None,
        }
    }
}

/// Overrides of a [`PolicySection`] for one run (`None`: the section's value).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ModeOverrides {
    /// The deployment.
    pub mode: Option<DeployKind>,
    /// πR² NFEs per action; must equal the trained `n` (a head trained for one `n` is run
    /// with that `n`).
    pub nfe: Option<usize>,
    /// Euler steps `K` of the flow baselines.
    pub flow_steps: Option<usize>,
    /// Sync flow's `h`.
    pub h: Option<usize>,
    /// Naive async: temporal ensembling decay (`Some(None)`: plain swap).
    pub ensemble: Option<Option<f32>>,
}

impl PolicySection {
    /// The policies a deployment kind can run: πR² kinds need a πR² head, the flow kinds a
    /// standard-flow head, RTC a train-time-RTC head.
    pub fn trained_for(kind: DeployKind) -> &'static [pir2_runtime::Policy] {
        use pir2_runtime::Policy as P;
        match kind {
            DeployKind::PiR2Async | DeployKind::PiR2Sync => {
                &[P::PiR2, P::PiR2Hidden, P::PiR2Full, P::PiR2ZeroDelay]
            }
            DeployKind::SyncFlow | DeployKind::NaiveAsync => &[P::Flow],
            DeployKind::Rtc => &[P::Rtc],
        }
    }

    /// The runtime mode of this section with `o` applied. Errors name both sides of a
    /// mismatch: a deployment the head was not trained for, an `n` other than the trained
    /// one, or a zero `K`, `h`, `n` or an ensembling decay outside `(0, 1]`.
    pub fn mode(&self, o: &ModeOverrides) -> Result<pir2_runtime::Mode> {
        use pir2_runtime::{Mode, Policy as P};
        use pir2_schedule::{Alignment, FrontMode};
        let kind = o.mode.unwrap_or(self.mode);
        let allowed = Self::trained_for(kind);
        if !allowed.contains(&self.trained) {
            let names: Vec<String> = allowed.iter().map(|p| policy_name(*p)).collect();
            return Err(Gr00tError::Config(format!(
                "mode {} needs an action head trained as {}, but the checkpoint declares \
                 [policy] trained = \"{}\"",
                kind.name(),
                names.join(" or "),
                policy_name(self.trained)
            )));
        }
        let nfe = o.nfe.unwrap_or(self.nfe);
        if o.nfe.is_some_and(|n| n != self.nfe) {
            return Err(Gr00tError::Config(format!(
                "--nfe {nfe}: the checkpoint declares [policy] nfe = {} (a πR² head runs with \
                 the n it was trained for)",
                self.nfe
            )));
        }
        let steps = o.flow_steps.unwrap_or(self.flow_steps);
        let h = o.h.unwrap_or(self.h);
        let ensemble = o.ensemble.unwrap_or(self.ensemble);
        let positive = |what: &str, v: usize| {
            if v == 0 {
                Err(Gr00tError::Config(format!("[policy] {what} must be >= 1")))
            } else {
                Ok(v)
            }
        };
        let pir2 = |sync: bool| -> Result<Mode> {
            let (nfe, alignment, front) = match self.trained {
                P::PiR2Full => (None, Alignment::Paper, FrontMode::Visible),
                P::PiR2Hidden => (
                    Some(positive("nfe", nfe)?),
                    Alignment::Fresh,
                    FrontMode::Hidden,
                ),
                _ => (
                    Some(positive("nfe", nfe)?),
                    Alignment::Fresh,
                    FrontMode::Visible,
                ),
            };
            Ok(if sync {
                Mode::PiR2Sync {
                    nfe,
                    alignment,
                    front,
                }
            } else {
                Mode::PiR2Async {
                    nfe,
                    alignment,
                    front,
                }
            })
        };
        Ok(match kind {
            DeployKind::PiR2Async => pir2(false)?,
            DeployKind::PiR2Sync => pir2(true)?,
            DeployKind::SyncFlow => Mode::SyncFlow {
                steps: positive("flow_steps", steps)?,
                h: positive("h", h)?,
            },
            DeployKind::NaiveAsync => {
                if let Some(m) = ensemble {
                    if !(m > 0.0 && m <= 1.0) {
                        return Err(Gr00tError::Config(format!(
                            "[policy] ensemble = {m}: the decay must be in (0, 1]"
                        )));
                    }
                }
                Mode::NaiveAsync {
                    steps: positive("flow_steps", steps)?,
                    ensemble,
                }
            }
            DeployKind::Rtc => Mode::TrainTimeRtc {
                steps: positive("flow_steps", steps)?,
            },
        })
    }
}

/// The `embodiment.toml` spelling of a policy.
pub fn policy_name(p: pir2_runtime::Policy) -> String {
    serde_json::to_value(p)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_else(|| format!("{p:?}"))
}

/// Default stale-slow grace, ms (see [`SafetySection::slow_grace_ms`]).
pub const DEFAULT_SLOW_GRACE_MS: f64 = 200.0;

/// Bound on every size an embodiment file declares (groups, values per group, horizon,
/// `n_obs`, image side, prompt tokens): a larger one is refused by name instead of being
/// allocated.
pub const MAX_SIZE: usize = 8192;

fn default_slow_grace_ms() -> f64 {
    DEFAULT_SLOW_GRACE_MS
}

/// The `[safety]` table of an embodiment: what the robot side enforces around the policy.
///
/// ```toml
/// [safety]
/// slow_grace_ms = 200
/// [safety.limits.hand_joints]
/// lower = [-0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
/// upper = [1.8, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6, 1.6]
/// max_velocity = 4.0     # rad/s
/// max_accel = 80.0       # rad/s²
/// tracking_error = 0.8   # rad, |target − measured|
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SafetySection {
    /// Stale-slow stop: a call whose slow features are older than `d_vis_max` ticks (plus
    /// half a tick) for longer than this stops the robot, ms.
    #[serde(default = "default_slow_grace_ms")]
    pub slow_grace_ms: f64,
    /// Per action group (keyed by the group's name), limits overriding the robot's defaults.
    #[serde(default)]
    pub limits: BTreeMap<String, GroupLimits>,
}

impl Default for SafetySection {
    fn default() -> Self {
        SafetySection {
            slow_grace_ms: DEFAULT_SLOW_GRACE_MS,
            limits: BTreeMap::new(),
        }
    }
}

/// Safety limits of one action group; absent fields keep the robot's defaults.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GroupLimits {
    /// Lower joint limits, rad (one per joint of the group).
    pub lower: Option<Vec<f32>>,
    /// Upper joint limits, rad.
    pub upper: Option<Vec<f32>>,
    /// Largest joint speed, rad/s.
    pub max_velocity: Option<f32>,
    /// Largest change of joint speed, rad/s².
    pub max_accel: Option<f32>,
    /// Largest `|target − measured position|`, rad.
    pub tracking_error: Option<f32>,
}

/// [`GroupLimits`] flattened over the action vector: `None` keeps the robot's default.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ActionLimits {
    /// Lower joint limit per action dimension.
    pub lower: Vec<Option<f32>>,
    /// Upper joint limit per action dimension.
    pub upper: Vec<Option<f32>>,
    /// Speed limit per action dimension, rad/s.
    pub max_velocity: Vec<Option<f32>>,
    /// Acceleration limit per action dimension, rad/s².
    pub max_accel: Vec<Option<f32>>,
    /// Tracking-error bound per action dimension, rad.
    pub tracking_error: Vec<Option<f32>>,
}

impl EmbodimentConfig {
    /// The paper's xArm6 + XHand setup (docs/method.md §4).
    pub fn xarm6_xhand() -> Self {
        EmbodimentConfig {
            name: "gr00t-xarm-xhand".to_string(),
            embodiment_tag: "new_embodiment".to_string(),
            embodiment_id: 10,
            control_hz: 25.0,
            horizon: 50,
            d_max: 5,
            d_vis_max: 5,
            n_obs: 1,
            num_timestep_buckets: 1000,
            state_token_timestep: None,
            state: vec![
                Group::new("arm_joints", 6),
                Group::new("hand_joints", 12),
                Group::new("hand_torques", 12),
                Group::new("fingertip_forces", 15),
            ],
            action: vec![Group::new("arm_joints", 6), Group::new("hand_joints", 12)],
            tasks: PAPER_TASKS
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect(),
            image: ImageConfig::default(),
            prompt: PromptConfig::default(),
            safety: SafetySection::default(),
            policy: PolicySection::default(),
        }
    }

    /// The stale-slow grace in nanoseconds.
    pub fn slow_grace_ns(&self) -> u64 {
        (self.safety.slow_grace_ms * 1e6).round() as u64
    }

    /// The stale-slow grace.
    pub fn slow_grace(&self) -> std::time::Duration {
        std::time::Duration::from_nanos(self.slow_grace_ns())
    }

    /// The `[safety.limits]` over the action vector (see [`ActionLimits`]).
    pub fn action_limits(&self) -> ActionLimits {
        let n = self.action_dim();
        let mut out = ActionLimits {
            lower: vec![None; n],
            upper: vec![None; n],
            max_velocity: vec![None; n],
            max_accel: vec![None; n],
            tracking_error: vec![None; n],
        };
        let mut at = 0;
        for g in &self.action {
            if let Some(l) = self.safety.limits.get(&g.name) {
                for j in 0..g.dim {
                    out.lower[at + j] = l.lower.as_ref().map(|v| v[j]);
                    out.upper[at + j] = l.upper.as_ref().map(|v| v[j]);
                    out.max_velocity[at + j] = l.max_velocity;
                    out.max_accel[at + j] = l.max_accel;
                    out.tracking_error[at + j] = l.tracking_error;
                }
            }
            at += g.dim;
        }
        out
    }

    /// Check the action groups against what a robot takes, by name, width and order (a
    /// checkpoint trained on `[hand, arm]` must not drive an `[arm, hand]` robot even though
    /// the widths add up).
    pub fn check_action_groups(&self, robot: &[(&str, usize)]) -> Result<()> {
        let ours: Vec<(&str, usize)> = self
            .action
            .iter()
            .map(|g| (g.name.as_str(), g.dim))
            .collect();
        if ours != robot {
            return Err(Gr00tError::Config(format!(
                "the checkpoint's action groups {ours:?} do not match the robot's {robot:?} \
                 (names, widths and order must agree)"
            )));
        }
        Ok(())
    }

    /// Read a TOML (`.toml`) or JSON (anything else) file and validate it.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Gr00tError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let parse = |message: String| Gr00tError::Parse {
            path: path.to_path_buf(),
            message,
        };
        let cfg: EmbodimentConfig = if path.extension().is_some_and(|e| e == "toml") {
            toml::from_str(&text).map_err(|e| parse(e.to_string()))?
        } else {
            serde_json::from_str(&text).map_err(|e| parse(e.to_string()))?
        };
        cfg.validate()?;
        Ok(cfg)
    }

    /// TOML text of this configuration.
    pub fn to_toml(&self) -> Result<String> {
        toml::to_string(self).map_err(|e| Gr00tError::Config(e.to_string()))
    }

    /// Proprioception width (sum of the state groups).
    pub fn state_dim(&self) -> usize {
        self.state.iter().map(|g| g.dim).sum()
    }

    /// Action width (sum of the action groups).
    pub fn action_dim(&self) -> usize {
        self.action.iter().map(|g| g.dim).sum()
    }

    /// Control period in nanoseconds.
    pub fn period_ns(&self) -> u64 {
        (1e9 / self.control_hz).round() as u64
    }

    /// The state token's timestep.
    pub fn state_timestep(&self) -> i64 {
        self.state_token_timestep
            .unwrap_or(self.num_timestep_buckets - 1)
    }

    /// Resolve a task: a key of [`tasks`](Self::tasks) or a prompt given verbatim.
    pub fn prompt_for<'a>(&'a self, task: &'a str) -> &'a str {
        self.tasks.get(task).map(String::as_str).unwrap_or(task)
    }

    /// Check sizes and limits; the message names the field.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Gr00tError::Config(m));
        if !(self.control_hz.is_finite() && self.control_hz > 0.0) {
            return bad(format!("control_hz must be > 0, got {}", self.control_hz));
        }
        if self.horizon == 0 || self.n_obs == 0 {
            return bad(format!(
                "horizon ({}) and n_obs ({}) must be positive",
                self.horizon, self.n_obs
            ));
        }
        if self.d_max == 0 || self.d_max >= self.horizon {
            return bad(format!(
                "d_max must be in [1, H), got {} with H = {}",
                self.d_max, self.horizon
            ));
        }
        if self.num_timestep_buckets < 1 {
            return bad(format!(
                "num_timestep_buckets must be >= 1, got {}",
                self.num_timestep_buckets
            ));
        }
        let st = self.state_timestep();
        if !(0..self.num_timestep_buckets).contains(&st) {
            return bad(format!(
                "state_token_timestep {st} outside [0, {})",
                self.num_timestep_buckets
            ));
        }
        for (what, groups) in [("state", &self.state), ("action", &self.action)] {
            if groups.is_empty() {
                return bad(format!("no {what} groups"));
            }
            for g in groups.iter() {
                if g.dim == 0 {
                    return bad(format!("{what} group `{}` has dim 0", g.name));
                }
            }
            if groups.len() > MAX_SIZE || groups.iter().any(|g| g.dim > MAX_SIZE) {
                return bad(format!(
                    "{what} groups: at most {MAX_SIZE} groups of at most {MAX_SIZE} values"
                ));
            }
        }
        for (what, v) in [
            ("horizon", self.horizon),
            ("n_obs", self.n_obs),
            ("image.resize", self.image.resize),
            ("prompt.text_tokens", self.prompt.text_tokens),
        ] {
            if v > MAX_SIZE {
                return bad(format!("{what} = {v} is above the limit {MAX_SIZE}"));
            }
        }
        match self.image.pipeline {
            ImagePipeline::ResizeCrop => {
                if self.image.crop == 0 || self.image.crop > self.image.resize {
                    return bad(format!(
                        "image crop {} must be in [1, resize = {}]",
                        self.image.crop, self.image.resize
                    ));
                }
            }
            ImagePipeline::Gr00tN17 => {
                if self.image.shortest_edge == 0 || self.image.shortest_edge > MAX_SIZE {
                    return bad(format!(
                        "image.shortest_edge = {} must be in [1, {MAX_SIZE}]",
                        self.image.shortest_edge
                    ));
                }
                let f = self.image.crop_fraction;
                if !(f > 0.0 && f <= 1.0) {
                    return bad(format!("image.crop_fraction = {f} must be in (0, 1]"));
                }
            }
        }
        if self.image.std.iter().any(|s| *s <= 0.0) {
            return bad(format!("image std must be > 0: {:?}", self.image.std));
        }
        if self.prompt.text_tokens == 0 {
            return bad("prompt.text_tokens must be positive".to_string());
        }
        self.prompt
            .chat
            .tokens_per_image(self.prompt.image_tokens)?;
        let sg = self.safety.slow_grace_ms;
        if !(sg.is_finite() && sg > 0.0) {
            return bad(format!("safety.slow_grace_ms must be > 0, got {sg}"));
        }
        for (name, l) in &self.safety.limits {
            let Some(g) = self.action.iter().find(|g| &g.name == name) else {
                return bad(format!(
                    "safety.limits.{name}: no action group `{name}` (groups: {:?})",
                    self.action.iter().map(|g| &g.name).collect::<Vec<_>>()
                ));
            };
            for (what, v) in [("lower", &l.lower), ("upper", &l.upper)] {
                if let Some(v) = v {
                    if v.len() != g.dim {
                        return bad(format!(
                            "safety.limits.{name}.{what} has {} values, the group has dim {}",
                            v.len(),
                            g.dim
                        ));
                    }
                    if v.iter().any(|x| !x.is_finite()) {
                        return bad(format!("safety.limits.{name}.{what} must be finite"));
                    }
                }
            }
            if let (Some(lo), Some(hi)) = (&l.lower, &l.upper) {
                if let Some(j) = (0..g.dim).find(|&j| lo[j] > hi[j]) {
                    return bad(format!(
                        "safety.limits.{name}: joint {j} lower {} > upper {}",
                        lo[j], hi[j]
                    ));
                }
            }
            for (what, v) in [
                ("max_velocity", l.max_velocity),
                ("max_accel", l.max_accel),
                ("tracking_error", l.tracking_error),
            ] {
                if let Some(v) = v {
                    if !(v.is_finite() && v > 0.0) {
                        return bad(format!("safety.limits.{name}.{what} must be > 0, got {v}"));
                    }
                }
            }
        }
        Ok(())
    }
}

/// Per-dimension affine normalisation of the state and the action (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Normalizer {
    /// `norm(x) = (x − state_offset) · state_inv_scale`, per state dimension.
    state_offset: Vec<f32>,
    state_inv_scale: Vec<f32>,
    /// Clip the normalised state to `[-1, 1]` (min/max and percentile groups).
    state_clip: Vec<bool>,
    /// `raw = scale · x + offset`, per action dimension.
    action_scale: Vec<f32>,
    action_offset: Vec<f32>,
}

type StatsFile = BTreeMap<String, BTreeMap<String, BTreeMap<String, BTreeMap<String, Vec<f64>>>>>;

impl Normalizer {
    /// The identity (no statistics).
    pub fn identity(state_dim: usize, action_dim: usize) -> Self {
        Normalizer {
            state_offset: vec![0.0; state_dim],
            state_inv_scale: vec![1.0; state_dim],
            state_clip: vec![false; state_dim],
            action_scale: vec![1.0; action_dim],
            action_offset: vec![0.0; action_dim],
        }
    }

    /// Load GR00T's `statistics.json` for `cfg` (every group and statistic its norm needs
    /// must be present with the group's width; the error names the missing key).
    pub fn load(path: &Path, cfg: &EmbodimentConfig) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Gr00tError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let stats: StatsFile = serde_json::from_str(&text).map_err(|e| Gr00tError::Parse {
            path: path.to_path_buf(),
            message: format!(
                "expected {{embodiment: {{modality: {{group: {{stat: [numbers]}}}}}}}}: {e}"
            ),
        })?;
        Self::from_stats(&stats, path, cfg)
    }

    fn from_stats(stats: &StatsFile, path: &Path, cfg: &EmbodimentConfig) -> Result<Self> {
        let err =
            |modality: &str, group: &str, stat: &str, problem: String| Gr00tError::Statistics {
                path: path.to_path_buf(),
                key: format!("{}.{modality}.{group}.{stat}", cfg.embodiment_tag),
                problem,
            };
        let emb = stats.get(&cfg.embodiment_tag).ok_or_else(|| {
            err(
                "*",
                "*",
                "*",
                format!(
                    "is missing: no embodiment `{}` (found {:?})",
                    cfg.embodiment_tag,
                    stats.keys().collect::<Vec<_>>()
                ),
            )
        })?;
        // (offset, scale) per dim: norm = (x − offset)/scale; raw = scale·norm + offset.
        let affine = |modality: &str,
                      groups: &[Group]|
         -> Result<(Vec<f32>, Vec<f32>, Vec<bool>)> {
            let (mut off, mut scale, mut clip) = (Vec::new(), Vec::new(), Vec::new());
            for g in groups {
                let get = |stat: &str| -> Result<Vec<f64>> {
                    let v = emb
                        .get(modality)
                        .and_then(|m| m.get(&g.name))
                        .and_then(|s| s.get(stat))
                        .ok_or_else(|| err(modality, &g.name, stat, "is missing".to_string()))?;
                    if v.len() != g.dim {
                        return Err(err(
                            modality,
                            &g.name,
                            stat,
                            format!("has {} values, the group has dim {}", v.len(), g.dim),
                        ));
                    }
                    if v.iter().any(|x| !x.is_finite()) {
                        return Err(err(modality, &g.name, stat, "is not finite".to_string()));
                    }
                    Ok(v.clone())
                };
                match g.norm {
                    Norm::MinMax | Norm::Q01Q99 => {
                        let (lo, hi) = if g.norm == Norm::MinMax {
                            ("min", "max")
                        } else {
                            ("q01", "q99")
                        };
                        let (lo, hi) = (get(lo)?, get(hi)?);
                        for (l, h) in lo.iter().zip(&hi) {
                            let range = (h - l).max(1e-8);
                            off.push((l + range / 2.0) as f32);
                            scale.push((range / 2.0) as f32);
                            clip.push(true);
                        }
                    }
                    Norm::MeanStd => {
                        let (mean, std) = (get("mean")?, get("std")?);
                        for (m, s) in mean.iter().zip(&std) {
                            off.push(*m as f32);
                            scale.push(s.max(1e-8) as f32);
                            clip.push(false);
                        }
                    }
                    Norm::None => {
                        for _ in 0..g.dim {
                            off.push(0.0);
                            scale.push(1.0);
                            clip.push(false);
                        }
                    }
                }
            }
            Ok((off, scale, clip))
        };
        let (so, ss, sc) = affine("state", &cfg.state)?;
        let (ao, ascale, _) = affine("action", &cfg.action)?;
        Ok(Normalizer {
            state_offset: so,
            state_inv_scale: ss.iter().map(|s| 1.0 / s).collect(),
            state_clip: sc,
            action_scale: ascale,
            action_offset: ao,
        })
    }

    /// State width.
    pub fn state_dim(&self) -> usize {
        self.state_offset.len()
    }

    /// Normalise one raw state vector into `out` (same length).
    pub fn normalize_state(&self, raw: &[f32], out: &mut [f32]) {
        for i in 0..raw.len().min(out.len()).min(self.state_offset.len()) {
            let v = (raw[i] - self.state_offset[i]) * self.state_inv_scale[i];
            out[i] = if self.state_clip[i] {
                v.clamp(-1.0, 1.0)
            } else {
                v
            };
        }
    }

    /// Denormalise one action vector in place.
    pub fn denormalize_action(&self, a: &mut [f32]) {
        for (i, x) in a.iter_mut().enumerate() {
            *x = self.action_scale[i] * *x + self.action_offset[i];
        }
    }

    /// The runtime's output map that turns model actions into absolute joint targets.
    pub fn action_output_map(&self) -> pir2_runtime::OutputMap {
        pir2_runtime::OutputMap {
            scale: self.action_scale.clone(),
            offset: self.action_offset.clone(),
        }
    }
}

/// Read the embodiment slot from GR00T's `embodiment_id.json` (`{tag: id}`), if the file exists.
pub fn read_embodiment_id(path: &Path, tag: &str) -> Result<Option<i64>> {
    if !path.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(path).map_err(|source| Gr00tError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let map: BTreeMap<String, i64> =
        serde_json::from_str(&text).map_err(|e| Gr00tError::Parse {
            path: path.to_path_buf(),
            message: format!("expected {{tag: id}}: {e}"),
        })?;
    Ok(map.get(tag).copied())
}

/// The files of a checkpoint directory (names relative to it; see `docs/gr00t-contract.md`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CheckpointFiles {
    /// Embodiment configuration (optional: the built-in xArm6 + XHand is used without it).
    pub embodiment: PathBuf,
    /// GR00T normalisation statistics.
    pub statistics: PathBuf,
    /// GR00T embodiment slots (optional).
    pub embodiment_id: PathBuf,
    /// State encoder ONNX.
    pub state_encoder: PathBuf,
    /// Action encoder ONNX.
    pub action_encoder: PathBuf,
    /// DiT ONNX.
    pub dit: PathBuf,
    /// Action decoder ONNX.
    pub action_decoder: PathBuf,
    /// Backbone (ViT + LLM) ONNX.
    pub backbone: PathBuf,
    /// VL self-attention ONNX (optional).
    pub vl_self_attention: PathBuf,
    /// pir2 side weights: delay table, position embedding, `vlln`.
    pub weights: PathBuf,
    /// The VLM's Hugging Face tokenizer (used when present).
    pub tokenizer: PathBuf,
    /// Tokenizer vocabulary of older pir2 checkpoints (used without `tokenizer.json`).
    pub vocab: PathBuf,
}

impl CheckpointFiles {
    /// The default layout under `dir`.
    pub fn in_dir(dir: &Path) -> Self {
        let onnx = dir.join("onnx");
        CheckpointFiles {
            embodiment: dir.join("embodiment.toml"),
            statistics: dir.join("statistics.json"),
            embodiment_id: dir.join("embodiment_id.json"),
            state_encoder: onnx.join("state_encoder.onnx"),
            action_encoder: onnx.join("action_encoder.onnx"),
            dit: onnx.join("dit.onnx"),
            action_decoder: onnx.join("action_decoder.onnx"),
            backbone: onnx.join("backbone.onnx"),
            vl_self_attention: onnx.join("vl_self_attention.onnx"),
            weights: dir.join("pir2_gr00t.safetensors"),
            tokenizer: dir.join("tokenizer.json"),
            vocab: dir.join("vocab.txt"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xarm6_xhand_matches_the_paper() {
        let c = EmbodimentConfig::xarm6_xhand();
        c.validate().unwrap();
        assert_eq!(c.state_dim(), 45);
        assert_eq!(c.action_dim(), 18);
        assert_eq!((c.horizon, c.d_max, c.d_vis_max), (50, 5, 5));
        assert_eq!(c.period_ns(), 40_000_000);
        assert_eq!(c.prompt_for("catch_book"), "catch the book");
        assert_eq!(c.prompt_for("catch the book"), "catch the book");
        assert_eq!(c.tasks.len(), 4);
        let back: EmbodimentConfig = toml::from_str(&c.to_toml().unwrap()).unwrap();
        assert_eq!(back, c);
    }

    /// `[safety]` in embodiment.toml: grace and per-group limits are read, flattened over
    /// the action vector, and bad values are one error naming the field (before: hand limits
    /// and tracking bounds were placeholders in code, not configurable).
    #[test]
    fn safety_section_is_parsed_flattened_and_checked() {
        let text = "slow_grace_ms = 150.0\n\n[limits.hand_joints]\n\
                    lower = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.2]\n\
                    upper = [1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.0]\n\
                    max_velocity = 3.0\ntracking_error = 0.4\n";
        let mut c = EmbodimentConfig::xarm6_xhand();
        c.safety = toml::from_str(text).unwrap();
        // The whole file round-trips with the table in it.
        let c: EmbodimentConfig = toml::from_str(&c.to_toml().unwrap()).unwrap();
        c.validate().unwrap();
        assert_eq!(c.slow_grace_ns(), 150_000_000);
        let l = c.action_limits();
        assert_eq!(l.lower.len(), 18);
        assert_eq!(
            (l.lower[0], l.lower[6], l.lower[17]),
            (None, Some(0.0), Some(-0.2))
        );
        assert_eq!(
            (l.upper[17], l.max_velocity[6], l.max_velocity[5]),
            (Some(1.0), Some(3.0), None)
        );
        assert_eq!((l.tracking_error[10], l.max_accel[10]), (Some(0.4), None));
        // Defaults when the table is absent.
        let d = EmbodimentConfig::xarm6_xhand();
        assert_eq!(d.slow_grace_ns(), 200_000_000);
        assert!(d.action_limits().lower.iter().all(Option::is_none));
        // Errors name the field.
        let bad = |edit: &dyn Fn(&mut EmbodimentConfig), want: &str| {
            let mut c = EmbodimentConfig::xarm6_xhand();
            edit(&mut c);
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        };
        bad(&|c| c.safety.slow_grace_ms = 0.0, "slow_grace_ms");
        bad(
            &|c| {
                c.safety
                    .limits
                    .insert("wrist".into(), GroupLimits::default());
            },
            "safety.limits.wrist",
        );
        bad(
            &|c| {
                c.safety.limits.insert(
                    "hand_joints".into(),
                    GroupLimits {
                        lower: Some(vec![0.0; 5]),
                        ..Default::default()
                    },
                );
            },
            "hand_joints.lower has 5 values",
        );
        bad(
            &|c| {
                c.safety.limits.insert(
                    "arm_joints".into(),
                    GroupLimits {
                        max_velocity: Some(-1.0),
                        ..Default::default()
                    },
                );
            },
            "arm_joints.max_velocity",
        );
        assert!(toml::from_str::<SafetySection>("grace = 1").is_err());
    }

    /// The action groups must be the robot's by name and order, not only by total width.
    #[test]
    fn action_groups_are_checked_by_name_and_order() {
        let robot = [("arm_joints", 6), ("hand_joints", 12)];
        let c = EmbodimentConfig::xarm6_xhand();
        c.check_action_groups(&robot).unwrap();
        let mut swapped = c.clone();
        swapped.action.reverse();
        assert_eq!(swapped.action_dim(), 18);
        let e = swapped.check_action_groups(&robot).unwrap_err().to_string();
        assert!(e.contains("do not match"), "{e}");
        let mut renamed = c;
        renamed.action[1].name = "gripper".into();
        assert!(renamed.check_action_groups(&robot).is_err());
    }

    fn stats_json(drop: Option<&str>) -> String {
        let c = EmbodimentConfig::xarm6_xhand();
        let mut emb = serde_json::Map::new();
        for (m, groups) in [("state", &c.state), ("action", &c.action)] {
            let mut gm = serde_json::Map::new();
            for g in groups.iter() {
                let mut s = serde_json::Map::new();
                for (k, v) in [("min", -2.0), ("max", 4.0), ("mean", 1.0), ("std", 2.0)] {
                    if drop == Some(&format!("{m}.{}.{k}", g.name)) {
                        continue;
                    }
                    s.insert(k.into(), serde_json::json!(vec![v; g.dim]));
                }
                gm.insert(g.name.clone(), s.into());
            }
            emb.insert(m.into(), gm.into());
        }
        serde_json::json!({ "new_embodiment": emb }).to_string()
    }

    #[test]
    fn min_max_maps_to_unit_interval_and_back() {
        let dir = std::env::temp_dir().join(format!("pir2-gr00t-stats-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("statistics.json");
        std::fs::write(&p, stats_json(None)).unwrap();
        let c = EmbodimentConfig::xarm6_xhand();
        let n = Normalizer::load(&p, &c).unwrap();
        let mut out = vec![0.0; 45];
        n.normalize_state(&[-2.0; 45], &mut out);
        assert!(out.iter().all(|x| (*x + 1.0).abs() < 1e-6), "{out:?}");
        n.normalize_state(&[1.0; 45], &mut out);
        assert!(out.iter().all(|x| x.abs() < 1e-6));
        n.normalize_state(&[100.0; 45], &mut out);
        assert!(out.iter().all(|x| *x == 1.0), "clipped");
        let mut a = vec![1.0; 18];
        n.denormalize_action(&mut a);
        assert!(a.iter().all(|x| (*x - 4.0).abs() < 1e-6));

        std::fs::write(&p, stats_json(Some("state.hand_torques.max"))).unwrap();
        let e = Normalizer::load(&p, &c).unwrap_err().to_string();
        assert!(
            e.contains("new_embodiment.state.hand_torques.max") && e.contains("missing"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn every_row_of_the_robot_table_resolves_from_the_policy_table() {
        use pir2_runtime::{Mode, Policy};
        use pir2_schedule::{Alignment, FrontMode};
        // No [policy] table: a πR² head (n = 2) in πR² async, as before the table existed.
        let c = EmbodimentConfig::xarm6_xhand();
        assert_eq!(
            c.policy.mode(&ModeOverrides::default()).unwrap(),
            Mode::PiR2Async {
                nfe: Some(2),
                alignment: Alignment::Fresh,
                front: FrontMode::Visible
            }
        );
        let section = |text: &str| -> PolicySection { toml::from_str(text).unwrap() };
        let flow = section("trained = \"flow\"\nmode = \"sync_flow\"\nflow_steps = 4\nh = 10");
        let over = |mode: DeployKind| ModeOverrides {
            mode: Some(mode),
            ..Default::default()
        };
        assert_eq!(
            flow.mode(&ModeOverrides::default()).unwrap(),
            Mode::SyncFlow { steps: 4, h: 10 }
        );
        assert_eq!(
            flow.mode(&ModeOverrides {
                ensemble: Some(Some(0.1)),
                ..over(DeployKind::NaiveAsync)
            })
            .unwrap(),
            Mode::NaiveAsync {
                steps: 4,
                ensemble: Some(0.1)
            }
        );
        let rtc = section("trained = \"rtc\"\nmode = \"rtc\"\nflow_steps = 4");
        assert_eq!(
            rtc.mode(&ModeOverrides::default()).unwrap(),
            Mode::TrainTimeRtc { steps: 4 }
        );
        let full = section("trained = \"pi_r2_full\"");
        assert_eq!(
            full.mode(&over(DeployKind::PiR2Sync)).unwrap(),
            Mode::PiR2Sync {
                nfe: None,
                alignment: Alignment::Paper,
                front: FrontMode::Visible
            }
        );
        let hidden = section("trained = \"pi_r2_hidden\"\nnfe = 3");
        assert_eq!(
            hidden.mode(&ModeOverrides::default()).unwrap(),
            Mode::PiR2Async {
                nfe: Some(3),
                alignment: Alignment::Fresh,
                front: FrontMode::Hidden
            }
        );
        // Mismatches name both sides.
        let e = c
            .policy
            .mode(&over(DeployKind::Rtc))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("mode rtc") && e.contains("trained = \"pi_r2\""),
            "{e}"
        );
        let e = flow
            .mode(&over(DeployKind::PiR2Async))
            .unwrap_err()
            .to_string();
        assert!(e.contains("pir2_async") && e.contains("\"flow\""), "{e}");
        let e = c
            .policy
            .mode(&ModeOverrides {
                nfe: Some(4),
                ..Default::default()
            })
            .unwrap_err()
            .to_string();
        assert!(e.contains("--nfe 4") && e.contains("nfe = 2"), "{e}");
        let e = flow
            .mode(&ModeOverrides {
                h: Some(0),
                ..Default::default()
            })
            .unwrap_err()
            .to_string();
        assert!(e.contains("h must be >= 1"), "{e}");
        let e = flow
            .mode(&ModeOverrides {
                ensemble: Some(Some(1.5)),
                ..over(DeployKind::NaiveAsync)
            })
            .unwrap_err()
            .to_string();
        assert!(e.contains("ensemble = 1.5"), "{e}");
        // Unknown modes and keys are refused by the TOML reader.
        assert!(toml::from_str::<PolicySection>("mode = \"fast\"").is_err());
        assert!(toml::from_str::<PolicySection>("steps = 4").is_err());
        assert_eq!(policy_name(Policy::PiR2Hidden), "pi_r2_hidden");
        for k in DeployKind::ALL {
            assert_eq!(DeployKind::parse(k.name()), Some(k));
        }
    }
}
