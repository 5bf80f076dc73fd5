//! Conditional U-Net 1D (diffusion-policy design) with per-position FiLM.
//!
//! Activations are channels-last `[B, L, C]` throughout. Layout (widths `[w0, w1, …]`, one halving per level): per level two residual blocks
//! (Conv1d → GroupNorm → Mish, FiLM, Conv1d → GroupNorm → Mish, + 1×1 residual), then a
//! stride-2 conv; two middle blocks; on the way up the skip is concatenated, two blocks, then
//! nearest ×2 + conv3 (candle has no backward for `conv_transpose1d`; this replaces
//! diffusion-policy's transposed conv); a final conv block and a 1×1 conv to `A`.
//!
//! Conditioning: global = `[encoded fast history, slow (token mean), e(d_vis)]`; per-position
//! `τ` embedding `e_p = MLP(sin/cos(1000 τ_p), hidden_p)`. FiLM of a block at resolution `L`:
//! `h ← (1 + γ)·h + β`, with `(γ, β)` per [`FilmMode`]:
//! - `Shared`: `W·[mish(mean_p e_p), global]`, one pair per sample (the baselines);
//! - `PerPositionHeads` (the paper's): `W_l·[mish(ē_l), global]` with one head `W_l` per slot `l`
//!   of the block's resolution, `ē_l` the mean embedding over the chunk positions the slot
//!   covers (one position at full resolution); every `W_l` starts as a copy of the shared head;
//! - `PerPositionTau` (ablation): `W·[mish(mean_p e_p), global] + W_p·mean_l(mish(e))`, `W_p`
//!   zero-initialised and shared by all slots.
//!
//! Both per-position variants start position-uniform at a uniform `τ`, fresh or finetuned from
//! a shared-FiLM checkpoint.

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
    /// The shared head (absent with per-position heads).
    film: Option<candle_nn::Linear>,
    film_pos: Option<candle_nn::Linear>,
    /// Per-slot heads: weight `[L, 2C, E+G]`, bias `[L, 2C]`.
    heads: Option<(Tensor, Tensor)>,
    res: Option<Conv1d>,
    cout: usize,
}

