//! The embodiment configuration (serde TOML/JSON) and GR00T's normalisation statistics.
//!
//! One file on purpose: the embodiment TOML schema and its validation (every cross-field check
//! names the field) must be read together; the statistics and the policy section live in
//! `config/`.
//!
//! [`EmbodimentConfig::xarm6_xhand`] is the paper's real-robot setup: 45-d proprioception
//! (6 arm joints, 12 hand joints, 12 hand torques, 15 fingertip forces), 18-d absolute joint
//! targets, `H = 50` at 25 Hz, `d_max = d_vis_max = 5`, and the four task prompts of the
//! paper's task-prompt table.
//!
//! Statistics come from the checkpoint's `statistics.json` in GR00T's layout
//! `{embodiment_tag: {"state"|"action": {group: {"min","max","mean","std","q01","q99": [..]}}}}`.
//! Per group, [`Norm`] picks the map, as GR00T's `StateActionProcessor` (with its default
//! `clip_outliers`) applies it:
//! - `min_max`: `2·(x − min)/(max − min) − 1`, clipped to `[-1, 1]`; a dimension whose
//!   `max` and `min` are equal within `1e-8 + 1e-5·|min|` (numpy's `isclose`) maps to 0.
//!   Back: `(clip(x, −1, 1) + 1)/2 · (max − min) + min`;
//! - `q01_q99`: the same with `q01`/`q99` in place of `min`/`max`;
//! - `mean_std`: `(x − mean)/std`, back `x·std + mean`; a dimension with `std = 0` passes
//!   through unchanged both ways;
//! - `none`: identity;
//! - `sin_cos` (state only): `[sin x₁ … sin x_D, cos x₁ … cos x_D]`, so the model's state is
//!   wider than the robot's ([`EmbodimentConfig::encoded_state_dim`]).
//!
//! Actions are denormalised by the runtime's output map (`clip(x)·scale + offset`, the clip
//! for the min/max and percentile groups), see [`Normalizer::action_output_map`].

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::prompt::ChatTemplate;
use crate::error::{Error, Result};

mod normalizer;
mod policy;
#[cfg(test)]
mod tests;

pub use normalizer::{Normalizer, MAX_STAT_ABS};
pub use policy::{policy_name, DeployKind, ModeOverrides, PolicySection};

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
    /// State groups only: GR00T's sin/cos encoding of angles. A group of width `D` enters
    /// the model as `2·D` values, `[sin x₁ … sin x_D, cos x₁ … cos x_D]`, with no statistics
    /// and no normalisation (GR00T's `sin_cos_embedding_keys`).
    SinCos,
}

/// What the values of an action group are (GR00T's `ActionFormat`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum GroupFormat {
    /// Independent values (joint angles, gripper): a relative action is `a − s` per value.
    #[default]
    Default,
    /// An end-effector pose: position and a 6-d rotation (9 values).
    XyzRot6d,
    /// An end-effector pose: position and a rotation vector (6 values).
    XyzRotvec,
}

fn is_false(b: &bool) -> bool {
    !*b
}

fn is_default_format(f: &GroupFormat) -> bool {
    *f == GroupFormat::Default
}

/// One named slice of the state or action vector.
///
/// ```toml
/// [[action]]
/// name = "arm_joints"
/// dim = 6
/// relative = true          # GR00T's use_relative_action for this key
/// state_key = "arm_joints" # the state group it is relative to (default: the same name)
/// ```
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Group {
    /// The key in `statistics.json` (GR00T's modality key).
    pub name: String,
    /// Width of the slice.
    pub dim: usize,
    /// Normalisation.
    #[serde(default)]
    pub norm: Norm,
    /// Action groups only: the model predicts this group relative to the robot's state
    /// (GR00T's `ActionRepresentation.RELATIVE`): the chunk made from an observation is
    /// `a − s`, with `s` the newest raw state of the observation window's
    /// [`state_key`](Self::state_key) group; its statistics are
    /// `relative_action.<name>` (per chunk slot, `[H, D]`, or `[D]`) in place of
    /// `action.<name>`. The runtime decodes every executed action against the state of the
    /// chunk it comes from and rebases what it carries between calls (see
    /// `pir2_runtime::OutputMap`).
    #[serde(default, skip_serializing_if = "is_false")]
    pub relative: bool,
    /// The state group a relative action group is taken against (default: the state group
    /// of the same name; it must have the same width).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state_key: Option<String>,
    /// Action groups only: what the values are. A relative end-effector pose (`xyz_rot6d`,
    /// `xyz_rotvec`) is `T_ref⁻¹·T` with `T_ref` the `state_key` group read in the same
    /// layout (see `pir2_runtime::pose`).
    #[serde(default, skip_serializing_if = "is_default_format")]
    pub format: GroupFormat,
}

