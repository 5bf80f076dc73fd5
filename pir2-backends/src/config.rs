//! Model configurations (serde TOML/JSON) and normalisation statistics.
//!
//! A checkpoint's `config.json` is a [`Config`]: the [`Spec`] every model shares (what goes
//! in and out) plus the architecture ([`ModelConfig`]). Its `stats.json` is a [`Stats`].
//!
//! **Action space.** Every model works in *normalised* action space: `x` and the velocity
//! are in units of `(a − mean)/std`. Callers (the runtime, the trainer) convert with
//! [`Stats::normalize_action`] / [`Stats::denormalize_action`]. Observations are passed raw;
//! the model normalises them itself ([`Stats::encode_fast`], [`Stats::encode_slow`]).
//!
//! ```
//! use pir2_backends::config::{Config, ModelConfig, MlpConfig, Spec, SlowSpec};
//! let spec = Spec { horizon: 16, action_dim: 2, n_obs: 2, fast_dim: 3, slow: SlowSpec::Vector { dim: 2 }, d_vis_max: 3 };
//! let cfg = Config { spec, model: ModelConfig::Mlp(MlpConfig::default()) };
//! let text = toml::to_string(&cfg).unwrap();
//! let back: Config = toml::from_str(&text).unwrap();
//! assert_eq!(back, cfg);
//! ```

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

pub use pir2_runtime::SlowSpec;

/// What every model takes and returns.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Spec {
    /// Chunk length `H`.
    pub horizon: usize,
    /// Action dimension `A`.
    pub action_dim: usize,
    /// Fast observation history length `n_obs` (oldest first).
    pub n_obs: usize,
    /// Fast observation width `F`.
    pub fast_dim: usize,
    /// Slow channel layout.
    #[serde(default)]
    pub slow: SlowSpec,
    /// Largest slow-feature age the delay embedding knows (larger ages are clamped).
    #[serde(default)]
    pub d_vis_max: usize,
}

/// Bound on every size a [`Config`] declares (widths, lengths, depths, counts): configs
/// come from files, and a larger size is refused by name before any shape arithmetic
/// could overflow or any buffer be sized from it.
pub const MAX_SIZE: usize = 1 << 16;

fn bounded(field: &'static str, v: usize) -> Result<()> {
    if v > MAX_SIZE {
        return Err(Error::config(
            field,
            format!("{v} is above the limit {MAX_SIZE}"),
        ));
    }
    Ok(())
}

impl Spec {
    /// Validate sizes.
    pub fn validate(&self) -> Result<()> {
        bounded("spec.horizon", self.horizon)?;
        bounded("spec.action_dim", self.action_dim)?;
        bounded("spec.n_obs", self.n_obs)?;
        bounded("spec.fast_dim", self.fast_dim)?;
        bounded("spec.slow", self.slow.width())?;
        bounded("spec.slow", self.slow.tokens())?;
        bounded("spec.d_vis_max", self.d_vis_max)?;
        if self.horizon == 0 {
            return Err(Error::config("spec.horizon", "must be >= 1"));
        }
        if self.action_dim == 0 {
            return Err(Error::config("spec.action_dim", "must be >= 1"));
        }
        if self.n_obs == 0 {
            return Err(Error::config("spec.n_obs", "must be >= 1"));
        }
        if let SlowSpec::Vector { dim: 0 }
        | SlowSpec::Tokens { dim: 0, .. }
        | SlowSpec::Tokens { tokens: 0, .. } = self.slow
        {
            return Err(Error::config(
                "spec.slow",
                "slow sizes must be >= 1 (use kind = \"none\")",
            ));
        }
        Ok(())
    }

    /// Width of the encoded fast history `[o_t, o_t − o_{t−1}, …]`: `n_obs·F`.
    pub fn fast_encoded_dim(&self) -> usize {
        self.n_obs * self.fast_dim
    }

    /// Check that `other` (a checkpoint's spec) equals `self`, naming the first differing field.
    pub fn expect_eq(&self, found: &Spec) -> Result<()> {
        macro_rules! chk {
            ($f:ident) => {
                if self.$f != found.$f {
                    return Err(Error::SpecMismatch {
                        field: stringify!($f),
                        expected: format!("{:?}", self.$f),
                        found: format!("{:?}", found.$f),
                    });
                }
            };
        }
        chk!(horizon);
        chk!(action_dim);
        chk!(n_obs);
        chk!(fast_dim);
        chk!(slow);
        chk!(d_vis_max);
        Ok(())
    }
}