struct Cond<'a> {
    /// `[mish(mean τ-embedding), global]`: `[B, E + G]`.
    shared: &'a Tensor,
    /// `mish(pooled τ-embedding)` at this block's resolution: `[B, L, E]` (ablation).
    pos: Option<&'a Tensor>,
    /// Per-slot head inputs `[mish(ē_l), global]`, slot-major: `[L, B, E+G]` (heads).
    heads_in: Option<&'a Tensor>,
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
        l: usize,
    ) -> CResult<Self> {
        let b0 = ConvBlock::new(ps, &format!("{name}.block0"), cin, cout, k, groups)?;
        let b1 = ConvBlock::new(ps, &format!("{name}.block1"), cout, cout, k, groups)?;
        let (film_l, heads) = match film {
            FilmMode::PerPositionHeads => (
                None,
                Some(ps.linear_heads(&format!("{name}.film_heads"), l, cs, 2 * cout)?),
            ),
            _ => (
                Some(ps.linear(&format!("{name}.film"), cs, 2 * cout)?),
                None,
            ),
        };
        let film_pos = match film {
            FilmMode::PerPositionTau => {
                Some(ps.linear_zero(&format!("{name}.film_pos"), e, 2 * cout)?)
            }
            _ => None,
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
            heads,
            res,
            cout,
        })
    }

    /// FiLM parameters `[B, L, 2C]` (scale, bias) for a block at length `l` (channels-last).
    fn film_params(&self, c: &Cond<'_>, l: usize) -> CResult<Tensor> {
        let b = c.shared.dim(0)?;
        if let (Some((w, bias)), Some(u)) = (&self.heads, c.heads_in) {
            // [L, B, cs] × [L, cs, 2C] → [L, B, 2C] → [B, L, 2C]
            let f = u
                .matmul(&w.transpose(1, 2)?)?
                .broadcast_add(&bias.unsqueeze(1)?)?;
            return f.transpose(0, 1)?.contiguous();
        }
        let film = self.film.as_ref().ok_or_else(|| {
            candle_core::Error::Msg("per-position FiLM heads without their inputs".into())
        })?;
        let shared = film.forward(c.shared)?.unsqueeze(1)?; // [B, 1, 2C]
        match (&self.film_pos, c.pos) {
            (Some(fp), Some(pos)) => fp.forward(pos)?.broadcast_add(&shared),
            _ => shared.broadcast_as((b, l, 2 * self.cout))?.contiguous(),
        }
    }

    fn forward(&self, x: &Tensor, c: &Cond<'_>) -> CResult<Tensor> {
        let out = self.b0.forward(x)?;
        let l = out.dim(1)?;
        let f = self.film_params(c, l)?;
        let scale = f.narrow(2, 0, self.cout)?;
        let bias = f.narrow(2, self.cout, self.cout)?;
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
            let lv = spec.horizon >> i;
            down.push(Level {
                r0: ResBlock::new(
                    ps,
                    &format!("{nm}.res0"),
                    din,
                    dout,
                    k,
                    gr,
                    cs,
                    e,
                    c.film,
                    lv,
                )?,
                r1: ResBlock::new(
                    ps,
                    &format!("{nm}.res1"),
                    dout,
                    dout,
                    k,
                    gr,
                    cs,
                    e,
                    c.film,
                    lv,
                )?,
                resample: if i + 1 < n {
                    Some(ps.conv1d(&format!("{nm}.down"), dout, dout, 3, 2)?)
                } else {
                    None
                },
            });
        }
        let wmax = c.widths[n - 1];
        let lmid = spec.horizon >> (n - 1);
        let mid = [
            ResBlock::new(ps, "mid.0", wmax, wmax, k, gr, cs, e, c.film, lmid)?,
            ResBlock::new(ps, "mid.1", wmax, wmax, k, gr, cs, e, c.film, lmid)?,
        ];
        let mut up = Vec::with_capacity(n.saturating_sub(1));
        for (j, i) in (1..n).rev().enumerate() {
            let (din, dout) = (dims[i], dims[i + 1]);
            let nm = format!("up.{j}");
            let lv = spec.horizon >> i;
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
                    lv,
                )?,
                r1: ResBlock::new(
                    ps,
                    &format!("{nm}.res1"),
                    din,
                    din,
                    k,
                    gr,
                    cs,
                    e,
                    c.film,
                    lv,
                )?,
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

    /// Shared conditioning `[B, E+G]` and the raw per-position `τ` embedding `[B, H, E]`.
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
                                 // Mish on the τ part only: on raw normalised observations it would fold negative
                                 // values together (mish is not monotonic below −1.2).
        let mut parts = vec![mish(&mean)?, inp.fast.clone()];
        if let Some(sl) = &inp.slow {
            parts.push(sl.mean(1)?);
        }
        parts.push(self.dvis.forward(&inp.dvis)?);
        let shared = Tensor::cat(&parts, 1)?;
        Ok((shared, emb))
    }

    /// The per-level conditioning of the per-position variants: `(ablation term, head inputs)`
    /// for each level (see the module docs).
    #[allow(clippy::type_complexity)]
    fn level_conditioning(
        &self,
        shared: &Tensor,
        emb: &Tensor,
    ) -> CResult<(Vec<Option<Tensor>>, Vec<Option<Tensor>>)> {
        let n = self.down.len();
        match self.film {
            FilmMode::Shared => Ok((vec![None; n], vec![None; n])),
            FilmMode::PerPositionTau => {
                let pos = mish(emb)?;
                let pooled = (0..n)
                    .map(|i| Self::pool(&pos, self.h >> i).map(Some))
                    .collect::<CResult<_>>()?;
                Ok((pooled, vec![None; n]))
            }
            FilmMode::PerPositionHeads => {
                let (b, cs) = shared.dims2()?;
                let e = self.tau_dim;
                let global = shared.narrow(1, e, cs - e)?.unsqueeze(0)?; // [1, B, G]
                let heads = (0..n)
                    .map(|i| {
                        let l = self.h >> i;
                        let tau = mish(&Self::pool(emb, l)?)?.transpose(0, 1)?; // [L, B, E]
                        let g = global.broadcast_as((l, b, cs - e))?;
                        Tensor::cat(&[&tau, &g], 2)?.contiguous().map(Some)
                    })
                    .collect::<CResult<_>>()?;
                Ok((vec![None; n], heads))
            }
        }
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
        let (shared, emb) = self.conditioning(inp)?;
        let n = self.down.len();
        let (pooled, heads_in) = self.level_conditioning(&shared, &emb)?;
        let cond = |lvl: usize| Cond {
            shared: &shared,
            pos: pooled[lvl].as_ref(),
            heads_in: heads_in[lvl].as_ref(),
        };
        let mut x = inp.x.clone(); // channels-last [B, H, A]
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
            x = Tensor::cat(&[&x, &skip], 2)?;
            x = lv.r0.forward(&x, &cond(lvl))?;
            x = lv.r1.forward(&x, &cond(lvl))?;
            if let Some(u) = &lv.resample {
                let (b, l, c) = x.dims3()?;
                let up = x
                    .unsqueeze(2)?
                    .broadcast_as((b, l, 2, c))?
                    .reshape((b, 2 * l, c))?;
                x = u.forward(&up)?;
            }
        }
        let y = self.final_conv.forward(&self.final_block.forward(&x)?)?; // [B, H, A]
        y.reshape((inp.b, self.h, self.a))
    }

    /// FiLM parameters of every down-path residual block (tests).
    #[cfg(test)]
    pub(crate) fn all_film_params(&self, inp: &Inputs) -> CResult<Vec<Tensor>> {
        let (shared, emb) = self.conditioning(inp)?;
        let (pooled, heads_in) = self.level_conditioning(&shared, &emb)?;
        let mut out = Vec::new();
        for (i, lv) in self.down.iter().enumerate() {
            let l = self.h >> i;
            let c = Cond {
                shared: &shared,
                pos: pooled[i].as_ref(),
                heads_in: heads_in[i].as_ref(),
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
    use crate::config::{Config, FilmMode, ModelConfig, SlowSpec, Spec, Stats, UNetConfig};
    use candle_core::Tensor;
    use pir2_runtime::model::{ModelInput, SlowInput};

    fn spec() -> Spec {
        Spec {
            horizon: 8,
            action_dim: 3,
            n_obs: 2,
            fast_dim: 4,
            slow: SlowSpec::None,
            d_vis_max: 1,
        }
    }

    fn model(film: FilmMode, seed: u64) -> CandleModel {
        let cfg = Config {
            spec: spec(),
            model: ModelConfig::UNet(UNetConfig {
                widths: vec![8, 16],
                kernel: 3,
                groups: 4,
                tau_dim: 8,
                dvis_dim: 2,
                film,
            }),
        };
        CandleModel::new(cfg, Stats::identity(&spec()), seed).unwrap()
    }

    /// Per-sample uniform τ (the base model's regime) or a staircase with a hidden-front marker.
    fn taus(uniform: bool) -> Vec<f32> {
        (0..16)
            .map(|i| match (uniform, i / 8) {
                (true, 0) => 0.25,
                (true, _) => 0.75,
                (false, _) if i % 8 == 0 => -1.0,
                (false, _) => (i % 8) as f32 / 8.0,
            })
            .collect()
    }

    fn films(m: &mut CandleModel, tau: &[f32]) -> Vec<Tensor> {
        let x = vec![0.3; 2 * 8 * 3];
        let obs: Vec<f32> = (0..16).map(|i| i as f32 * 0.1).collect();
        let input = ModelInput {
            batch: 2,
            horizon: 8,
            action_dim: 3,
            x: &x,
            tau,
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
        u.all_film_params(&inp).unwrap()
    }

    fn flat(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    }

    #[test]
    fn per_position_variants_start_position_uniform() {
        for film in [FilmMode::PerPositionHeads, FilmMode::PerPositionTau] {
            let mut m = model(film, 0);
            let fs = films(&mut m, &taus(true));
            assert_eq!(fs.len(), 4);
            for f in fs {
                let (b, l, c2) = f.dims3().unwrap();
                let v = flat(&f);
                let mut nonzero = false;
                for bi in 0..b {
                    for ch in 0..c2 {
                        let first = v[bi * l * c2 + ch];
                        nonzero |= first != 0.0;
                        for p in 0..l {
                            let here = v[(bi * l + p) * c2 + ch];
                            assert!(
                                (here - first).abs() <= 1e-6 * first.abs().max(1.0),
                                "{film:?}: modulation varies over positions at init \
                                 (sample {bi}, channel {ch}, position {p})"
                            );
                        }
                    }
                }
                assert!(nonzero, "the shared FiLM pair must not be trivially zero");
            }
        }
    }

    /// The paper's heads start as copies of the shared head: with the same seed, every other
    /// weight is the shared model's, and at a position-uniform τ the modulation is the shared
    /// model's.
    #[test]
    fn per_position_heads_start_as_the_shared_model() {
        let mut shared = model(FilmMode::Shared, 7);
        let mut heads = model(FilmMode::PerPositionHeads, 7);
        let sv: std::collections::HashMap<String, Vec<f32>> = shared
            .vars()
            .iter()
            .map(|(n, v)| (n.clone(), flat(v.as_tensor())))
            .collect();
        let mut n_heads = 0;
        for (n, v) in heads.vars() {
            let hv = flat(v.as_tensor());
            if let Some(base) = n
                .strip_suffix(".film_heads.weight")
                .map(|b| format!("{b}.film.weight"))
                .or_else(|| {
                    n.strip_suffix(".film_heads.bias")
                        .map(|b| format!("{b}.film.bias"))
                })
            {
                let s = &sv[&base];
                assert_eq!(hv.len() % s.len(), 0);
                for (i, c) in hv.chunks(s.len()).enumerate() {
                    assert_eq!(c, &s[..], "{n}: head {i} is not a copy of the shared head");
                }
                n_heads += 1;
            } else {
                assert_eq!(hv, sv[n.as_str()], "{n} differs from the shared model's");
            }
        }
        assert_eq!(
            n_heads,
            2 * 8,
            "one head weight and bias per residual block"
        );
        let tau = taus(true);
        for (a, b) in films(&mut shared, &tau).iter().zip(films(&mut heads, &tau)) {
            let (a, b) = (
                flat(&a.broadcast_as(b.dims()).unwrap().contiguous().unwrap()),
                flat(&b),
            );
            for (x, y) in a.iter().zip(&b) {
                assert!((x - y).abs() <= 1e-6 * x.abs().max(1.0), "{x} vs {y}");
            }
        }
    }

    /// Each slot has parameters of its own: changing head 0 changes slot 0's modulation only.
    #[test]
    fn each_position_has_its_own_head() {
        let mut m = model(FilmMode::PerPositionHeads, 3);
        let tau = taus(false);
        let before = flat(&films(&mut m, &tau)[0]);
        for (n, var) in m.vars() {
            if n == "down.0.res0.film_heads.bias" {
                let t = var.as_tensor();
                let mut v = flat(t);
                let width = v.len() / 8;
                for x in &mut v[..width] {
                    *x += 0.5;
                }
                var.set(&Tensor::from_vec(v, t.dims(), t.device()).unwrap())
                    .unwrap();
            }
        }
        let after = flat(&films(&mut m, &tau)[0]);
        let c2 = after.len() / 16;
        for (i, (a, b)) in before.iter().zip(&after).enumerate() {
            let p = (i / c2) % 8;
            if p == 0 {
                assert!((b - a - 0.5).abs() < 1e-5, "slot 0 must move with its head");
            } else {
                assert_eq!(a, b, "position {p} moved with head 0");
            }
        }
    }
}