impl Group {
    /// A min/max-normalised absolute group of `dim` values.
    pub(crate) fn new(name: &str, dim: usize) -> Self {
        Group {
            name: name.to_string(),
            dim,
            norm: Norm::MinMax,
            relative: false,
            state_key: None,
            format: GroupFormat::Default,
        }
    }

    /// The state group a relative action group refers to.
    pub fn reference_key(&self) -> &str {
        self.state_key.as_deref().unwrap_or(&self.name)
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
/// letterbox = true        # GR00T N1.7 always letterboxes (its `letter_box_transform` is not read)
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
    /// `gr00t_n17`: pad to a square with black first (default, as GR00T N1.7 does whatever
    /// its `letter_box_transform` says; without it a non-square frame is an error naming this
    /// setting).
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

/// The GR00T checkpoint key of the VLM's token-embedding table (GR00T N1.7:
/// `Gr00tN1d7.backbone` → `Qwen3Backbone.model` (Qwen3-VL for conditional generation) →
/// `.model.language_model.embed_tokens`).
pub const EMBED_TOKENS_KEY: &str = "backbone.model.model.language_model.embed_tokens.weight";

/// How the split backbone turns `pixel_values` into the ViT's patch rows and where it finds
/// the token-embedding table (the VLM's image processor and GR00T's checkpoint; the defaults
/// are Cosmos-Reason2-2B's, a Qwen3-VL-2B).
///
/// ```toml
/// [vision]
/// patch_size = 16           # the image processor's patch_size
/// temporal_patch_size = 2   # an image is repeated this many times along time
/// merge_size = 2            # spatial_merge_size: merge_size² patches → one LLM token
/// embed_tokens_key = "backbone.model.model.language_model.embed_tokens.weight"
/// ```
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VisionConfig {
    /// Side of one ViT patch, pixels.
    pub patch_size: usize,
    /// Frames per temporal patch (an image is repeated to fill it).
    pub temporal_patch_size: usize,
    /// Patches merged per side into one LLM token.
    pub merge_size: usize,
    /// Name of the token-embedding table in the checkpoint's safetensors.
    pub embed_tokens_key: String,
}

impl Default for VisionConfig {
    fn default() -> Self {
        VisionConfig {
            patch_size: 16,
            temporal_patch_size: 2,
            merge_size: 2,
            embed_tokens_key: EMBED_TOKENS_KEY.to_string(),
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
    /// The dataset's video features of the camera views, in view order (one per
    /// `prompt.chat.images`), e.g. `["observation.images.ego_view"]`: which videos
    /// `pir2 gr00t features` reads for each frame. Empty (the default): not named.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cameras: Vec<String>,
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
    /// The VLM's vision patching and token table, for the split backbone (GR00T's own
    /// `vit_*.onnx` + `llm_*.onnx`, see [`super::split`]); unused with a fused
    /// `backbone.onnx`.
    #[serde(default)]
    pub vision: VisionConfig,
    /// Robot-side safety settings (the stale-slow grace, per action group limits).
    #[serde(default)]
    pub safety: SafetySection,
    /// How the action head was fine-tuned and how it is deployed by default.
    #[serde(default)]
    pub policy: PolicySection,
}

/// Default stale-slow grace, ms (see [`SafetySection::slow_grace_ms`]).
pub const DEFAULT_SLOW_GRACE_MS: f64 = 200.0;

/// Ceiling of the stale-slow grace, ms: a checkpoint (or `pir2 gr00t run --slow-grace-ms`) may
/// set a shorter grace, never a longer one. One second of acting on features older than `d_vis_max`
/// ticks is already far past what any slow channel this project deploys produces.
pub const MAX_SLOW_GRACE_MS: f64 = 1000.0;

/// Ceiling of an embodiment's `control_hz`: no robot this project drives takes actions faster
/// (the xArm driver streams servo-j at 100-250 Hz and interpolates between actions; the
/// robot's own driver refuses a rate above its streaming rate).
pub const MAX_CONTROL_HZ: f64 = 250.0;

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
    /// half a tick) for longer than this stops the robot, ms, at most [`MAX_SLOW_GRACE_MS`].
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
            cameras: Vec::new(),
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
            vision: VisionConfig::default(),
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
            return Err(Error::Gr00tConfig(format!(
                "the checkpoint's action groups {ours:?} do not match the robot's {robot:?} \
                 (names, widths and order must agree)"
            )));
        }
        Ok(())
    }

    /// Read a TOML (`.toml`) or JSON (anything else) file and validate it.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let parse = |message: String| Error::Parse {
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
        toml::to_string(self).map_err(|e| Error::Gr00tConfig(e.to_string()))
    }

