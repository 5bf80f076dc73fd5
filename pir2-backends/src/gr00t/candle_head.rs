//! [`Gr00tCandleHead`]: the fine-tuned GR00T N1.7 action head run in candle, directly from a
//! `pir2 gr00t train` step directory, in place of the four ONNX graphs.
//!
//! It is a [`VelocityModel`] with exactly the ONNX stack's glue ([`super::Gr00tActionHead`]):
//! the normalised state padded to `max_state_dim` per history step, `x` padded to `A_max`,
//! GR00T's timestep bucket of every position's `τ` (a hidden front as 0), the state token at
//! the embodiment's state timestep, `d_vis` clamped to `d_vis_max` into the delay table, the
//! backbone tokens with the run's token layout; the network is
//! [`Gr00tN17Head::velocity`] itself. The backbone tokens it gets are post-`vlln` (the
//! backbone applies `vlln` and the VL self-attention), as the ONNX DiT gets them.

use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use pir2_runtime::{ModelInput, SlowInput, VelocityModel};

use super::config::{EmbodimentConfig, Normalizer};
use super::head::VlLayout;
use crate::error::{Error, Result};
use crate::gr00t::n17::{timestep_bucket, Gr00tN17Head, Timesteps, VlTokens};

/// GR00T N1.7's action head in candle behind the ONNX head's interface (module docs).
#[derive(Debug)]
pub struct Gr00tCandleHead {
    head: Gr00tN17Head,
    path: PathBuf,
    norm: Normalizer,
    embodiment_id: u32,
    horizon: usize,
    action_dim: usize,
    state_dim: usize,
    encoded_state_dim: usize,
    n_obs: usize,
    d_vis_max: usize,
    state_timestep: u32,
    layout: Option<VlLayout>,
    d_vis_counts: Vec<u64>,
}

impl Gr00tCandleHead {
    /// Load the head of `step` (`model.safetensors` with the delay table + `config.json`) on
    /// the CPU for the embodiment `cfg` with the statistics of `norm`, checking that the head
    /// serves the embodiment (history length, widths, slot, buckets, horizon, delay rows).
    pub fn load(
        step: &Path,
        cfg: &EmbodimentConfig,
        norm: Normalizer,
        embodiment_id: i64,
    ) -> Result<Self> {
        cfg.validate()?;
        let head = Gr00tN17Head::load(step, &Device::Cpu).map_err(|e| Error::Gr00tCandle {
            path: step.to_path_buf(),
            source: Box::new(e),
        })?;
        let c = head.config();
        let bad = |problem: String| {
            Error::Gr00tConfig(format!("candle head `{}`: {problem}", step.display()))
        };
        if cfg.n_obs != c.state_history_length {
            return Err(bad(format!(
                "state_history_length {} but the embodiment has n_obs = {}",
                c.state_history_length, cfg.n_obs
            )));
        }
        if cfg.encoded_state_dim() > c.max_state_dim || cfg.action_dim() > c.max_action_dim {
            return Err(bad(format!(
                "max_state_dim {} / max_action_dim {} cannot hold the embodiment's {} state / {} \
                 action values",
                c.max_state_dim,
                c.max_action_dim,
                cfg.encoded_state_dim(),
                cfg.action_dim()
            )));
        }
        if embodiment_id < 0 || embodiment_id as usize >= c.max_num_embodiments {
            return Err(bad(format!(
                "embodiment slot {embodiment_id} is not one of its 0..{} slots",
                c.max_num_embodiments
            )));
        }
        if cfg.num_timestep_buckets as usize != c.num_timestep_buckets {
            return Err(bad(format!(
                "num_timestep_buckets {} but the embodiment has {}",
                c.num_timestep_buckets, cfg.num_timestep_buckets
            )));
        }
        if c.add_pos_embed && cfg.horizon > c.max_seq_len {
            return Err(bad(format!(
                "the position embedding has {} rows, the embodiment's horizon is {}",
                c.max_seq_len, cfg.horizon
            )));
        }
        let rows = head.delay_embedding().map(|t| t.dims()[0]);
        if rows != Some(cfg.d_vis_max + 1) {
            return Err(bad(format!(
                "the delay table `action_head.delay_embedding.weight` has {} rows, the \
                 embodiment needs d_vis_max + 1 = {} (a base checkpoint has none: run a \
                 `pir2 gr00t train` step directory)",
                rows.map_or("no".to_string(), |r| r.to_string()),
                cfg.d_vis_max + 1
            )));
        }
        if norm.state_dim() != cfg.state_dim() {
            return Err(bad(format!(
                "the statistics have {} state values, the embodiment {}",
                norm.state_dim(),
                cfg.state_dim()
            )));
        }
        Ok(Gr00tCandleHead {
            head,
            path: step.to_path_buf(),
            norm,
            embodiment_id: embodiment_id as u32,
            horizon: cfg.horizon,
            action_dim: cfg.action_dim(),
            state_dim: cfg.state_dim(),
            encoded_state_dim: cfg.encoded_state_dim(),
            n_obs: cfg.n_obs,
            d_vis_max: cfg.d_vis_max,
            state_timestep: cfg.state_timestep() as u32,
            layout: None,
            d_vis_counts: vec![0; cfg.d_vis_max + 1],
        })
    }