/// Small MLP head (the embedded-task workhorse: 3×256 SiLU).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct MlpConfig {
    /// Hidden width.
    pub width: usize,
    /// Number of hidden layers.
    pub depth: usize,
    /// Fourier features per position for `τ` (the input also gets `τ` and the hidden flag).
    pub tau_freqs: usize,
    /// Width of the learned `d_vis` embedding (zero-initialised).
    pub dvis_dim: usize,
}

impl Default for MlpConfig {
    fn default() -> Self {
        Self {
            width: 256,
            depth: 3,
            tau_freqs: 2,
            dvis_dim: 8,
        }
    }
}

/// How `τ` conditions the U-Net's FiLM layers.
///
/// Every residual block modulates its hidden state with `h ← (1 + γ)·h + β`. The variants differ
/// in which parameters compute `(γ, β)`:
///
/// | variant | parameters per block | input of the projection |
/// |---|---|---|
/// | [`Shared`](Self::Shared) | one `Linear(E+G → 2C)` | mean `τ` embedding over the chunk, global cond |
/// | [`PerPositionHeads`](Self::PerPositionHeads) | one `Linear(E+G → 2C)` **per slot** (`L` of them) | the slot's `τ` embedding, global cond |
/// | [`PerPositionTau`](Self::PerPositionTau) | the shared one plus one zero-initialised `Linear(E → 2C)` shared by all slots | shared input, plus the slot's `τ` embedding |
///
/// A block at resolution `L` (`L = H` at the full-resolution level, `H/2^i` after `i`
/// down-samplings) has one slot per position of its activation; slot `l` covers chunk positions
/// `[l·H/L, (l+1)·H/L)` and its `τ` part is `mish` of the mean `τ` embedding over them. At full
/// resolution a slot is one chunk position, so each position `p` has its own head `head_p`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum FilmMode {
    /// One `(γ, β)` per sample from the mean `τ` embedding (baselines, shared `τ`).
    Shared,
    /// The paper's architecture: every block has one FiLM head per slot (per chunk position at
    /// full resolution), `(γ_l, β_l) = head_l([mish(ē_l), global])`. Each head is initialised as
    /// a copy of the shared head (the same draws as [`Shared`](Self::Shared) with the same seed,
    /// tiled), and a shared checkpoint fine-tuned with heads has its shared pair copied into
    /// every head, so at a position-uniform `τ` the model computes exactly the shared model's
    /// function at its first step; the heads then specialise in training.
    #[default]
    PerPositionHeads,
    /// Ablation (not the paper's): the shared pair plus a zero-initialised projection, shared
    /// by all slots, of each slot's `τ` embedding. Position reaches the modulation only through
    /// `τ_p`. Read as `per_position` in configs of pir2 ≤ 0.1 (the default then).
    #[serde(rename = "per_position_tau", alias = "per_position")]
    PerPositionTau,
}

impl FilmMode {
    /// What a DiT config written before per-position heads existed means (the shared head
    /// fed per-token `τ`).
    pub fn legacy() -> Self {
        Self::PerPositionTau
    }
}

/// Conditional U-Net 1D (diffusion-policy design) with per-position FiLM.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct UNetConfig {
    /// Channel widths per level (one down-sampling between consecutive levels).
    pub widths: Vec<usize>,
    /// Convolution kernel size (odd).
    pub kernel: usize,
    /// GroupNorm groups (must divide every width).
    pub groups: usize,
    /// Sinusoidal `τ` embedding width.
    pub tau_dim: usize,
    /// Width of the learned `d_vis` embedding (zero-initialised).
    pub dvis_dim: usize,
    /// FiLM variant.
    pub film: FilmMode,
}

impl Default for UNetConfig {
    fn default() -> Self {
        Self {
            widths: vec![64, 128, 256],
            kernel: 5,
            groups: 8,
            tau_dim: 64,
            dvis_dim: 16,
            film: FilmMode::PerPositionHeads,
        }
    }
}