    /// Proprioception width (sum of the state groups).
    pub fn state_dim(&self) -> usize {
        self.state.iter().map(|g| g.dim).sum()
    }

    /// State width as the model sees it: [`EmbodimentConfig::state_dim`] with every
    /// [`Norm::SinCos`] group counted twice.
    pub fn encoded_state_dim(&self) -> usize {
        self.state
            .iter()
            .map(|g| {
                if g.norm == Norm::SinCos {
                    2 * g.dim
                } else {
                    g.dim
                }
            })
            .sum()
    }

    /// Per action dimension, the raw state index a relative action is taken against
    /// (`None`: absolute). Assumes a validated configuration.
    pub fn action_reference(&self) -> Vec<Option<usize>> {
        let mut out = Vec::with_capacity(self.action_dim());
        for g in &self.action {
            let first = g
                .relative
                .then(|| self.state_offset(g.reference_key()))
                .flatten();
            out.extend((0..g.dim).map(|k| first.map(|f| f + k)));
        }
        out
    }

    /// The relative end-effector pose groups as the runtime's output map holds them (first
    /// action dimension and layout).
    pub fn action_poses(&self) -> Vec<pir2_runtime::PoseGroup> {
        let mut out = Vec::new();
        let mut at = 0;
        for g in &self.action {
            let format = match g.format {
                GroupFormat::Default => None,
                GroupFormat::XyzRot6d => Some(pir2_runtime::pose::PoseFormat::XyzRot6d),
                GroupFormat::XyzRotvec => Some(pir2_runtime::pose::PoseFormat::XyzRotvec),
            };
            if let Some(format) = format.filter(|_| g.relative) {
                out.push(pir2_runtime::PoseGroup { first: at, format });
            }
            at += g.dim;
        }
        out
    }

    /// The relative action groups as `group → state group`, for logs and run summaries.
    pub fn relative_groups(&self) -> Vec<String> {
        self.action
            .iter()
            .filter(|g| g.relative)
            .map(|g| format!("{} → {}", g.name, g.reference_key()))
            .collect()
    }

    /// Whether any action group is relative.
    pub fn has_relative_actions(&self) -> bool {
        self.action.iter().any(|g| g.relative)
    }

