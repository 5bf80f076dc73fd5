//! `pir2 gr00t bench --train`: the wall-clock time of `pir2 gr00t train`'s training step on a
//! synthetic batch of the head's real shapes (feature `gr00t`).
//!
//! The head is loaded as `pir2 gr00t train` loads it ([`super::train::load_head`]: trainable,
//! delay table, per-position AdaLN heads for πR²) on the `--device` it names, with the
//! paper's recipe ([`super::train::train_config`]: the draws of the embodiment's policy, so
//! `τ` per position from πR²'s staircase for a πR² head). The data are synthetic and seeded:
//! episodes of random normalised states and actions of the embodiment's widths, and VL tokens
//! of the checkpoint's `backbone_embedding_dim`, `--vl-tokens` of them per frame (default:
//! the embodiment's `prompt.image_tokens + prompt.text_tokens`, the backbone's sequence),
//! the first `image_tokens` marked as image tokens, every one attended. Each step is the
//! trainer's own ([`Gr00tTrainer::time_steps`]): batch draw, upload, forward with GR00T's
//! dropout, loss, backward, grad-norm clip, AdamW.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pir2_backends::gr00t::n17::train::{Gr00tTrainer, VlFeatures};
use pir2_backends::train::Episode;
use serde::Serialize;

use super::train::{load_head, train_config, train_spec};
use crate::gr00t::Gr00tBenchOptions;

/// What `pir2 gr00t bench --train` measured (also its `--json`).
#[derive(Debug, Clone, Serialize)]
pub struct Gr00tTrainBench {
    /// The head's checkpoint directory.
    pub checkpoint: PathBuf,
    /// The candle device, as given.
    pub device: String,
    /// Samples per step.
    pub batch: usize,
    /// Untimed steps before the timed ones.
    pub warmup: usize,
    /// Timed steps.
    pub steps: usize,
    /// Chunk length `H`.
    pub horizon: usize,
    /// The robot's action width `A`.
    pub action_dim: usize,
    /// VL tokens per sample.
    pub vl_tokens: usize,
    /// Their width `D_vl`.
    pub vl_dim: usize,
    /// Trained parameters.
    pub parameters: usize,
    /// Whether GR00T's DiT dropout was on.
    pub dropout: bool,
    /// Median step time, ms (nearest rank).
    pub median_ms: f64,
    /// 90th percentile step time, ms (nearest rank).
    pub p90_ms: f64,
    /// Samples per second at the median step time.
    pub samples_per_s: f64,
    /// Every timed step, ms.
    pub step_ms: Vec<f64>,
    /// The last step's loss (synthetic data: only a check that it is finite).
    pub last_loss: f32,
}

/// In-memory VL tokens: a small pool of random frames, frame `i` is pool row `i % pool`.
struct SyntheticVl {
    frames: usize,
    tokens: usize,
    dim: usize,
    image_tokens: usize,
    pool: Vec<Vec<f32>>,
}

impl VlFeatures for SyntheticVl {
    fn frames(&self) -> usize {
        self.frames
    }
    fn tokens(&self) -> usize {
        self.tokens
    }
    fn dim(&self) -> usize {
        self.dim
    }
    fn read(
        &mut self,
        frame: usize,
        emb: &mut [f32],
        image_mask: &mut [f32],
        attention_mask: &mut [f32],
    ) -> pir2_backends::Result<()> {
        emb.copy_from_slice(&self.pool[frame % self.pool.len()]);
        for (i, m) in image_mask.iter_mut().enumerate() {
            *m = if i < self.image_tokens { 1.0 } else { 0.0 };
        }
        attention_mask.fill(1.0);
        Ok(())
    }
}

/// A seeded uniform draw in `[-1, 1)` (splitmix64).
fn uniform(seed: u64) -> impl FnMut() -> f32 {
    let mut s = seed ^ 0x9E37_79B9_7F4A_7C15;
    move || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
    }
}