/// DiT action head with per-position AdaLN and cross-attention to slow tokens.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct DitConfig {
    /// Token width `D`.
    pub width: usize,
    /// Number of blocks (each: self-attention, cross-attention, MLP).
    pub depth: usize,
    /// Attention heads (must divide `width`).
    pub heads: usize,
    /// MLP expansion ratio.
    pub mlp_ratio: usize,
    /// Sinusoidal `τ` embedding width.
    pub tau_dim: usize,
    /// AdaLN of the blocks and of the output: [`FilmMode::PerPositionHeads`] (the paper's: one
    /// modulation head per token position, each a copy of the shared head, adaLN-zero) or one
    /// shared head fed each token's `τ` embedding ([`FilmMode::PerPositionTau`]; `shared` is
    /// the same network). A config written before this field existed means the shared head.
    #[serde(default = "FilmMode::legacy")]
    pub ada: FilmMode,
}

impl Default for DitConfig {
    fn default() -> Self {
        Self {
            width: 128,
            depth: 4,
            heads: 4,
            mlp_ratio: 4,
            tau_dim: 64,
            ada: FilmMode::PerPositionHeads,
        }
    }
}

/// The architecture.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ModelConfig {
    /// MLP head.
    Mlp(MlpConfig),
    /// Conditional U-Net 1D.
    #[serde(rename = "unet")]
    UNet(UNetConfig),
    /// DiT action head.
    Dit(DitConfig),
}

/// A complete model configuration (a checkpoint's `config.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    /// Inputs and outputs.
    pub spec: Spec,
    /// Architecture.
    pub model: ModelConfig,
}

impl Config {
    /// Validate the spec and the architecture's sizes.
    pub fn validate(&self) -> Result<()> {
        self.spec.validate()?;
        match &self.model {
            ModelConfig::Mlp(m) => {
                bounded("mlp.width", m.width)?;
                bounded("mlp.depth", m.depth)?;
                bounded("mlp.tau_freqs", m.tau_freqs)?;
                bounded("mlp.dvis_dim", m.dvis_dim)?;
                if m.width == 0 || m.depth == 0 {
                    return Err(Error::config("mlp.width/depth", "must be >= 1"));
                }
            }
            ModelConfig::UNet(u) => {
                if u.widths.is_empty() {
                    return Err(Error::config("unet.widths", "needs at least one level"));
                }
                if u.widths.len() > 16 {
                    return Err(Error::config("unet.widths", "at most 16 levels"));
                }
                for &w in &u.widths {
                    bounded("unet.widths", w)?;
                }
                bounded("unet.kernel", u.kernel)?;
                bounded("unet.tau_dim", u.tau_dim)?;
                bounded("unet.dvis_dim", u.dvis_dim)?;
                if u.kernel % 2 == 0 {
                    return Err(Error::config(
                        "unet.kernel",
                        format!("must be odd, got {}", u.kernel),
                    ));
                }
                if u.groups == 0 || u.widths.iter().any(|w| w % u.groups != 0) {
                    return Err(Error::config(
                        "unet.groups",
                        format!("{} must divide every width {:?}", u.groups, u.widths),
                    ));
                }
                if u.tau_dim < 2 || u.tau_dim % 2 != 0 {
                    return Err(Error::config("unet.tau_dim", "must be even and >= 2"));
                }
                let levels = u.widths.len() - 1;
                let halvings = u32::try_from(levels)
                    .ok()
                    .and_then(|l| 1usize.checked_shl(l))
                    .filter(|h| *h <= self.spec.horizon);
                if halvings.is_none_or(|h| self.spec.horizon % h != 0) {
                    return Err(Error::config(
                        "unet.widths",
                        format!(
                            "horizon {} must be divisible by 2^{levels} (one halving per level)",
                            self.spec.horizon
                        ),
                    ));
                }
            }
            ModelConfig::Dit(d) => {
                bounded("dit.width", d.width)?;
                bounded("dit.depth", d.depth)?;
                bounded("dit.heads", d.heads)?;
                bounded("dit.mlp_ratio", d.mlp_ratio)?;
                bounded("dit.tau_dim", d.tau_dim)?;
                if d.heads == 0 || d.width % d.heads != 0 {
                    return Err(Error::config(
                        "dit.heads",
                        format!("{} must divide width {}", d.heads, d.width),
                    ));
                }
                if d.tau_dim < 2 || d.tau_dim % 2 != 0 {
                    return Err(Error::config("dit.tau_dim", "must be even and >= 2"));
                }
                if d.depth == 0 || d.mlp_ratio == 0 {
                    return Err(Error::config("dit.depth/mlp_ratio", "must be >= 1"));
                }
            }
        }
        Ok(())
    }