    /// First raw state index of the state group `name`.
    fn state_offset(&self, name: &str) -> Option<usize> {
        let mut at = 0;
        for s in &self.state {
            if s.name == name {
                return Some(at);
            }
            at += s.dim;
        }
        None
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
        let bad = |m: String| Err(Error::Gr00tConfig(m));
        if !(self.control_hz.is_finite()
            && self.control_hz > 0.0
            && self.control_hz <= MAX_CONTROL_HZ)
        {
            return bad(format!(
                "control_hz must be in (0, {MAX_CONTROL_HZ}] Hz, got {}",
                self.control_hz
            ));
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
        if !self.cameras.is_empty() && self.cameras.len() != self.prompt.chat.images {
            return bad(format!(
                "cameras names {} view(s) ({}) but prompt.chat.images is {}",
                self.cameras.len(),
                self.cameras.join(", "),
                self.prompt.chat.images
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
            if what == "state" {
                if let Some(g) = groups.iter().find(|g| {
                    g.relative || g.state_key.is_some() || g.format != GroupFormat::Default
                }) {
                    return bad(format!(
                        "state group `{}`: relative, state_key and format are action-group \
                         settings",
                        g.name
                    ));
                }
            }
            if what == "action" {
                if let Some(g) = groups.iter().find(|g| g.norm == Norm::SinCos) {
                    return bad(format!(
                        "action group `{}`: norm = \"sin_cos\" is a state encoding \
                         (it cannot be decoded back into actions)",
                        g.name
                    ));
                }
            }
            if groups.len() > MAX_SIZE || groups.iter().any(|g| g.dim > MAX_SIZE) {
                return bad(format!(
                    "{what} groups: at most {MAX_SIZE} groups of at most {MAX_SIZE} values"
                ));
            }
        }
        for g in &self.action {
            let want = match g.format {
                GroupFormat::Default => None,
                GroupFormat::XyzRot6d => Some(9),
                GroupFormat::XyzRotvec => Some(6),
            };
            if let Some(w) = want.filter(|&w| w != g.dim) {
                return bad(format!(
                    "action group `{}`: format {:?} has {w} values, the group has dim {}",
                    g.name, g.format, g.dim
                ));
            }
            if !g.relative {
                if g.state_key.is_some() {
                    return bad(format!(
                        "action group `{}`: state_key is only used with relative = true",
                        g.name
                    ));
                }
                continue;
            }
            let key = g.reference_key();
            match self.state.iter().find(|s| s.name == key) {
                None => {
                    return bad(format!(
                        "action group `{}` is relative to state group `{key}`, which does not \
                         exist (state groups: {:?})",
                        g.name,
                        self.state.iter().map(|s| &s.name).collect::<Vec<_>>()
                    ))
                }
                Some(s) if s.dim != g.dim => {
                    return bad(format!(
                        "action group `{}` (dim {}) is relative to state group `{key}` of dim {}: \
                         the widths must agree",
                        g.name, g.dim, s.dim
                    ))
                }
                Some(_) => {}
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
        if !(sg.is_finite() && sg > 0.0 && sg <= MAX_SLOW_GRACE_MS) {
            return bad(format!(
                "safety.slow_grace_ms must be in (0, {MAX_SLOW_GRACE_MS}] ms, got {sg}"
            ));
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

/// Read the embodiment slot from GR00T's `embodiment_id.json` (`{tag: id}`), if the file exists.
pub fn read_embodiment_id(path: &Path, tag: &str) -> Result<Option<i64>> {
    if !path.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(path).map_err(|source| Error::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let map: BTreeMap<String, i64> = serde_json::from_str(&text).map_err(|e| Error::Parse {
        path: path.to_path_buf(),
        message: format!("expected {{tag: id}}: {e}"),
    })?;
    Ok(map.get(tag).copied())
}

/// `onnx/NAME_fp32.onnx`, or `onnx/NAME_bf16.onnx` when only that one exists (GR00T's
/// exporter names its files by precision; the file's declared types, not its name, decide
/// how it is fed).
fn precision_variant(onnx: &Path, name: &str) -> PathBuf {
    let fp32 = onnx.join(format!("{name}_fp32.onnx"));
    let bf16 = onnx.join(format!("{name}_bf16.onnx"));
    if !fp32.exists() && bf16.exists() {
        bf16
    } else {
        fp32
    }
}

/// The two forms of the backbone (see [`CheckpointFiles::backbone_form`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BackboneForm {
    /// `onnx/backbone.onnx`: ViT + LLM fused by the user.
    Fused,
    /// GR00T's own `vit_*.onnx` + `llm_*.onnx`, glued in Rust ([`super::split`]).
    Split,
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
    /// Backbone (ViT + LLM) ONNX, fused.
    pub backbone: PathBuf,
    /// GR00T's ViT export (`full_pipeline`): `onnx/vit_fp32.onnx`, or `onnx/vit_bf16.onnx`
    /// when only that one exists.
    pub vit: PathBuf,
    /// GR00T's LLM export (`full_pipeline`): `onnx/llm_fp32.onnx`, or `onnx/llm_bf16.onnx`
    /// (the exporter's default) when only that one exists. The name only picks the file: its
    /// declared element types decide how it is fed ([`super::contract::Precision`]).
    pub llm: PathBuf,
    /// GR00T's checkpoint weights (one file), which hold the VLM's token-embedding table.
    pub model_weights: PathBuf,
    /// GR00T's sharded checkpoint index (used instead of `model_weights` when present).
    pub model_index: PathBuf,
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
            vit: precision_variant(&onnx, "vit"),
            llm: precision_variant(&onnx, "llm"),
            model_weights: dir.join("model.safetensors"),
            model_index: dir.join("model.safetensors.index.json"),
            vl_self_attention: onnx.join("vl_self_attention.onnx"),
            weights: dir.join("pir2_gr00t.safetensors"),
            tokenizer: dir.join("tokenizer.json"),
            vocab: dir.join("vocab.txt"),
        }
    }

    /// Which backbone the checkpoint carries: the fused `backbone.onnx`, or GR00T's split
    /// ViT + LLM export with the checkpoint's safetensors (for the token-embedding table).
    /// Both forms present, or a split set with a file missing, is one error naming the
    /// files; with neither, the fused form is expected (its loader names the missing file).
    pub fn backbone_form(&self) -> Result<BackboneForm> {
        let fused = self.backbone.exists();
        let (vit, llm) = (self.vit.exists(), self.llm.exists());
        let table = self.model_index.exists() || self.model_weights.exists();
        let dir = self
            .backbone
            .parent()
            .and_then(Path::parent)
            .unwrap_or(Path::new("."))
            .to_path_buf();
        let err = |problem: String| {
            Err(Error::BackboneFiles {
                dir: dir.clone(),
                problem,
            })
        };
        if fused && (vit || llm) {
            let split: Vec<String> = [(&self.vit, vit), (&self.llm, llm)]
                .iter()
                .filter(|(_, e)| *e)
                .map(|(p, _)| format!("`{}`", p.display()))
                .collect();
            return err(format!(
                "both the fused `{}` and the split {} are present; keep one form",
                self.backbone.display(),
                split.join(" and ")
            ));
        }
        if !vit && !llm {
            return Ok(BackboneForm::Fused);
        }
        let mut missing = Vec::new();
        if !vit {
            missing.push(format!("`{}` (ViT)", self.vit.display()));
        }
        if !llm {
            missing.push(format!("`{}` (LLM)", self.llm.display()));
        }
        if !table {
            missing.push(format!(
                "`{}` or `{}` (the checkpoint's weights, for the token-embedding table)",
                self.model_weights.display(),
                self.model_index.display()
            ));
        }
        if !missing.is_empty() {
            let present: Vec<String> = [(&self.vit, vit), (&self.llm, llm)]
                .iter()
                .filter(|(_, e)| *e)
                .map(|(p, _)| format!("`{}`", p.display()))
                .collect();
            return err(format!(
                "the split backbone is incomplete: {} present, {} missing",
                present.join(" and "),
                missing.join(" and ")
            ));
        }
        Ok(BackboneForm::Split)
    }

    /// The checkpoint's embodiment: its `embodiment.toml`, or the built-in xArm6 + XHand
    /// when the file is absent (a file that exists but does not parse is an error).
    pub fn embodiment_config(&self) -> Result<EmbodimentConfig> {
        if self.embodiment.exists() {
            EmbodimentConfig::load(&self.embodiment)
        } else {
            Ok(EmbodimentConfig::xarm6_xhand())
        }
    }
}
