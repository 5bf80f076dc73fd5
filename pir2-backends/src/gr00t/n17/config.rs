//! The action-head part of a GR00T N1.7 model configuration (`config.json` of a checkpoint).

use std::path::{Path, PathBuf};

use serde_json::{Map, Value};

use crate::error::{Error, Result};

/// The DiT of the action head (GR00T's `diffusion_model_cfg`).
#[derive(Debug, Clone, PartialEq)]
pub struct DitConfig {
    /// Transformer blocks.
    pub num_layers: usize,
    /// Attention heads.
    pub num_attention_heads: usize,
    /// Width of one head; `heads · head_dim` is the token width and must equal
    /// [`Gr00tN17Config::input_embedding_dim`].
    pub attention_head_dim: usize,
    /// Output width (must equal [`Gr00tN17Config::hidden_size`], the decoder's input).
    pub output_dim: usize,
    /// Odd blocks self-attend instead of cross-attending to the VL tokens.
    pub interleave_self_attention: bool,
    /// Fixed sinusoidal position embeddings added to each block's normalised input
    /// (`positional_embeddings = "sinusoidal"`; GR00T N1.7 uses none).
    pub sinusoidal_positions: bool,
    /// Rows of the sinusoidal table (`max_num_positional_embeddings`).
    pub max_num_positional_embeddings: usize,
    /// LayerNorm epsilon of the blocks (`norm_eps`).
    pub norm_eps: f64,
    /// Training-time dropout rate `p` of the blocks (`dropout`; N1.7: 0.2): after the
    /// attention's output projection and after the feed-forward's GELU. Inference never
    /// drops; see [`super::DitDropout`].
    pub dropout: f64,
    /// With `dropout`, also drop the attention output a second time and the feed-forward's
    /// output (`final_dropout`; N1.7: true).
    pub final_dropout: bool,
}

/// The optional self-attention stack over the VL tokens (GR00T's `vl_self_attention_cfg`).
#[derive(Debug, Clone, PartialEq)]
pub struct VlSelfAttentionConfig {
    /// Transformer blocks (0 = none).
    pub num_layers: usize,
    /// Attention heads.
    pub num_attention_heads: usize,
    /// Width of one head; `heads · head_dim` must equal the backbone width.
    pub attention_head_dim: usize,
    /// Fixed sinusoidal position embeddings (GR00T's default for this stack).
    pub sinusoidal_positions: bool,
    /// Rows of the sinusoidal table.
    pub max_num_positional_embeddings: usize,
}

/// The fields of a GR00T N1.7 configuration that define the action head. Field names and
/// defaults are GR00T's (`Gr00tN1d7Config`); [`Default`] is the released N1.7 head.
#[derive(Debug, Clone, PartialEq)]
pub struct Gr00tN17Config {
    /// Backbone token width `D_vl` (`backbone_embedding_dim`, 2048).
    pub backbone_embedding_dim: usize,
    /// Padded state width per history step (`max_state_dim`, 132).
    pub max_state_dim: usize,
    /// Padded action width `A_max` (`max_action_dim`, 132).
    pub max_action_dim: usize,
    /// Chunk length `H` (`action_horizon`, 40).
    pub action_horizon: usize,
    /// MLP width of the state encoder / decoder and DiT output width (`hidden_size`, 1024).
    pub hidden_size: usize,
    /// Token width `D_in` of the state and action tokens (`input_embedding_dim`, 1536).
    pub input_embedding_dim: usize,
    /// State steps flattened into the state token (`state_history_length`, 1).
    pub state_history_length: usize,
    /// Learned position embedding added to the action tokens (`add_pos_embed`).
    pub add_pos_embed: bool,
    /// Rows of the position embedding (`max_seq_len`, 1024).
    pub max_seq_len: usize,
    /// LayerNorm on the backbone tokens (`use_vlln`).
    pub use_vlln: bool,
    /// Cross-attention blocks alternate between text and image tokens (`use_alternate_vl_dit`).
    pub use_alternate_vl_dit: bool,
    /// Alternation period of text/image cross-attention (`attend_text_every_n_blocks`, 2).
    pub attend_text_every_n_blocks: usize,
    /// The DiT.
    pub dit: DitConfig,
    /// Self-attention over the VL tokens after `vlln` (none in N1.7).
    pub vl_self_attention: Option<VlSelfAttentionConfig>,
    /// Embodiment slots of the category-specific MLPs (`max_num_embodiments`, 32).
    pub max_num_embodiments: usize,
    /// Euler steps of GR00T's own sampler (`num_inference_timesteps`, 4).
    pub num_inference_timesteps: usize,
    /// Discrete timestep range: `t ∈ [0, 1)` maps to `⌊t · buckets⌋` (`num_timestep_buckets`, 1000).
    pub num_timestep_buckets: usize,
}