    /// Read a config from a `.toml` or `.json` file (by extension; JSON otherwise).
    pub fn from_file(path: &std::path::Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let fmt = |m: String| Error::Format {
            path: path.to_owned(),
            message: m,
        };
        let cfg: Config = if path.extension().is_some_and(|e| e == "toml") {
            toml::from_str(&text).map_err(|e| fmt(e.to_string()))?
        } else {
            serde_json::from_str(&text).map_err(|e| fmt(e.to_string()))?
        };
        cfg.validate()?;
        Ok(cfg)
    }
}

/// Per-dimension mean and standard deviation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Norm {
    /// Mean per dimension.
    pub mean: Vec<f32>,
    /// Standard deviation per dimension (floored when computed).
    pub std: Vec<f32>,
}

impl Norm {
    /// The identity normalisation of width `n`.
    pub fn identity(n: usize) -> Self {
        Self {
            mean: vec![0.0; n],
            std: vec![1.0; n],
        }
    }
    /// Width.
    pub fn dim(&self) -> usize {
        self.mean.len()
    }
    /// Accumulating statistics: feed rows with [`NormAcc::push`].
    pub fn accumulator(n: usize) -> NormAcc {
        NormAcc {
            n: 0,
            sum: vec![0.0; n],
            sq: vec![0.0; n],
        }
    }
}

/// Streaming mean/std accumulator (f64 sums).
#[derive(Debug, Clone)]
pub struct NormAcc {
    n: u64,
    sum: Vec<f64>,
    sq: Vec<f64>,
}

impl NormAcc {
    /// Add one row.
    pub fn push(&mut self, row: &[f32]) {
        self.n += 1;
        for ((s, q), &v) in self.sum.iter_mut().zip(&mut self.sq).zip(row) {
            *s += v as f64;
            *q += (v as f64) * (v as f64);
        }
    }
    /// Finish; `std` is floored at `floor` (constant dimensions stay finite).
    pub fn finish(&self, floor: f32) -> Norm {
        let n = self.n.max(1) as f64;
        let mean: Vec<f32> = self.sum.iter().map(|s| (s / n) as f32).collect();
        let std = self
            .sum
            .iter()
            .zip(&self.sq)
            .map(|(s, q)| (((q / n) - (s / n) * (s / n)).max(0.0).sqrt() as f32).max(floor))
            .collect();
        Norm { mean, std }
    }
}

/// Normalisation statistics stored with a checkpoint (`stats.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// Fast observation `o_t`, width `F`.
    pub fast: Norm,
    /// Successive fast differences `o_t − o_{t−1}`, width `F` (shared by every difference).
    pub fast_diff: Norm,
    /// Slow features, width `S` (vector) or `D` (per token); empty without a slow channel.
    pub slow: Norm,
    /// Actions, width `A`.
    pub action: Norm,
}

impl Stats {
    /// Identity statistics for a spec.
    pub fn identity(spec: &Spec) -> Self {
        Self {
            fast: Norm::identity(spec.fast_dim),
            fast_diff: Norm::identity(spec.fast_dim),
            slow: Norm::identity(spec.slow.width()),
            action: Norm::identity(spec.action_dim),
        }
    }

    /// Check the widths against a spec.
    pub fn validate(&self, spec: &Spec) -> Result<()> {
        let chk = |what: &str, n: &Norm, want: usize| -> Result<()> {
            if n.mean.len() != want || n.std.len() != want {
                return Err(Error::shape(
                    format!("stats.{what}"),
                    want,
                    (n.mean.len(), n.std.len()),
                ));
            }
            if n.std.iter().any(|s| !(s.is_finite() && *s > 0.0))
                || n.mean.iter().any(|m| !m.is_finite())
            {
                return Err(Error::config(
                    "stats",
                    format!("stats.{what} must be finite with std > 0"),
                ));
            }
            Ok(())
        };
        chk("fast", &self.fast, spec.fast_dim)?;
        chk("fast_diff", &self.fast_diff, spec.fast_dim)?;
        chk("slow", &self.slow, spec.slow.width())?;
        chk("action", &self.action, spec.action_dim)
    }

