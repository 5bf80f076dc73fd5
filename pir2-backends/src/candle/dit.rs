//! DiT action head: a state token and `H` action tokens; blocks alternate cross-attention to
//! the slow tokens (even blocks) and self-attention (odd blocks), each followed by an MLP,
//! all modulated by **per-position AdaLN**: shift/scale/gate per token from that position's `τ`
//! embedding, through one modulation head per token position (the paper's, the default;
//! `ada = per_position_tau` keeps one shared head), adaLN-zero init. Heads are copies of the
//! shared head, so a model finetuned with heads from a shared checkpoint starts as it.
//!
//! Tokens: state = `W_s·fast_enc`; action `p` = `W_a·x_p + pos_p + e(d_vis)`, where `e` is a
//! learned delay embedding with `d_vis_max + 1` entries, zero-initialised (so a model
//! finetuned from one without it starts unchanged). Conditioning per token: action `p` gets
//! `MLP(sin/cos(1000 τ_p), hidden_p) + W_c·fast_enc`, the state token the mean over positions.
//! Slow input: `T` tokens projected to the width, plus a learned token position; a slow vector
//! is one token. Without a slow channel every block self-attends.

use candle_core::{Device, Module, Tensor, D};

use super::layers::{layer_norm, sinusoidal_tau, CResult, Init, ParamStore};
use super::Inputs;
use crate::config::{DitConfig, FilmMode, SlowSpec, Spec};

fn softmax_last(x: &Tensor) -> CResult<Tensor> {
    let m = x.max_keepdim(D::Minus1)?.detach();
    let e = x.broadcast_sub(&m)?.exp()?;
    e.broadcast_div(&e.sum_keepdim(D::Minus1)?)
}

#[derive(Debug)]
struct Attention {
    q: candle_nn::Linear,
    kv: candle_nn::Linear,
    o: candle_nn::Linear,
    heads: usize,
}

impl Attention {
    fn new(ps: &mut ParamStore, name: &str, d: usize, dkv: usize, heads: usize) -> CResult<Self> {
        Ok(Self {
            q: ps.linear(&format!("{name}.q"), d, d)?,
            kv: ps.linear(&format!("{name}.kv"), dkv, 2 * d)?,
            o: ps.linear(&format!("{name}.o"), d, d)?,
            heads,
        })
    }

    /// `x` `[B, N, D]` attends to `mem` `[B, M, Dkv]`.
    fn forward(&self, x: &Tensor, mem: &Tensor) -> CResult<Tensor> {
        let (b, n, d) = x.dims3()?;
        let m = mem.dim(1)?;
        let (nh, hd) = (self.heads, d / self.heads);
        let q = self
            .q
            .forward(x)?
            .reshape((b, n, nh, hd))?
            .transpose(1, 2)?
            .contiguous()?;
        let kv = self.kv.forward(mem)?;
        let k = kv
            .narrow(2, 0, d)?
            .reshape((b, m, nh, hd))?
            .transpose(1, 2)?
            .contiguous()?;
        let v = kv
            .narrow(2, d, d)?
            .reshape((b, m, nh, hd))?
            .transpose(1, 2)?
            .contiguous()?;
        let att = (q.matmul(&k.t()?.contiguous()?)? / (hd as f64).sqrt())?;
        let y = softmax_last(&att)?.matmul(&v)?; // [B, nh, N, hd]
        self.o
            .forward(&y.transpose(1, 2)?.contiguous()?.reshape((b, n, d))?)
    }
}

/// AdaLN modulation: one shared head, or one head per token position.
#[derive(Debug)]
enum Ada {
    Shared(candle_nn::Linear),
    /// Weight `[N, out, in]`, bias `[N, out]`.
    Heads(Tensor, Tensor),
}

impl Ada {
    fn new(
        ps: &mut ParamStore,
        name: &str,
        heads: Option<usize>,
        din: usize,
        dout: usize,
    ) -> CResult<Self> {
        Ok(match heads {
            None => Ada::Shared(ps.linear_zero(name, din, dout)?),
            Some(n) => Ada::Heads(
                ps.param(
                    &format!("{name}_heads.weight"),
                    &[n, dout, din],
                    Init::Zeros,
                )?,
                ps.param(&format!("{name}_heads.bias"), &[n, dout], Init::Zeros)?,
            ),
        })
    }

    /// `c` `[B, N, D]` → `[B, N, out]`.
    fn forward(&self, c: &Tensor) -> CResult<Tensor> {
        match self {
            Ada::Shared(l) => l.forward(c),
            Ada::Heads(w, b) => c
                .transpose(0, 1)?
                .contiguous()?
                .matmul(&w.transpose(1, 2)?)?
                .broadcast_add(&b.unsqueeze(1)?)?
                .transpose(0, 1)?
                .contiguous(),
        }
    }
}

#[derive(Debug)]
struct Block {
    /// Per-token modulation: shift/scale/gate for the attention and for the MLP (6·D).
    ada: Ada,
    attn: Attention,
    /// Cross-attention to the slow tokens (else self-attention).
    cross: bool,
    fc1: candle_nn::Linear,
    fc2: candle_nn::Linear,
    d: usize,
}

impl Block {
    fn modulate(x: &Tensor, shift: &Tensor, scale: &Tensor) -> CResult<Tensor> {
        layer_norm(x, 1e-6)?.mul(&(scale + 1.0)?)?.add(shift)
    }

