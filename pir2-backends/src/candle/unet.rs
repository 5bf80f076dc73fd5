//! Conditional U-Net 1D (diffusion-policy design) with per-position FiLM.
//!
//! Layout (widths `[w0, w1, …]`, one halving per level): per level two residual blocks
//! (Conv1d → GroupNorm → Mish, FiLM, Conv1d → GroupNorm → Mish, + 1×1 residual), then a
//! stride-2 conv; two middle blocks; on the way up the skip is concatenated, two blocks, then
//! nearest ×2 + conv3 (candle has no backward for `conv_transpose1d`; this replaces
//! diffusion-policy's transposed conv); a final conv block and a 1×1 conv to `A`.
//!
//! Conditioning: global = `[encoded fast history, slow (token mean), e(d_vis)]`; per-position
//! `τ` embedding `e_p = MLP(sin/cos(1000 τ_p), hidden_p)`. FiLM of a block at resolution `L`:
//! `h ← (1 + γ)·h + β` with `(γ, β) = W_s·mish([mean_p e_p, global]) + W_p·mish(pool_L(e)_l)` — the second (per-position)
//! term is zero-initialised and absent in [`FilmMode::Shared`], so a fresh model, or one
//! finetuned from a shared-FiLM checkpoint, starts position-uniform.

use candle_core::{Module, Tensor};

use super::layers::{mish, sinusoidal_tau, CResult, Conv1d, GroupNorm, ParamStore};
use super::Inputs;
use crate::config::{FilmMode, Spec, UNetConfig};

#[derive(Debug)]
struct ConvBlock {
    conv: Conv1d,
    gn: GroupNorm,
}

impl ConvBlock {
    fn new(
        ps: &mut ParamStore,
        name: &str,
        cin: usize,
        cout: usize,
        k: usize,
        groups: usize,
    ) -> CResult<Self> {
        Ok(Self {
            conv: ps.conv1d(&format!("{name}.conv"), cin, cout, k, 1)?,
            gn: ps.group_norm(&format!("{name}.gn"), groups, cout)?,
        })
    }
    fn forward(&self, x: &Tensor) -> CResult<Tensor> {
        mish(&self.gn.forward(&self.conv.forward(x)?)?)
    }
}

#[derive(Debug)]
struct ResBlock {
    b0: ConvBlock,
    b1: ConvBlock,
    film: candle_nn::Linear,
    film_pos: Option<candle_nn::Linear>,
    res: Option<Conv1d>,
    cout: usize,
}

struct Cond<'a> {
    /// `mish([mean τ-embedding, global])`: `[B, E + G]`.
    shared: &'a Tensor,
    /// `mish(pooled τ-embedding)` at this block's resolution: `[B, L, E]`.
    pos: Option<&'a Tensor>,
}

impl ResBlock {
    #[allow(clippy::too_many_arguments)]
    fn new(
        ps: &mut ParamStore,
        name: &str,
        cin: usize,
        cout: usize,
        k: usize,
        groups: usize,
        cs: usize,
        e: usize,
        film: FilmMode,
    ) -> CResult<Self> {
        let b0 = ConvBlock::new(ps, &format!("{name}.block0"), cin, cout, k, groups)?;
        let b1 = ConvBlock::new(ps, &format!("{name}.block1"), cout, cout, k, groups)?;
        let film_l = ps.linear(&format!("{name}.film"), cs, 2 * cout)?;
        let film_pos = match film {
            FilmMode::PerPosition => {
                Some(ps.linear_zero(&format!("{name}.film_pos"), e, 2 * cout)?)
            }
            FilmMode::Shared => None,
        };
        let res = if cin != cout {
            Some(ps.conv1d(&format!("{name}.res"), cin, cout, 1, 1)?)
        } else {
            None
        };
        Ok(Self {
            b0,
            b1,
            film: film_l,
            film_pos,
            res,
            cout,
        })
    }