    /// Normalise actions in place (`[…, A]` rows).
    pub fn normalize_action(&self, a: &mut [f32]) {
        let n = &self.action;
        for row in a.chunks_mut(n.dim()) {
            for ((v, m), s) in row.iter_mut().zip(&n.mean).zip(&n.std) {
                *v = (*v - m) / s;
            }
        }
    }

    /// Denormalise actions in place (`[…, A]` rows).
    pub fn denormalize_action(&self, a: &mut [f32]) {
        let n = &self.action;
        for row in a.chunks_mut(n.dim()) {
            for ((v, m), s) in row.iter_mut().zip(&n.mean).zip(&n.std) {
                *v = *v * s + m;
            }
        }
    }

    /// Encode one sample's fast history `[n_obs, F]` (oldest first) into
    /// `[norm(o_t), norm_d(o_t − o_{t−1}), norm_d(o_{t−1} − o_{t−2}), …]` (`n_obs·F` values).
    pub fn encode_fast(&self, hist: &[f32], n_obs: usize, out: &mut [f32]) {
        let f = self.fast.dim();
        let last = &hist[(n_obs - 1) * f..n_obs * f];
        for j in 0..f {
            out[j] = (last[j] - self.fast.mean[j]) / self.fast.std[j];
        }
        for k in 1..n_obs {
            // k-th difference: o_{t−k+1} − o_{t−k}
            let newer = &hist[(n_obs - k) * f..(n_obs - k + 1) * f];
            let older = &hist[(n_obs - k - 1) * f..(n_obs - k) * f];
            for j in 0..f {
                out[k * f + j] =
                    (newer[j] - older[j] - self.fast_diff.mean[j]) / self.fast_diff.std[j];
            }
        }
    }

    /// Normalise one sample's slow features (`S` or `T·D` values) into `out`.
    pub fn encode_slow(&self, slow: &[f32], out: &mut [f32]) {
        let w = self.slow.dim();
        if w == 0 {
            return;
        }
        for (row, orow) in slow.chunks(w).zip(out.chunks_mut(w)) {
            for j in 0..w {
                orow[j] = (row[j] - self.slow.mean[j]) / self.slow.std[j];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_encoding_is_last_obs_and_differences() {
        let spec = Spec {
            horizon: 4,
            action_dim: 1,
            n_obs: 3,
            fast_dim: 2,
            slow: SlowSpec::None,
            d_vis_max: 0,
        };
        let mut st = Stats::identity(&spec);
        st.fast.mean = vec![1.0, 0.0];
        st.fast_diff.std = vec![2.0, 2.0];
        let hist = [0.0, 0.0, 1.0, 2.0, 3.0, 6.0]; // o_{t-2}, o_{t-1}, o_t
        let mut out = [0.0; 6];
        st.encode_fast(&hist, 3, &mut out);
        assert_eq!(out, [2.0, 6.0, 1.0, 2.0, 0.5, 1.0]);
    }

    #[test]
    fn action_normalisation_round_trips() {
        let spec = Spec {
            horizon: 2,
            action_dim: 2,
            n_obs: 1,
            fast_dim: 1,
            slow: SlowSpec::None,
            d_vis_max: 0,
        };
        let mut st = Stats::identity(&spec);
        st.action = Norm {
            mean: vec![1.0, -2.0],
            std: vec![0.5, 4.0],
        };
        let orig = [1.5, 2.0, 0.0, -6.0];
        let mut a = orig;
        st.normalize_action(&mut a);
        assert_eq!(a, [1.0, 1.0, -2.0, -1.0]);
        st.denormalize_action(&mut a);
        assert_eq!(a, orig);
    }

    #[test]
    fn spec_mismatch_names_the_field() {
        let a = Spec {
            horizon: 16,
            action_dim: 2,
            n_obs: 2,
            fast_dim: 3,
            slow: SlowSpec::None,
            d_vis_max: 0,
        };
        let b = Spec { fast_dim: 4, ..a };
        let e = a.expect_eq(&b).unwrap_err();
        assert!(
            matches!(
                e,
                Error::SpecMismatch {
                    field: "fast_dim",
                    ..
                }
            ),
            "{e}"
        );
    }
}
