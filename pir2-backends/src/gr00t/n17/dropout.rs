//! GR00T's training-time dropout in the DiT, with masks that are a pure function of
//! `(seed, step, site)`.

use candle_core::{DType, Device, Shape, Tensor};
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
/// Every mask is a pure function of `(seed, step, site)` and the element's index, no random
/// state: the same seed and step give the same bits, and a resumed run draws the masks the
/// uninterrupted one drew. Two constructions ([`MaskSource`]): on the CPU the host's
/// per-element SplitMix64 hash ([`Self::mask`]); on any other device a hash evaluated there
/// with exact `u32` tensor ops, so that no mask crosses from the host
/// ([`Self::mask_tensor`]).
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

/// How a mask is built ([`DitDropout::mask_tensor`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MaskSource {
    /// On the host, element `i` from SplitMix64 of `(seed, step, site, i)` ([`DitDropout::mask`]),
    /// then uploaded: `n` values cross to the device.
    Host,
    /// On the tensor's device. For a mask of shape `[.., C]` read as `R × C` (`C` the last
    /// dimension), the host draws three residues modulo the prime [`DEVICE_MODULUS`]
    /// (`P = 32749`) per row and per column from SplitMix64 of `(seed, step, site, lane,
    /// row or column)`, `6·(R + C)` values in all; the device forms
    /// `x = (a₀·b₀ + a₁·b₁ + a₂·b₂) mod P` per element (below `2³²` before the reduction,
    /// so every `u32` op is exact on every backend) and drops the element when
    /// `x < round(p·P)`. Two distinct elements' `x` are independent and uniform on
    /// `0..P` (a linear map of independent uniform residues, invertible but for events of
    /// probability `~1/P²`), so the drop rate
    /// is `p` rounded to a multiple of `1/P` (within `1.6·10⁻⁵`). The bits differ from
    /// [`MaskSource::Host`]'s; they are the same on every device, integer ops and one `f32`
    /// multiplication being exact everywhere.
    Device,
}

impl MaskSource {
    /// What the training forward uses on `device`: [`MaskSource::Host`] on the CPU (its
    /// masks are the ones CPU runs have always drawn), [`MaskSource::Device`] elsewhere.
    pub fn for_device(device: &Device) -> Self {
        if device.is_cpu() {
            Self::Host
        } else {
            Self::Device
        }
    }
}

/// The prime modulus of [`MaskSource::Device`]'s masks: `3·(P − 1)² < 2³²`.
pub const DEVICE_MODULUS: u32 = 32_749;

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
/// Separates the device masks' per-row and per-column residues.
const DEVICE_DOMAIN: u64 = 0x6465_7669_6365_6d6b; // "devicemk"
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
        let key = self.key(site);
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

    /// The key of `site`'s mask at this seed and step.
    fn key(&self, site: DropoutSite) -> u64 {
        mix(mix(mix(self.seed ^ DOMAIN) ^ self.step) ^ site.id())
    }

    /// The `f32` mask of `site` for a tensor of shape `shape` on `device`, built as `source`
    /// says: [`MaskSource::Host`] is [`Self::mask`] (flat index order) uploaded;
    /// [`MaskSource::Device`] is computed on `device` from `6·(R + C)` uploaded residues
    /// (see there). Either way a pure function of `(seed, step, site, shape)`.
    pub fn mask_tensor(
        &self,
        site: DropoutSite,
        shape: impl Into<Shape>,
        device: &Device,
        source: MaskSource,
    ) -> Result<Tensor> {
        let shape = shape.into();
        match source {
            MaskSource::Host => Ok(Tensor::from_vec(
                self.mask(site, shape.elem_count())?,
                shape,
                device,
            )?),
            MaskSource::Device => self.device_mask(site, shape, device),
        }
    }

    fn device_mask(&self, site: DropoutSite, shape: Shape, device: &Device) -> Result<Tensor> {
        self.check()?;
        let scale = (1.0 / (1.0 - self.rate)) as f32;
        let n = shape.elem_count();
        let cols = shape.dims().last().copied().unwrap_or(1);
        if n == 0 {
            return Ok(Tensor::zeros(shape, DType::F32, device)?);
        }
        let rows = n / cols;
        let key = mix(self.key(site) ^ DEVICE_DOMAIN);
        let p = DEVICE_MODULUS as u64;
        // Residues `0..P` of lane `lane` for `len` rows (`which` 0) or columns (1).
        let residues = |which: u64, lane: u64, len: usize| -> Vec<u32> {
            let k = mix(mix(key ^ which) ^ lane);
            (0..len as u64)
                .map(|i| (mix(k.wrapping_add(i.wrapping_mul(GAMMA))) % p) as u32)
                .collect()
        };
        // `a_l·b_l` as a `[rows, cols]` tensor; each term is below `P²`, their sum below 2³².
        let lane = |l: u64| -> Result<Tensor> {
            let a = Tensor::from_vec(residues(0, l, rows), (rows, 1), device)?;
            let b = Tensor::from_vec(residues(1, l, cols), (1, cols), device)?;
            Ok(a.broadcast_mul(&b)?)
        };
        let x = ((lane(0)? + lane(1)?)? + lane(2)?)?;
        let modulus = Tensor::new(DEVICE_MODULUS, device)?;
        let x = (&x - x.broadcast_div(&modulus)?.broadcast_mul(&modulus)?)?;
        let threshold = (self.rate * DEVICE_MODULUS as f64).round() as u32;
        let keep = x.broadcast_ge(&Tensor::new(threshold, device)?)?;
        Ok(keep
            .to_dtype(DType::F32)?
            .broadcast_mul(&Tensor::new(scale, device)?)?
            .reshape(shape)?)
    }

    /// `x` with the mask of `site` applied (unchanged when the rate is zero), the mask built
    /// as [`MaskSource::for_device`] says for `x`'s device.
    pub(super) fn apply(&self, x: &Tensor, site: DropoutSite) -> Result<Tensor> {
        self.check()?;
        if !self.is_active() {
            return Ok(x.clone());
        }
        let m = self
            .mask_tensor(
                site,
                x.shape(),
                x.device(),
                MaskSource::for_device(x.device()),
            )?
            .to_dtype(x.dtype())?;
        Ok(x.mul(&m)?)
    }
}