    /// FiLM parameters `[B, 2, C, L]` (scale, bias) for a block at length `l`.
    fn film_params(&self, c: &Cond<'_>, l: usize) -> CResult<Tensor> {
        let b = c.shared.dim(0)?;
        let shared = self.film.forward(c.shared)?.reshape((b, 2, self.cout, 1))?;
        match (&self.film_pos, c.pos) {
            (Some(fp), Some(pos)) => {
                let p = fp
                    .forward(pos)?
                    .transpose(1, 2)?
                    .reshape((b, 2, self.cout, l))?;
                p.broadcast_add(&shared)
            }
            _ => shared.broadcast_as((b, 2, self.cout, l))?.contiguous(),
        }
    }

    fn forward(&self, x: &Tensor, c: &Cond<'_>) -> CResult<Tensor> {
        let out = self.b0.forward(x)?;
        let (b, _, l) = out.dims3()?;
        let f = self.film_params(c, l)?;
        let scale = f.narrow(1, 0, 1)?.reshape((b, self.cout, l))?;
        let bias = f.narrow(1, 1, 1)?.reshape((b, self.cout, l))?;
        let out = self.b1.forward(&((out * (scale + 1.0)?)? + bias)?)?;
        match &self.res {
            Some(r) => out + r.forward(x)?,
            None => out + x,
        }
    }
}

#[derive(Debug)]
struct Level {
    r0: ResBlock,
    r1: ResBlock,
    /// Down: stride-2 conv. Up: conv3 after nearest ×2.
    resample: Option<Conv1d>,
}

#[derive(Debug)]
pub(crate) struct UNet {
    tau_l0: candle_nn::Linear,
    tau_l1: candle_nn::Linear,
    dvis: candle_nn::Embedding,
    down: Vec<Level>,
    mid: [ResBlock; 2],
    up: Vec<Level>,
    final_block: ConvBlock,
    final_conv: Conv1d,
    tau_dim: usize,
    film: FilmMode,
    h: usize,
    a: usize,
}

impl UNet {
    pub(crate) fn new(ps: &mut ParamStore, spec: &Spec, c: &UNetConfig) -> CResult<Self> {
        let e = c.tau_dim;
        let tau_l0 = ps.linear("tau_mlp.0", e + 1, 4 * e)?;
        let tau_l1 = ps.linear("tau_mlp.1", 4 * e, e)?;
        let dvis = ps.embedding_zero("dvis_embed", spec.d_vis_max + 1, c.dvis_dim)?;
        let g = spec.fast_encoded_dim() + spec.slow.width() + c.dvis_dim;
        let cs = e + g;
        let (k, gr) = (c.kernel, c.groups);
        let mut dims = vec![spec.action_dim];
        dims.extend_from_slice(&c.widths);
        let n = c.widths.len();
        let mut down = Vec::with_capacity(n);
        for i in 0..n {
            let (din, dout) = (dims[i], dims[i + 1]);
            let nm = format!("down.{i}");
            down.push(Level {
                r0: ResBlock::new(ps, &format!("{nm}.res0"), din, dout, k, gr, cs, e, c.film)?,
                r1: ResBlock::new(ps, &format!("{nm}.res1"), dout, dout, k, gr, cs, e, c.film)?,
                resample: if i + 1 < n {
                    Some(ps.conv1d(&format!("{nm}.down"), dout, dout, 3, 2)?)
                } else {
                    None
                },
            });
        }
        let wmax = c.widths[n - 1];
        let mid = [
            ResBlock::new(ps, "mid.0", wmax, wmax, k, gr, cs, e, c.film)?,
            ResBlock::new(ps, "mid.1", wmax, wmax, k, gr, cs, e, c.film)?,
        ];
        let mut up = Vec::with_capacity(n.saturating_sub(1));
        for (j, i) in (1..n).rev().enumerate() {
            let (din, dout) = (dims[i], dims[i + 1]);
            let nm = format!("up.{j}");
            up.push(Level {
                r0: ResBlock::new(
                    ps,
                    &format!("{nm}.res0"),
                    2 * dout,
                    din,
                    k,
                    gr,
                    cs,
                    e,
                    c.film,
                )?,
                r1: ResBlock::new(ps, &format!("{nm}.res1"), din, din, k, gr, cs, e, c.film)?,
                resample: Some(ps.conv1d(&format!("{nm}.up"), din, din, 3, 1)?),
            });
        }
        let w0 = c.widths[0];
        let final_block = ConvBlock::new(ps, "final.block", w0, w0, k, gr)?;
        let final_conv = ps.conv1d("final.conv", w0, spec.action_dim, 1, 1)?;
        Ok(Self {
            tau_l0,
            tau_l1,
            dvis,
            down,
            mid,
            up,
            final_block,
            final_conv,
            tau_dim: e,
            film: c.film,
            h: spec.horizon,
            a: spec.action_dim,
        })
    }