    /// The backbone token width `D_vl` the head takes.
    pub fn d_vl(&self) -> usize {
        self.head.config().backbone_embedding_dim
    }

    /// The step directory the head was loaded from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Set the token layout of the backbone features.
    pub fn set_vl_layout(&mut self, layout: VlLayout) {
        self.layout = Some(layout);
    }

    /// How many calls saw each `d_vis` (after clamping to `d_vis_max`).
    pub fn d_vis_counts(&self) -> &[u64] {
        &self.d_vis_counts
    }

    fn candle(&self, e: impl Into<Error>) -> Error {
        Error::Gr00tCandle {
            path: self.path.clone(),
            source: Box::new(e.into()),
        }
    }

    /// One NFE; `out` is `[B, H, A]` (the velocity in the normalised action space).
    pub fn forward(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        input.validate()?;
        let (h, a, n_obs) = (self.horizon, self.action_dim, self.n_obs);
        super::head::check_call(input, (h, a, n_obs, self.state_dim), out.len())?;
        let chk = super::head::expect_size;
        let b = input.batch;
        let c = self.head.config().clone();
        let (msd, a_max, d_vl) = (c.max_state_dim, c.max_action_dim, c.backbone_embedding_dim);
        let (vl, t) = match input.slow {
            SlowInput::Tokens { data, tokens, dim } if dim == d_vl => (data, tokens),
            SlowInput::Vector { data, dim } if dim > 0 && dim % d_vl == 0 => (data, dim / d_vl),
            _ => {
                return Err(Error::input(
                    "backbone features",
                    format!("[B, T, {d_vl}] tokens"),
                    "another width or none",
                ))
            }
        };
        chk("backbone features [B,T,D_vl]", b * t * d_vl, vl.len())?;
        let layout = self.layout.as_ref().ok_or_else(|| {
            Error::Gr00tConfig("the candle head has no VL token layout (set_vl_layout)".into())
        })?;
        chk("VL layout masks (length T)", t, layout.image_mask.len())?;
        chk("VL layout masks (length T)", t, layout.attention_mask.len())?;

        let dev = Device::Cpu;
        let mut state = vec![0f32; b * n_obs * msd];
        let sd = self.state_dim;
        for k in 0..b * n_obs {
            let src = &input.obs_fast[k * sd..(k + 1) * sd];
            self.norm
                .normalize_state(src, &mut state[k * msd..k * msd + self.encoded_state_dim]);
        }
        let mut x = vec![0f32; b * h * a_max];
        for r in 0..b * h {
            x[r * a_max..r * a_max + a].copy_from_slice(&input.x[r * a..(r + 1) * a]);
        }
        let buckets = c.num_timestep_buckets;
        let t_act: Vec<u32> = input
            .tau
            .iter()
            .map(|&t| timestep_bucket(t, buckets))
            .collect();
        let mut t_tok = Vec::with_capacity(b * (1 + h));
        for bi in 0..b {
            t_tok.push(self.state_timestep);
            t_tok.extend_from_slice(&t_act[bi * h..(bi + 1) * h]);
        }
        let mut d_vis = Vec::with_capacity(b);
        for &d in input.d_vis {
            let d = (d as usize).min(self.d_vis_max);
            self.d_vis_counts[d] += 1;
            d_vis.push(d as u32);
        }
        let rep =
            |m: &[bool]| -> Vec<u8> { (0..b).flat_map(|_| m.iter().map(|&v| v as u8)).collect() };
        let (img, att) = (rep(&layout.image_mask), rep(&layout.attention_mask));
        let v = (|| -> crate::error::Result<Vec<f32>> {
            let state = Tensor::from_vec(state, (b, n_obs, msd), &dev)?;
            let x = Tensor::from_vec(x, (b, h, a_max), &dev)?;
            let t_act = Tensor::from_vec(t_act, (b, h), &dev)?;
            let t_tok = Tensor::from_vec(t_tok, (b, 1 + h), &dev)?;
            let emb = Tensor::from_vec(vec![self.embodiment_id; b], b, &dev)?;
            let vl = Tensor::from_slice(vl, (b, t, d_vl), &dev)?;
            let img = Tensor::from_vec(img, (b, t), &dev)?;
            let att = Tensor::from_vec(att, (b, t), &dev)?;
            let d_vis = Tensor::from_vec(d_vis, b, &dev)?;
            let tokens = VlTokens {
                embeddings: &vl,
                attention_mask: Some(&att),
                image_mask: Some(&img),
                d_vis: Some(&d_vis),
            };
            let s = self.head.encode_state(&state, &emb)?;
            let per = Timesteps::PerPosition {
                actions: &t_act,
                tokens: &t_tok,
            };
            let v = self.head.velocity(&s, &x, per, &tokens, &emb)?;
            Ok(v.narrow(2, 0, a)?.flatten_all()?.to_vec1::<f32>()?)
        })()
        .map_err(|e| self.candle(e))?;
        out.copy_from_slice(&v);
        super::head::ensure_finite(out)
    }
}

impl VelocityModel for Gr00tCandleHead {
    fn backend(&self) -> &'static str {
        "candle (GR00T N1.7 action head)"
    }

    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        self.forward(input, out).map_err(Into::into)
    }
}