    fn forward(&self, x: &Tensor, c: &Tensor, mem: Option<&Tensor>) -> CResult<Tensor> {
        let d = self.d;
        let m = self.ada.forward(&c.silu()?)?; // [B, N, 6D]
        let ch = |i: usize| m.narrow(2, i * d, d);
        let h = Self::modulate(x, &ch(0)?, &ch(1)?)?;
        let a = match (self.cross, mem) {
            (true, Some(mem)) => self.attn.forward(&h, mem)?,
            _ => self.attn.forward(&h, &h)?,
        };
        let x = (x + ch(2)?.mul(&a)?)?;
        let h = Self::modulate(&x, &ch(3)?, &ch(4)?)?;
        let y = self.fc2.forward(&self.fc1.forward(&h)?.gelu()?)?;
        &x + ch(5)?.mul(&y)?
    }
}

#[derive(Debug)]
pub(crate) struct Dit {
    state_in: candle_nn::Linear,
    act_in: candle_nn::Linear,
    pos: Tensor,
    delay: candle_nn::Embedding,
    obs_cond: candle_nn::Linear,
    tau_l0: candle_nn::Linear,
    tau_l1: candle_nn::Linear,
    slow_in: Option<(candle_nn::Linear, Tensor)>,
    blocks: Vec<Block>,
    final_ada: Ada,
    out: candle_nn::Linear,
    tau_dim: usize,
    h: usize,
    a: usize,
}

impl Dit {
    pub(crate) fn new(ps: &mut ParamStore, spec: &Spec, c: &DitConfig) -> CResult<Self> {
        let d = c.width;
        let fe = spec.fast_encoded_dim();
        let state_in = ps.linear("state_in", fe, d)?;
        let act_in = ps.linear("action_in", spec.action_dim, d)?;
        let pos = ps.param("action_pos", &[spec.horizon, d], Init::Uniform(0.02))?;
        let delay = ps.embedding_zero("delay_embed", spec.d_vis_max + 1, d)?;
        let obs_cond = ps.linear("obs_cond", fe, d)?;
        let tau_l0 = ps.linear("tau_mlp.0", c.tau_dim + 1, d)?;
        let tau_l1 = ps.linear("tau_mlp.1", d, d)?;
        let slow_in = match spec.slow {
            SlowSpec::None => None,
            s => Some((
                ps.linear("slow_in", s.width(), d)?,
                ps.param("slow_pos", &[s.tokens(), d], Init::Uniform(0.02))?,
            )),
        };
        // One head per token: the state token and the H action tokens.
        let heads = (c.ada == FilmMode::PerPositionHeads).then_some(spec.horizon + 1);
        let mut blocks = Vec::with_capacity(c.depth);
        for i in 0..c.depth {
            let nm = format!("blocks.{i}");
            // Alternate: even blocks cross-attend to the slow tokens, odd blocks self-attend
            // (all self-attention without a slow channel).
            let cross = !spec.slow.is_empty() && i % 2 == 0;
            let attn_name = format!("{nm}.{}", if cross { "cross_attn" } else { "self_attn" });
            blocks.push(Block {
                ada: Ada::new(ps, &format!("{nm}.ada"), heads, d, 6 * d)?,
                attn: Attention::new(ps, &attn_name, d, d, c.heads)?,
                cross,
                fc1: ps.linear(&format!("{nm}.mlp.0"), d, c.mlp_ratio * d)?,
                fc2: ps.linear(&format!("{nm}.mlp.1"), c.mlp_ratio * d, d)?,
                d,
            });
        }
        let final_ada = Ada::new(ps, "final.ada", heads, d, 2 * d)?;
        let out = ps.linear_zero("final.out", d, spec.action_dim)?;
        Ok(Self {
            state_in,
            act_in,
            pos,
            delay,
            obs_cond,
            tau_l0,
            tau_l1,
            slow_in,
            blocks,
            final_ada,
            out,
            tau_dim: c.tau_dim,
            h: spec.horizon,
            a: spec.action_dim,
        })
    }

    pub(crate) fn forward(&self, inp: &Inputs) -> CResult<Tensor> {
        let b = inp.b;
        let mut sin = Vec::new();
        sinusoidal_tau(&inp.tau, self.tau_dim, &mut sin);
        let s = Tensor::from_vec(sin, (b, self.h, self.tau_dim + 1), &Device::Cpu)?;
        let temb = self.tau_l1.forward(&self.tau_l0.forward(&s)?.silu()?)?; // [B, H, D]
        let oc = self.obs_cond.forward(&inp.fast)?.unsqueeze(1)?; // [B, 1, D]
        let c = Tensor::cat(&[&temb.mean_keepdim(1)?, &temb], 1)?.broadcast_add(&oc)?; // [B, 1+H, D]
        let state = self.state_in.forward(&inp.fast)?.unsqueeze(1)?;
        let acts = self
            .act_in
            .forward(&inp.x)?
            .broadcast_add(&self.pos.unsqueeze(0)?)?
            .broadcast_add(&self.delay.forward(&inp.dvis)?.unsqueeze(1)?)?;
        let mut x = Tensor::cat(&[&state, &acts], 1)?;
        let mem = match (&self.slow_in, &inp.slow) {
            (Some((l, p)), Some(sl)) => Some(l.forward(sl)?.broadcast_add(&p.unsqueeze(0)?)?),
            _ => None,
        };
        for blk in &self.blocks {
            x = blk.forward(&x, &c, mem.as_ref())?;
        }
        let d = x.dim(2)?;
        let m = self.final_ada.forward(&c.silu()?)?;
        let h = Block::modulate(&x, &m.narrow(2, 0, d)?, &m.narrow(2, d, d)?)?;
        let y = self.out.forward(&h.narrow(1, 1, self.h)?)?;
        y.reshape((b, self.h, self.a))
    }
}