impl Default for Gr00tN17Config {
    fn default() -> Self {
        Self {
            backbone_embedding_dim: 2048,
            max_state_dim: 132,
            max_action_dim: 132,
            action_horizon: 40,
            hidden_size: 1024,
            input_embedding_dim: 1536,
            state_history_length: 1,
            add_pos_embed: true,
            max_seq_len: 1024,
            use_vlln: true,
            use_alternate_vl_dit: true,
            attend_text_every_n_blocks: 2,
            dit: DitConfig {
                num_layers: 16,
                num_attention_heads: 32,
                attention_head_dim: 48,
                output_dim: 1024,
                interleave_self_attention: true,
                sinusoidal_positions: false,
                max_num_positional_embeddings: 512,
                norm_eps: 1e-5,
                dropout: 0.2,
                final_dropout: true,
            },
            vl_self_attention: None,
            max_num_embodiments: 32,
            num_inference_timesteps: 4,
            num_timestep_buckets: 1000,
        }
    }
}

struct Fields<'a> {
    path: &'a Path,
    prefix: &'static str,
    map: &'a Map<String, Value>,
}

impl Fields<'_> {
    fn err(&self, key: &str, message: impl std::fmt::Display) -> Error {
        Error::Format {
            path: self.path.to_path_buf(),
            message: format!("`{}{key}`: {message}", self.prefix),
        }
    }
    /// The value of `key` read by `read` (`default` when absent or null); a value `read`
    /// rejects is an error saying it expected `expected`.
    fn typed<T>(
        &self,
        key: &str,
        default: T,
        read: impl FnOnce(&Value) -> Option<T>,
        expected: &str,
    ) -> Result<T> {
        match self.map.get(key) {
            None | Some(Value::Null) => Ok(default),
            Some(v) => {
                read(v).ok_or_else(|| self.err(key, format!("expected {expected}, got {v}")))
            }
        }
    }
    fn usize(&self, key: &str, default: usize) -> Result<usize> {
        self.typed(
            key,
            default,
            |v| v.as_u64().map(|n| n as usize),
            "a non-negative integer",
        )
    }
    fn bool(&self, key: &str, default: bool) -> Result<bool> {
        self.typed(key, default, Value::as_bool, "true or false")
    }
    fn f64(&self, key: &str, default: f64) -> Result<f64> {
        self.typed(key, default, Value::as_f64, "a number")
    }
    /// A string option; `None` for JSON null.
    fn opt_str(&self, key: &str, default: Option<&str>) -> Result<Option<String>> {
        match self.map.get(key) {
            None => Ok(default.map(str::to_string)),
            Some(Value::Null) => Ok(None),
            Some(Value::String(s)) => Ok(Some(s.clone())),
            Some(v) => Err(self.err(key, format!("expected a string or null, got {v}"))),
        }
    }
    fn require(&self, key: &str, value: Option<String>, allowed: &[&str]) -> Result<()> {
        match value {
            Some(v) if !allowed.contains(&v.as_str()) => Err(self.err(
                key,
                format!("`{v}` is not supported (supported: {})", allowed.join(", ")),
            )),
            _ => Ok(()),
        }
    }
}