    /// Shared conditioning `[B, E+G]` and the full-resolution per-position term `[B, H, E]`.
    fn conditioning(&self, inp: &Inputs) -> CResult<(Tensor, Tensor)> {
        let b = inp.b;
        let mut sin = Vec::new();
        sinusoidal_tau(&inp.tau, self.tau_dim, &mut sin);
        let s = Tensor::from_vec(
            sin,
            (b, self.h, self.tau_dim + 1),
            &candle_core::Device::Cpu,
        )?;
        let emb = self.tau_l1.forward(&mish(&self.tau_l0.forward(&s)?)?)?; // [B, H, E]
        let mean = emb.mean(1)?; // [B, E]
        let mut parts = vec![mean, inp.fast.clone()];
        if let Some(sl) = &inp.slow {
            parts.push(sl.mean(1)?);
        }
        parts.push(self.dvis.forward(&inp.dvis)?);
        let shared = mish(&Tensor::cat(&parts, 1)?)?;
        Ok((shared, mish(&emb)?))
    }

    /// Per-position term pooled to length `l`.
    fn pool(pos: &Tensor, l: usize) -> CResult<Tensor> {
        let (b, h, e) = pos.dims3()?;
        if l == h {
            return Ok(pos.clone());
        }
        pos.reshape((b, l, h / l, e))?.mean(2)
    }

    pub(crate) fn forward(&self, inp: &Inputs) -> CResult<Tensor> {
        let (shared, pos) = self.conditioning(inp)?;
        let per_pos = self.film == FilmMode::PerPosition;
        let n = self.down.len();
        let pooled: Vec<Option<Tensor>> = (0..n)
            .map(|i| {
                if per_pos {
                    Self::pool(&pos, self.h >> i).map(Some)
                } else {
                    Ok(None)
                }
            })
            .collect::<CResult<_>>()?;
        let cond = |lvl: usize| Cond {
            shared: &shared,
            pos: pooled[lvl].as_ref(),
        };
        let mut x = inp.x.transpose(1, 2)?.contiguous()?; // [B, A, H]
        let mut skips = Vec::with_capacity(n);
        for (i, lv) in self.down.iter().enumerate() {
            x = lv.r0.forward(&x, &cond(i))?;
            x = lv.r1.forward(&x, &cond(i))?;
            skips.push(x.clone());
            if let Some(d) = &lv.resample {
                x = d.forward(&x)?;
            }
        }
        for m in &self.mid {
            x = m.forward(&x, &cond(n - 1))?;
        }
        for (j, lv) in self.up.iter().enumerate() {
            let lvl = n - 1 - j;
            let skip = skips.pop().expect("one skip per level");
            x = Tensor::cat(&[&x, &skip], 1)?;
            x = lv.r0.forward(&x, &cond(lvl))?;
            x = lv.r1.forward(&x, &cond(lvl))?;
            if let Some(u) = &lv.resample {
                let (b, c, l) = x.dims3()?;
                let up = x
                    .unsqueeze(3)?
                    .broadcast_as((b, c, l, 2))?
                    .reshape((b, c, 2 * l))?;
                x = u.forward(&up)?;
            }
        }
        let y = self.final_conv.forward(&self.final_block.forward(&x)?)?; // [B, A, H]
        y.transpose(1, 2)?
            .contiguous()?
            .reshape((inp.b, self.h, self.a))
    }

