//! GR00T's training-time dropout in the DiT, with masks that are a pure function of
//! `(seed, step, site)`.

use candle_core::Tensor;
use rayon::prelude::*;

use super::config::DitConfig;
use crate::error::{Error, Result};

/// Where in a DiT block a dropout mask applies (GR00T N1.7's `BasicTransformerBlock` with
/// diffusers' `Attention` and `FeedForward`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DropoutSite {
    /// The attention output after its projection (`attn1.to_out.1`), block `i`.
    Attention(usize),
    /// The block's `final_dropout`, applied to the attention output a second time, block `i`.
    AttentionFinal(usize),
    /// The feed-forward's hidden activations after GELU (`ff.net.1`), block `i`.
    FeedForwardInner(usize),
    /// The feed-forward's output (`ff.net.3`, present with `final_dropout`), block `i`.
    FeedForwardOutput(usize),
}

impl DropoutSite {
    /// A distinct integer per site (`4 · block + kind`).
    fn id(self) -> u64 {
        let (block, kind) = match self {
            Self::Attention(b) => (b, 0),
            Self::AttentionFinal(b) => (b, 1),
            Self::FeedForwardInner(b) => (b, 2),
            Self::FeedForwardOutput(b) => (b, 3),
        };
        4 * block as u64 + kind
    }
}

/// The training forward's dropout in the DiT blocks, as GR00T N1.7 applies it when the DiT
/// is trained (`diffusion_model_cfg.dropout` = `p`, `final_dropout`): each dropped value is
/// zeroed with probability `p` and each kept one scaled by `1/(1 − p)` (PyTorch's
/// `nn.Dropout`), at the sites of [`DropoutSite`]:
///
/// - the attention output after `to_out.0` (`to_out.1`), in every block, self- or
///   cross-attending;
/// - with `final_dropout`, that attention output once more (the block's own
///   `final_dropout` module), with an independent mask;
/// - the feed-forward's hidden activations after GELU (`ff.net.1`);
/// - with `final_dropout`, the feed-forward's output (`ff.net.3`).
///
/// The attention probabilities are not dropped (GR00T calls SDPA with `dropout_p = 0`), nor
/// the timestep encoder, the output modulation, the projectors or the position embedding.
///
/// Every mask is a pure function of `(seed, step, site)` and the element's index: a
/// counter-based hash (SplitMix64), no random state. The same seed and step give the same
/// bits, and a resumed run draws the masks the uninterrupted one drew.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DitDropout {
    /// Drop probability `p` in `[0, 1)`.
    pub rate: f64,
    /// Also the second attention mask and the feed-forward output's.
    pub final_dropout: bool,
    /// The run's seed.
    pub seed: u64,
    /// The optimiser step the forward belongs to.
    pub step: u64,
}

/// SplitMix64's output function.
fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// SplitMix64's increment.
const GAMMA: u64 = 0x9e37_79b9_7f4a_7c15;
/// Separates these draws from any other stream keyed by the same seed.
const DOMAIN: u64 = 0x6472_6f70_6f75_7431; // "dropout1"
/// Values filled per rayon task.
const CHUNK: usize = 1 << 15;

impl DitDropout {
    /// The DiT configuration's dropout (`dit.dropout`, `dit.final_dropout`) for step `step` of
    /// a run seeded `seed`.
    pub fn from_config(dit: &DitConfig, seed: u64, step: u64) -> Self {
        Self {
            rate: dit.dropout,
            final_dropout: dit.final_dropout,
            seed,
            step,
        }
    }

    /// Whether any value can be dropped (`rate > 0`); a zero rate makes the training forward
    /// the inference forward.
    pub fn is_active(&self) -> bool {
        self.rate > 0.0
    }

    fn check(&self) -> Result<()> {
        if (0.0..1.0).contains(&self.rate) {
            Ok(())
        } else {
            Err(Error::config(
                "diffusion_model_cfg.dropout",
                format!("{} must be in [0, 1)", self.rate),
            ))
        }
    }

    /// The multipliers of `n` values at `site`: `0` (dropped, probability `rate`) or
    /// `1/(1 − rate)`, element `i` a function of `(seed, step, site, i)` only.
    pub fn mask(&self, site: DropoutSite, n: usize) -> Result<Vec<f32>> {
        self.check()?;
        let scale = (1.0 / (1.0 - self.rate)) as f32;
        let key = mix(mix(mix(self.seed ^ DOMAIN) ^ self.step) ^ site.id());
        // Drop `i` when its 53-bit uniform in [0, 1) is below the rate.
        let rate = self.rate;
        let mut out = vec![0f32; n];
        out.par_chunks_mut(CHUNK).enumerate().for_each(|(c, ch)| {
            let first = (c * CHUNK) as u64;
            for (j, o) in ch.iter_mut().enumerate() {
                let u = mix(key.wrapping_add((first + j as u64).wrapping_mul(GAMMA)));
                let uniform = (u >> 11) as f64 * (1.0 / (1u64 << 53) as f64);
                *o = if uniform < rate { 0.0 } else { scale };
            }
        });
        Ok(out)
    }

    /// `x` with the mask of `site` applied (unchanged when the rate is zero).
    pub(super) fn apply(&self, x: &Tensor, site: DropoutSite) -> Result<Tensor> {
        self.check()?;
        if !self.is_active() {
            return Ok(x.clone());
        }
        let m = Tensor::from_vec(self.mask(site, x.elem_count())?, x.shape(), x.device())?
            .to_dtype(x.dtype())?;
        Ok(x.mul(&m)?)
    }
}