impl Gr00tN17Config {
    /// Read the action-head fields of a GR00T N1.7 `config.json`; absent fields take GR00T's
    /// defaults (the model class's for the top level, the DiT's and the self-attention stack's
    /// for keys missing from `diffusion_model_cfg` / `vl_self_attention_cfg`).
    pub fn from_json_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::from_json_str(&text, path)
    }

    /// [`Gr00tN17Config::from_json_file`] on text; `path` only names the source in errors.
    pub fn from_json_str(text: &str, path: &Path) -> Result<Self> {
        let value: Value = serde_json::from_str(text).map_err(|e| Error::Format {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        let Value::Object(map) = &value else {
            return Err(Error::Format {
                path: path.to_path_buf(),
                message: "expected a JSON object".into(),
            });
        };
        let d = Self::default();
        let top = Fields {
            path,
            prefix: "",
            map,
        };
        let sub = |key: &str| -> Result<Option<&Map<String, Value>>> {
            match map.get(key) {
                None | Some(Value::Null) => Ok(None),
                Some(Value::Object(m)) => Ok(Some(m)),
                Some(v) => Err(top.err(key, format!("expected an object, got {v}"))),
            }
        };
        // The DiT: GR00T N1.7's default dict when absent; the DiT class defaults per key.
        let dit = match sub("diffusion_model_cfg")? {
            None => d.dit.clone(),
            Some(m) => {
                let f = Fields {
                    path,
                    prefix: "diffusion_model_cfg.",
                    map: m,
                };
                f.require("norm_type", f.opt_str("norm_type", None)?, &["ada_norm"])?;
                f.require(
                    "activation_fn",
                    f.opt_str("activation_fn", None)?,
                    &["gelu-approximate"],
                )?;
                if !f.bool("attention_bias", true)? {
                    return Err(f.err("attention_bias", "only `true` is supported"));
                }
                if f.bool("norm_elementwise_affine", false)? {
                    return Err(f.err("norm_elementwise_affine", "only `false` is supported"));
                }
                let pos = f.opt_str("positional_embeddings", Some("sinusoidal"))?;
                f.require("positional_embeddings", pos.clone(), &["sinusoidal"])?;
                DitConfig {
                    num_layers: f.usize("num_layers", 12)?,
                    num_attention_heads: f.usize("num_attention_heads", 8)?,
                    attention_head_dim: f.usize("attention_head_dim", 64)?,
                    output_dim: f.usize("output_dim", 26)?,
                    interleave_self_attention: f.bool("interleave_self_attention", false)?,
                    sinusoidal_positions: pos.is_some(),
                    max_num_positional_embeddings: f.usize("max_num_positional_embeddings", 512)?,
                    norm_eps: f.f64("norm_eps", 1e-5)?,
                    dropout: f.f64("dropout", 0.1)?,
                    final_dropout: f.bool("final_dropout", true)?,
                }
            }
        };
        let vl_self_attention = match sub("vl_self_attention_cfg")? {
            None => None,
            Some(m) => {
                let f = Fields {
                    path,
                    prefix: "vl_self_attention_cfg.",
                    map: m,
                };
                f.require(
                    "activation_fn",
                    f.opt_str("activation_fn", None)?,
                    &["gelu-approximate"],
                )?;
                if !f.bool("attention_bias", true)? {
                    return Err(f.err("attention_bias", "only `true` is supported"));
                }
                let pos = f.opt_str("positional_embeddings", Some("sinusoidal"))?;
                f.require("positional_embeddings", pos.clone(), &["sinusoidal"])?;
                let c = VlSelfAttentionConfig {
                    num_layers: f.usize("num_layers", 12)?,
                    num_attention_heads: f.usize("num_attention_heads", 8)?,
                    attention_head_dim: f.usize("attention_head_dim", 64)?,
                    sinusoidal_positions: pos.is_some(),
                    max_num_positional_embeddings: f.usize("max_num_positional_embeddings", 512)?,
                };
                (c.num_layers > 0).then_some(c)
            }
        };
        let cfg = Self {
            backbone_embedding_dim: top
                .usize("backbone_embedding_dim", d.backbone_embedding_dim)?,
            max_state_dim: top.usize("max_state_dim", d.max_state_dim)?,
            max_action_dim: top.usize("max_action_dim", d.max_action_dim)?,
            action_horizon: top.usize("action_horizon", d.action_horizon)?,
            hidden_size: top.usize("hidden_size", d.hidden_size)?,
            input_embedding_dim: top.usize("input_embedding_dim", d.input_embedding_dim)?,
            state_history_length: top.usize("state_history_length", d.state_history_length)?,
            add_pos_embed: top.bool("add_pos_embed", d.add_pos_embed)?,
            max_seq_len: top.usize("max_seq_len", d.max_seq_len)?,
            use_vlln: top.bool("use_vlln", d.use_vlln)?,
            use_alternate_vl_dit: top.bool("use_alternate_vl_dit", d.use_alternate_vl_dit)?,
            attend_text_every_n_blocks: top
                .usize("attend_text_every_n_blocks", d.attend_text_every_n_blocks)?,
            dit,
            vl_self_attention,
            max_num_embodiments: top.usize("max_num_embodiments", d.max_num_embodiments)?,
            num_inference_timesteps: top
                .usize("num_inference_timesteps", d.num_inference_timesteps)?,
            num_timestep_buckets: top.usize("num_timestep_buckets", d.num_timestep_buckets)?,
        };
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// Check the relations between sizes; `path` names the source in errors.
    pub fn validate(&self, path: &Path) -> Result<()> {
        let bad = |message: String| Error::Format {
            path: path.to_path_buf(),
            message,
        };
        let inner = self.dit.num_attention_heads * self.dit.attention_head_dim;
        if inner != self.input_embedding_dim {
            return Err(bad(format!(
                "the DiT's width `diffusion_model_cfg.num_attention_heads · attention_head_dim` = {inner} \
                 must equal `input_embedding_dim` = {}",
                self.input_embedding_dim
            )));
        }
        if self.dit.output_dim != self.hidden_size {
            return Err(bad(format!(
                "`diffusion_model_cfg.output_dim` = {} must equal `hidden_size` = {} (the action decoder's input)",
                self.dit.output_dim, self.hidden_size
            )));
        }
        if let Some(v) = &self.vl_self_attention {
            let w = v.num_attention_heads * v.attention_head_dim;
            if w != self.backbone_embedding_dim {
                return Err(bad(format!(
                    "`vl_self_attention_cfg.num_attention_heads · attention_head_dim` = {w} must equal \
                     `backbone_embedding_dim` = {}",
                    self.backbone_embedding_dim
                )));
            }
        }
        if !(0.0..1.0).contains(&self.dit.dropout) {
            return Err(bad(format!(
                "`diffusion_model_cfg.dropout` = {} must be in [0, 1)",
                self.dit.dropout
            )));
        }
        if self.use_alternate_vl_dit
            && (!self.dit.interleave_self_attention || self.attend_text_every_n_blocks == 0)
        {
            return Err(bad(
                "`use_alternate_vl_dit` needs `diffusion_model_cfg.interleave_self_attention = true` \
                 and `attend_text_every_n_blocks` ≥ 1"
                    .into(),
            ));
        }
        if self.add_pos_embed && self.max_seq_len < self.action_horizon {
            return Err(bad(format!(
                "`max_seq_len` = {} is shorter than `action_horizon` = {}",
                self.max_seq_len, self.action_horizon
            )));
        }
        let zero = [
            ("max_num_embodiments", self.max_num_embodiments),
            ("action_horizon", self.action_horizon),
            ("num_timestep_buckets", self.num_timestep_buckets),
            (
                "diffusion_model_cfg.num_attention_heads",
                self.dit.num_attention_heads,
            ),
        ];
        if let Some((k, _)) = zero.iter().find(|(_, v)| *v == 0) {
            return Err(bad(format!("`{k}` must be at least 1")));
        }
        Ok(())
    }

    /// The state width the state encoder takes: `state_history_length · max_state_dim`.
    pub fn state_input_dim(&self) -> usize {
        self.state_history_length * self.max_state_dim
    }
}

/// `config.json` next to the weights, as a GR00T checkpoint directory has it.
pub(crate) fn config_path(dir: &Path) -> PathBuf {
    dir.join("config.json")
}