    /// FiLM parameters of every residual block (tests: position-uniform at init).
    #[cfg(test)]
    pub(crate) fn all_film_params(&self, inp: &Inputs) -> CResult<Vec<Tensor>> {
        let (shared, pos) = self.conditioning(inp)?;
        let mut out = Vec::new();
        for (i, lv) in self.down.iter().enumerate() {
            let l = self.h >> i;
            let p = Self::pool(&pos, l)?;
            let c = Cond {
                shared: &shared,
                pos: if self.film == FilmMode::PerPosition {
                    Some(&p)
                } else {
                    None
                },
            };
            out.push(lv.r0.film_params(&c, l)?);
            out.push(lv.r1.film_params(&c, l)?);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::super::CandleModel;
    use crate::config::{Config, ModelConfig, SlowSpec, Spec, Stats, UNetConfig};
    use pir2_runtime::model::{ModelInput, SlowInput};

    #[test]
    fn per_position_film_starts_position_uniform() {
        let spec = Spec {
            horizon: 8,
            action_dim: 3,
            n_obs: 2,
            fast_dim: 4,
            slow: SlowSpec::None,
            d_vis_max: 1,
        };
        let cfg = Config {
            spec,
            model: ModelConfig::UNet(UNetConfig {
                widths: vec![8, 16],
                kernel: 3,
                groups: 4,
                tau_dim: 8,
                dvis_dim: 2,
                ..Default::default()
            }),
        };
        let mut m = CandleModel::new(cfg, Stats::identity(&spec), 0).unwrap();
        let x = vec![0.3; 2 * 8 * 3];
        let tau: Vec<f32> = (0..16)
            .map(|i| {
                if i % 8 == 0 {
                    -1.0
                } else {
                    (i % 8) as f32 / 8.0
                }
            })
            .collect();
        let obs: Vec<f32> = (0..16).map(|i| i as f32 * 0.1).collect();
        let input = ModelInput {
            batch: 2,
            horizon: 8,
            action_dim: 3,
            x: &x,
            tau: &tau,
            obs_fast: &obs,
            n_obs: 2,
            fast_dim: 4,
            slow: SlowInput::None,
            d_vis: &[0, 1],
        };
        let inp = m.encode(&input).unwrap();
        let super::super::Arch::UNet(u) = &m.net else {
            panic!("not a U-Net")
        };
        let films = u.all_film_params(&inp).unwrap();
        assert_eq!(films.len(), 4);
        for f in films {
            let (b, two, c, l) = f.dims4().unwrap();
            let v = f.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let mut nonzero = false;
            for i in 0..b * two * c {
                let row = &v[i * l..(i + 1) * l];
                nonzero |= row[0] != 0.0;
                assert!(
                    row.iter().all(|&r| r == row[0]),
                    "modulation varies over positions at init: {row:?}"
                );
            }
            assert!(nonzero, "the shared FiLM pair must not be trivially zero");
        }
        // After a perturbation of the per-position weights the modulation does vary.
        for (n, var) in m.vars() {
            if n.contains("film_pos.weight") {
                var.set(&(var.as_tensor().ones_like().unwrap() * 0.1).unwrap())
                    .unwrap();
            }
        }
        let super::super::Arch::UNet(u) = &m.net else {
            panic!("not a U-Net")
        };
        let f = &u.all_film_params(&inp).unwrap()[0];
        let v = f.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_ne!(v[0], v[1]);
    }
}