/// The `q` quantile of sorted `xs` by nearest rank.
fn nearest_rank(xs: &[f64], q: f64) -> f64 {
    let k = ((q * xs.len() as f64).ceil() as usize).clamp(1, xs.len());
    xs[k - 1]
}

/// The embodiment file of `checkpoint`: `embodiment` if given, else `embodiment.toml` in the
/// checkpoint directory or the one above it (`pir2 gr00t example`'s `head/`, a
/// `pir2 gr00t train` step directory).
fn embodiment_file(checkpoint: &Path, embodiment: Option<&Path>) -> Result<PathBuf> {
    if let Some(e) = embodiment {
        return Ok(e.to_path_buf());
    }
    let here = checkpoint.join("embodiment.toml");
    let above = checkpoint.join("..").join("embodiment.toml");
    for p in [here, above] {
        if p.is_file() {
            return Ok(p);
        }
    }
    bail!(
        "no embodiment.toml in {} or the directory above it: pass --embodiment",
        checkpoint.display()
    )
}

/// `pir2 gr00t bench --train` (see the module docs).
pub fn bench_train(o: &Gr00tBenchOptions) -> Result<Gr00tTrainBench> {
    if o.batch == 0 || o.steps == 0 {
        bail!("--batch and --steps must be positive");
    }
    let emb_path = embodiment_file(&o.checkpoint, o.embodiment.as_deref())?;
    let (emb, head) = load_head(&o.checkpoint, &emb_path, &o.device)?;
    let c = head.config().clone();
    let tokens = o
        .vl_tokens
        .unwrap_or(emb.prompt.image_tokens + emb.prompt.text_tokens);
    if tokens == 0 {
        bail!("--vl-tokens must be positive");
    }
    let (h, a, sw) = (emb.horizon, emb.action_dim(), c.max_state_dim);
    let enc = emb.encoded_state_dim();
    let mut next = uniform(o.seed);
    // Episodes long enough that the draws have many frames to pick from.
    let (episodes, len) = (8, h + 24);
    let data: Vec<Episode> = (0..episodes)
        .map(|_| {
            let mut ep = Episode::new(sw, 0, a);
            let mut s = vec![0f32; sw];
            for _ in 0..len {
                s[..enc].iter_mut().for_each(|x| *x = next());
                let act: Vec<f32> = (0..a).map(|_| next()).collect();
                ep.push(&s, &[], &act);
            }
            ep
        })
        .collect();
    let d_vl = c.backbone_embedding_dim;
    let pool = (0..4)
        .map(|_| (0..tokens * d_vl).map(|_| next()).collect())
        .collect();
    let mut vl = SyntheticVl {
        frames: episodes * len,
        tokens,
        dim: d_vl,
        image_tokens: emb.prompt.image_tokens.min(tokens),
        pool,
    };
    let cfg = train_config(&emb, o.warmup + o.steps, o.batch, 1e-4, o.seed, None);
    let times = Gr00tTrainer::new(cfg, train_spec(&emb), std::env::temp_dir())
        .dropout(o.dropout)
        .time_steps(&head, &data, &mut vl, o.warmup, o.steps)
        .with_context(|| format!("training steps of {}", o.checkpoint.display()))?;
    let step_ms: Vec<f64> = times.seconds.iter().map(|s| s * 1e3).collect();
    let mut sorted = step_ms.clone();
    sorted.sort_by(f64::total_cmp);
    let median_ms = nearest_rank(&sorted, 0.5);
    Ok(Gr00tTrainBench {
        checkpoint: o.checkpoint.clone(),
        device: o.device.clone(),
        batch: o.batch,
        warmup: o.warmup,
        steps: o.steps,
        horizon: h,
        action_dim: a,
        vl_tokens: tokens,
        vl_dim: d_vl,
        parameters: times.parameters,
        dropout: o.dropout && c.dit.dropout > 0.0,
        median_ms,
        p90_ms: nearest_rank(&sorted, 0.9),
        samples_per_s: o.batch as f64 / (median_ms / 1e3),
        step_ms,
        last_loss: times.last_loss,
    })
}
