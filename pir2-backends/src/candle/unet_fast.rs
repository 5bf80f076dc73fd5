//! Hand-written forward and backward of the conditional U-Net 1D ([`super::unet::UNet`]) on
//! host f32 buffers: the same parameters (same names, same layouts, read from the model's
//! variables), the same arithmetic up to float rounding, no autograd graph.
//!
//! The network is a fixed list of [`Op`]s over activation buffers; the backward walks it in
//! reverse. Every buffer is owned here and reused, so a warm call at an unchanged batch size
//! allocates nothing (the batch-1 inference path relies on it).
//!
//! One file on purpose: the op list, its forward and its reverse walk must stay in step.

use std::collections::HashMap;

use gemm::Parallelism;

use super::kernels::{mish1, mish_and_grad, Conv, ConvMode, GnMish, Heads, Lin};
use super::layers::{sinusoidal_tau, CResult};
use crate::config::{FilmMode, Spec, UNetConfig};

/// One residual block (two conv blocks, FiLM between them, 1×1 or identity residual).
#[derive(Debug)]
struct Res {
    c0: Conv,
    n0: GnMish,
    c1: Conv,
    n1: GnMish,
    /// The shared head (absent with per-position heads).
    film: Option<Lin>,
    film_pos: Option<Lin>,
    heads: Option<Heads>,
    res: Option<Conv>,
    cout: usize,
    lvl: usize,
    z0: Vec<f32>,
    a0: Vec<f32>,
    fs: Vec<f32>,
    f: Vec<f32>,
    h: Vec<f32>,
    z1: Vec<f32>,
    r: Vec<f32>,
}

/// Reusable backward temporaries.
#[derive(Debug, Default)]
struct Ws {
    t1: Vec<f32>,
    t2: Vec<f32>,
    t3: Vec<f32>,
    t4: Vec<f32>,
    t5: Vec<f32>,
    s0: Vec<f32>,
}

impl Res {
    #[allow(clippy::too_many_arguments)]
    fn fwd(
        &mut self,
        par: Parallelism,
        p: &[Vec<f32>],
        x: &[f32],
        b: usize,
        l: usize,
        shared: &[f32],
        pooled: Option<&[f32]>,
        heads_in: Option<&[f32]>,
        y: &mut Vec<f32>,
    ) {
        let c = self.cout;
        self.c0.fwd(par, p, x, b, l, &mut self.z0);
        self.n0.fwd(par, p, &self.z0, b, l, &mut self.a0);
        if let (Some(hd), Some(u)) = (&self.heads, heads_in) {
            // Slot-major [L, B, 2C] → [B, L, 2C].
            hd.fwd(par, p, u, b, &mut self.fs);
            self.f.resize(b * l * 2 * c, 0.0);
            for li in 0..l {
                for bi in 0..b {
                    self.f[(bi * l + li) * 2 * c..(bi * l + li + 1) * 2 * c].copy_from_slice(
                        &self.fs[(li * b + bi) * 2 * c..(li * b + bi + 1) * 2 * c],
                    );
                }
            }
        } else {
            let film = self
                .film
                .as_ref()
                .expect("a block without heads has the shared head");
            film.fwd(par, p, shared, b, &mut self.fs);
        }
        match (&self.film_pos, pooled) {
            _ if self.heads.is_some() => {}
            (Some(fp), Some(pl)) => {
                fp.fwd(par, p, pl, b * l, &mut self.f);
                for (i, row) in self.f.chunks_exact_mut(2 * c).enumerate() {
                    let fsr = &self.fs[(i / l) * 2 * c..(i / l + 1) * 2 * c];
                    for (v, &s) in row.iter_mut().zip(fsr) {
                        *v += s;
                    }
                }
            }
            _ => {
                self.f.resize(b * l * 2 * c, 0.0);
                for (i, row) in self.f.chunks_exact_mut(2 * c).enumerate() {
                    row.copy_from_slice(&self.fs[(i / l) * 2 * c..(i / l + 1) * 2 * c]);
                }
            }
        }
        self.h.resize(b * l * c, 0.0);
        for ((hr, ar), fr) in self
            .h
            .chunks_exact_mut(c)
            .zip(self.a0.chunks_exact(c))
            .zip(self.f.chunks_exact(2 * c))
        {
            let (sc, bi) = fr.split_at(c);
            for i in 0..c {
                hr[i] = ar[i] * (sc[i] + 1.0) + bi[i];
            }
        }
        self.c1.fwd(par, p, &self.h, b, l, &mut self.z1);
        self.n1.fwd(par, p, &self.z1, b, l, y);
        match &mut self.res {
            Some(rc) => {
                rc.fwd(par, p, x, b, l, &mut self.r);
                for (o, &v) in y.iter_mut().zip(&self.r) {
                    *o += v;
                }
            }
            None => {
                for (o, &v) in y.iter_mut().zip(x) {
                    *o += v;
                }
            }
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn bwd(
        &mut self,
        par: Parallelism,
        p: &[Vec<f32>],
        g: &mut [Vec<f32>],
        x: &[f32],
        dy: &[f32],
        b: usize,
        l: usize,
        shared: &[f32],
        pooled: Option<&[f32]>,
        heads_in: Option<(&[f32], &mut [f32])>,
        mut dx: Option<&mut [f32]>,
        dshared: &mut [f32],
        dpooled: Option<&mut [f32]>,
        ws: &mut Ws,
    ) {
        let c = self.cout;
        let n = b * l * c;
        match &self.res {
            Some(rc) => rc.bwd(par, p, g, x, dy, b, l, dx.as_deref_mut(), &mut ws.s0),
            None => {
                if let Some(dx) = dx.as_deref_mut() {
                    for (d, &v) in dx.iter_mut().zip(&dy[..n]) {
                        *d += v;
                    }
                }
            }
        }
        self.n1.bwd(par, p, g, dy, b, l, &mut ws.t1);
        ws.t2.clear();
        ws.t2.resize(n, 0.0);
        self.c1.bwd(
            par,
            p,
            g,
            &self.h,
            &ws.t1,
            b,
            l,
            Some(&mut ws.t2),
            &mut ws.s0,
        );
        // FiLM: h = a0·(1 + scale) + bias → da0 (into t1), d(scale, bias) (into t3).
        ws.t3.resize(b * l * 2 * c, 0.0);
        for r in 0..b * l {
            for i in 0..c {
                let dh = ws.t2[r * c + i];
                ws.t1[r * c + i] = dh * (1.0 + self.f[r * 2 * c + i]);
                ws.t3[r * 2 * c + i] = dh * self.a0[r * c + i];
                ws.t3[r * 2 * c + c + i] = dh;
            }
        }
        if let (Some(fp), Some(pl)) = (&self.film_pos, pooled) {
            fp.bwd(par, p, g, pl, &ws.t3, b * l, dpooled.map(|d| (d, true)));
        }
        if let (Some(hd), Some((u, du))) = (&self.heads, heads_in) {
            // [B, L, 2C] → slot-major [L, B, 2C].
            ws.t5.resize(b * l * 2 * c, 0.0);
            for li in 0..l {
                for bi in 0..b {
                    ws.t5[(li * b + bi) * 2 * c..(li * b + bi + 1) * 2 * c]
                        .copy_from_slice(&ws.t3[(bi * l + li) * 2 * c..(bi * l + li + 1) * 2 * c]);
                }
            }
            hd.bwd(par, p, g, u, &ws.t5, b, du);
        } else {
            ws.t4.clear();
            ws.t4.resize(b * 2 * c, 0.0);
            for r in 0..b * l {
                let bi = r / l;
                for i in 0..2 * c {
                    ws.t4[bi * 2 * c + i] += ws.t3[r * 2 * c + i];
                }
            }
            let film = self
                .film
                .as_ref()
                .expect("a block without heads has the shared head");
            film.bwd(par, p, g, shared, &ws.t4, b, Some((dshared, true)));
        }
        self.n0.bwd(par, p, g, &ws.t1, b, l, &mut ws.t2);
        self.c0.bwd(par, p, g, x, &ws.t2, b, l, dx, &mut ws.s0);
    }
}

/// One step of the network over activation buffers (indices into `acts`).
#[derive(Debug, Clone, Copy)]
enum Op {
    Res { blk: usize, x: usize, y: usize },
    Conv { conv: usize, x: usize, y: usize },
    Cat { a: usize, b: usize, y: usize },
    Gn { gn: usize, x: usize, y: usize },
}

/// One batch of encoded, normalised host inputs.
#[derive(Debug, Clone, Copy)]
pub(crate) struct HostBatch<'a> {
    pub(crate) b: usize,
    /// `[B, H, A]`.
    pub(crate) x: &'a [f32],
    /// Raw `τ`, `[B·H]`.
    pub(crate) tau: &'a [f32],
    /// Encoded fast history `[B, n_obs·F]`.
    pub(crate) fast: &'a [f32],
    /// Normalised slow features `[B, T·D]` (empty without a slow channel).
    pub(crate) slow: &'a [f32],
    /// Clamped slow ages `[B]`.
    pub(crate) dvis: &'a [u32],
}

/// The U-Net as host kernels (see the module docs).
#[derive(Debug)]
pub(crate) struct FastUNet {
    tau0: Lin,
    tau1: Lin,
    dvis: usize,
    dvis_dim: usize,
    blocks: Vec<Res>,
    convs: Vec<Conv>,
    gns: Vec<GnMish>,
    ops: Vec<Op>,
    /// `(L, C)` of every activation.
    shapes: Vec<(usize, usize)>,
    acts: Vec<Vec<f32>>,
    gacts: Vec<Vec<f32>>,
    e: usize,
    h: usize,
    a: usize,
    levels: usize,
    per_pos: bool,
    /// Per-position FiLM heads (the paper's variant).
    heads: bool,
    /// Per level: head inputs `[mish(ē_l), global]`, slot-major `[L, B, cs]`; the pre-mish
    /// slot means `ē_l` `[L, B, E]`; the gradient of the head inputs.
    hin: Vec<Vec<f32>>,
    hmean: Vec<Vec<f32>>,
    dhin: Vec<Vec<f32>>,
    fe: usize,
    sw: usize,
    tokens: usize,
    cs: usize,
    b: usize,
    sin: Vec<f32>,
    t0: Vec<f32>,
    m0: Vec<f32>,
    emb: Vec<f32>,
    mean: Vec<f32>,
    shared: Vec<f32>,
    pooled: Vec<Vec<f32>>,
    dshared: Vec<f32>,
    dpooled: Vec<Vec<f32>>,
    demb: Vec<f32>,
    dm0: Vec<f32>,
    dvis_idx: Vec<u32>,
    ws: Ws,
}

impl FastUNet {
    /// Build over the model's variables (`names` in parameter order).
    pub(crate) fn new(spec: &Spec, c: &UNetConfig, names: &[&str]) -> CResult<Self> {
        let index: HashMap<&str, usize> = names.iter().enumerate().map(|(i, n)| (*n, i)).collect();
        let idx = |n: String| -> CResult<usize> {
            index
                .get(n.as_str())
                .copied()
                .ok_or_else(|| candle_core::Error::Msg(format!("fast U-Net: no parameter {n}")))
        };
        let lin = |n: &str, din: usize, dout: usize| -> CResult<Lin> {
            Ok(Lin {
                w: idx(format!("{n}.weight"))?,
                b: idx(format!("{n}.bias"))?,
                din,
                dout,
            })
        };
        let conv = |n: &str, cin: usize, cout: usize, k: usize, mode: ConvMode| -> CResult<Conv> {
            Ok(Conv::new(
                idx(format!("{n}.weight"))?,
                idx(format!("{n}.bias"))?,
                cin,
                cout,
                k,
                mode,
            ))
        };
        let gn = |n: &str, ch: usize| -> CResult<GnMish> {
            Ok(GnMish::new(
                idx(format!("{n}.weight"))?,
                idx(format!("{n}.bias"))?,
                c.groups,
                ch,
            ))
        };
        let e = c.tau_dim;
        let per_pos = c.film == FilmMode::PerPositionTau;
        let with_heads = c.film == FilmMode::PerPositionHeads;
        let fe = spec.fast_encoded_dim();
        let sw = spec.slow.width();
        let cs = e + fe + sw + c.dvis_dim;
        let k = c.kernel;
        let h = spec.horizon;
        let res = |n: &str, cin: usize, cout: usize, lvl: usize| -> CResult<Res> {
            Ok(Res {
                c0: conv(&format!("{n}.block0.conv"), cin, cout, k, ConvMode::Same)?,
                n0: gn(&format!("{n}.block0.gn"), cout)?,
                c1: conv(&format!("{n}.block1.conv"), cout, cout, k, ConvMode::Same)?,
                n1: gn(&format!("{n}.block1.gn"), cout)?,
                film: if with_heads {
                    None
                } else {
                    Some(lin(&format!("{n}.film"), cs, 2 * cout)?)
                },
                heads: if with_heads {
                    Some(Heads {
                        w: idx(format!("{n}.film_heads.weight"))?,
                        b: idx(format!("{n}.film_heads.bias"))?,
                        l: h >> lvl,
                        din: cs,
                        dout: 2 * cout,
                    })
                } else {
                    None
                },
                film_pos: if per_pos {
                    Some(lin(&format!("{n}.film_pos"), e, 2 * cout)?)
                } else {
                    None
                },
                res: if cin != cout {
                    Some(conv(&format!("{n}.res"), cin, cout, 1, ConvMode::Same)?)
                } else {
                    None
                },
                cout,
                lvl,
                z0: Vec::new(),
                a0: Vec::new(),
                fs: Vec::new(),
                f: Vec::new(),
                h: Vec::new(),
                z1: Vec::new(),
                r: Vec::new(),
            })
        };
        let (h, a) = (spec.horizon, spec.action_dim);
        let mut dims = vec![a];
        dims.extend_from_slice(&c.widths);
        let n = c.widths.len();
        let mut blocks = Vec::new();
        let mut convs = Vec::new();
        let mut gns = Vec::new();
        let mut ops = Vec::new();
        let mut shapes = vec![(h, a)];
        let mut cur = 0;
        let mut l = h;
        let mut skips = Vec::with_capacity(n);
        macro_rules! push_res {
            ($blk:expr, $lout:expr, $cout:expr) => {{
                blocks.push($blk);
                shapes.push(($lout, $cout));
                let y = shapes.len() - 1;
                ops.push(Op::Res {
                    blk: blocks.len() - 1,
                    x: cur,
                    y,
                });
                cur = y;
            }};
        }
        macro_rules! push_conv {
            ($cv:expr, $lout:expr, $cout:expr) => {{
                convs.push($cv);
                shapes.push(($lout, $cout));
                let y = shapes.len() - 1;
                ops.push(Op::Conv {
                    conv: convs.len() - 1,
                    x: cur,
                    y,
                });
                cur = y;
            }};
        }
        for i in 0..n {
            let (din, dout) = (dims[i], dims[i + 1]);
            push_res!(res(&format!("down.{i}.res0"), din, dout, i)?, l, dout);
            push_res!(res(&format!("down.{i}.res1"), dout, dout, i)?, l, dout);
            skips.push(cur);
            if i + 1 < n {
                let cv = conv(&format!("down.{i}.down"), dout, dout, 3, ConvMode::Down2)?;
                l /= 2;
                push_conv!(cv, l, dout);
            }
        }
        let wmax = c.widths[n - 1];
        push_res!(res("mid.0", wmax, wmax, n - 1)?, l, wmax);
        push_res!(res("mid.1", wmax, wmax, n - 1)?, l, wmax);
        for (j, i) in (1..n).rev().enumerate() {
            let (din, dout) = (dims[i], dims[i + 1]);
            shapes.push((l, 2 * dout));
            let y = shapes.len() - 1;
            ops.push(Op::Cat {
                a: cur,
                b: skips[i],
                y,
            });
            cur = y;
            push_res!(res(&format!("up.{j}.res0"), 2 * dout, din, i)?, l, din);
            push_res!(res(&format!("up.{j}.res1"), din, din, i)?, l, din);
            let cv = conv(&format!("up.{j}.up"), din, din, 3, ConvMode::Up2)?;
            l *= 2;
            push_conv!(cv, l, din);
        }
        let w0 = c.widths[0];
        push_conv!(conv("final.block.conv", w0, w0, k, ConvMode::Same)?, l, w0);
        gns.push(gn("final.block.gn", w0)?);
        shapes.push((l, w0));
        let y = shapes.len() - 1;
        ops.push(Op::Gn { gn: 0, x: cur, y });
        cur = y;
        push_conv!(conv("final.conv", w0, a, 1, ConvMode::Same)?, l, a);
        debug_assert_eq!(l, h);
        let _ = cur;
        let nacts = shapes.len();
        Ok(Self {
            tau0: lin("tau_mlp.0", e + 1, 4 * e)?,
            tau1: lin("tau_mlp.1", 4 * e, e)?,
            dvis: idx("dvis_embed".into())?,
            dvis_dim: c.dvis_dim,
            blocks,
            convs,
            gns,
            ops,
            shapes,
            acts: vec![Vec::new(); nacts],
            gacts: vec![Vec::new(); nacts],
            e,
            h,
            a,
            levels: n,
            per_pos,
            heads: with_heads,
            hin: vec![Vec::new(); n],
            hmean: vec![Vec::new(); n],
            dhin: vec![Vec::new(); n],
            fe,
            sw,
            tokens: spec.slow.tokens(),
            cs,
            b: 0,
            sin: Vec::new(),
            t0: Vec::new(),
            m0: Vec::new(),
            emb: Vec::new(),
            mean: Vec::new(),
            shared: Vec::new(),
            pooled: vec![Vec::new(); n],
            dshared: Vec::new(),
            dpooled: vec![Vec::new(); n],
            demb: Vec::new(),
            dm0: Vec::new(),
            dvis_idx: Vec::new(),
            ws: Ws::default(),
        })
    }

    /// Forward pass; returns the velocity `[B, H, A]` (kept until the next call).
    pub(crate) fn forward(
        &mut self,
        par: Parallelism,
        p: &[Vec<f32>],
        inp: &HostBatch<'_>,
    ) -> &[f32] {
        let b = inp.b;
        self.b = b;
        let (h, e) = (self.h, self.e);
        // Conditioning: τ embedding, shared vector, pooled per-position terms.
        sinusoidal_tau(inp.tau, e, &mut self.sin);
        self.tau0.fwd(par, p, &self.sin, b * h, &mut self.t0);
        self.m0.resize(self.t0.len(), 0.0);
        for (m, &t) in self.m0.iter_mut().zip(&self.t0) {
            *m = mish1(t);
        }
        self.tau1.fwd(par, p, &self.m0, b * h, &mut self.emb);
        self.mean.clear();
        self.mean.resize(b * e, 0.0);
        for bi in 0..b {
            let mr = &mut self.mean[bi * e..(bi + 1) * e];
            for pos in 0..h {
                for (m, &v) in mr
                    .iter_mut()
                    .zip(&self.emb[(bi * h + pos) * e..(bi * h + pos + 1) * e])
                {
                    *m += v;
                }
            }
            for m in mr.iter_mut() {
                *m /= h as f32;
            }
        }
        let cs = self.cs;
        self.shared.resize(b * cs, 0.0);
        self.dvis_idx.clear();
        self.dvis_idx.extend_from_slice(inp.dvis);
        let dd = self.dvis_dim;
        for bi in 0..b {
            let row = &mut self.shared[bi * cs..(bi + 1) * cs];
            for (o, &m) in row[..e].iter_mut().zip(&self.mean[bi * e..(bi + 1) * e]) {
                *o = mish1(m);
            }
            let mut off = e;
            row[off..off + self.fe].copy_from_slice(&inp.fast[bi * self.fe..(bi + 1) * self.fe]);
            off += self.fe;
            if self.sw > 0 {
                let t = self.tokens;
                let s = &inp.slow[bi * t * self.sw..(bi + 1) * t * self.sw];
                let dst = &mut row[off..off + self.sw];
                dst.fill(0.0);
                for tok in s.chunks_exact(self.sw) {
                    for (d, &v) in dst.iter_mut().zip(tok) {
                        *d += v;
                    }
                }
                for d in dst.iter_mut() {
                    *d /= t as f32;
                }
                off += self.sw;
            }
            let di = inp.dvis[bi] as usize;
            row[off..off + dd].copy_from_slice(&p[self.dvis][di * dd..(di + 1) * dd]);
        }
        if self.per_pos {
            let p0 = &mut self.pooled[0];
            p0.resize(b * h * e, 0.0);
            for (o, &v) in p0.iter_mut().zip(&self.emb) {
                *o = mish1(v);
            }
            for lvl in 1..self.levels {
                let l = h >> lvl;
                let w = h / l;
                let (lo, hi) = self.pooled.split_at_mut(lvl);
                let (src, dst) = (&lo[0], &mut hi[0]);
                dst.clear();
                dst.resize(b * l * e, 0.0);
                for bi in 0..b {
                    for q in 0..h {
                        let o = (bi * l + q / w) * e;
                        for (d, &v) in dst[o..o + e]
                            .iter_mut()
                            .zip(&src[(bi * h + q) * e..(bi * h + q + 1) * e])
                        {
                            *d += v;
                        }
                    }
                }
                let inv = 1.0 / w as f32;
                for d in dst.iter_mut() {
                    *d *= inv;
                }
            }
        }
        if self.heads {
            for lvl in 0..self.levels {
                let l = h >> lvl;
                let w = h / l;
                let inv = 1.0 / w as f32;
                let (hm, hi) = (&mut self.hmean[lvl], &mut self.hin[lvl]);
                hm.clear();
                hm.resize(l * b * e, 0.0);
                hi.resize(l * b * cs, 0.0);
                for li in 0..l {
                    for bi in 0..b {
                        let m = &mut hm[(li * b + bi) * e..(li * b + bi + 1) * e];
                        for q in li * w..(li + 1) * w {
                            for (d, &v) in m
                                .iter_mut()
                                .zip(&self.emb[(bi * h + q) * e..(bi * h + q + 1) * e])
                            {
                                *d += v;
                            }
                        }
                        let row = &mut hi[(li * b + bi) * cs..(li * b + bi + 1) * cs];
                        for (o, mv) in row[..e].iter_mut().zip(m.iter_mut()) {
                            *mv *= inv;
                            *o = mish1(*mv);
                        }
                        row[e..].copy_from_slice(&self.shared[bi * cs + e..(bi + 1) * cs]);
                    }
                }
            }
        }
        // The network.
        let n0 = b * h * self.a;
        self.acts[0].clear();
        self.acts[0].extend_from_slice(&inp.x[..n0]);
        for &op in &self.ops {
            match op {
                Op::Res { blk, x, y } => {
                    let mut out = std::mem::take(&mut self.acts[y]);
                    let l = self.shapes[x].0;
                    let lvl = self.blocks[blk].lvl;
                    let pooled = if self.per_pos {
                        Some(self.pooled[lvl].as_slice())
                    } else {
                        None
                    };
                    let heads_in = if self.heads {
                        Some(self.hin[lvl].as_slice())
                    } else {
                        None
                    };
                    self.blocks[blk].fwd(
                        par,
                        p,
                        &self.acts[x],
                        b,
                        l,
                        &self.shared,
                        pooled,
                        heads_in,
                        &mut out,
                    );
                    self.acts[y] = out;
                }
                Op::Conv { conv, x, y } => {
                    let mut out = std::mem::take(&mut self.acts[y]);
                    let l = self.shapes[x].0;
                    self.convs[conv].fwd(par, p, &self.acts[x], b, l, &mut out);
                    self.acts[y] = out;
                }
                Op::Cat { a, b: s, y } => {
                    let mut out = std::mem::take(&mut self.acts[y]);
                    let (l, ca) = self.shapes[a];
                    let cb = self.shapes[s].1;
                    out.resize(b * l * (ca + cb), 0.0);
                    for (r, row) in out.chunks_exact_mut(ca + cb).enumerate() {
                        row[..ca].copy_from_slice(&self.acts[a][r * ca..(r + 1) * ca]);
                        row[ca..].copy_from_slice(&self.acts[s][r * cb..(r + 1) * cb]);
                    }
                    self.acts[y] = out;
                }
                Op::Gn { gn, x, y } => {
                    let mut out = std::mem::take(&mut self.acts[y]);
                    let l = self.shapes[x].0;
                    self.gns[gn].fwd(par, p, &self.acts[x], b, l, &mut out);
                    self.acts[y] = out;
                }
            }
        }
        let last = self.acts.len() - 1;
        &self.acts[last][..n0]
    }

    /// Backward of the last [`FastUNet::forward`] (same `p`) for the output gradient `dout`
    /// `[B, H, A]`; accumulates into `g` (one buffer per parameter, same lengths as `p`).
    pub(crate) fn backward(
        &mut self,
        par: Parallelism,
        p: &[Vec<f32>],
        g: &mut [Vec<f32>],
        dout: &[f32],
    ) {
        let b = self.b;
        let (h, e) = (self.h, self.e);
        for (ga, a) in self.gacts.iter_mut().zip(&self.acts) {
            ga.clear();
            ga.resize(a.len(), 0.0);
        }
        let last = self.gacts.len() - 1;
        self.gacts[last].copy_from_slice(&dout[..b * h * self.a]);
        self.dshared.clear();
        self.dshared.resize(b * self.cs, 0.0);
        for (lvl, d) in self.dpooled.iter_mut().enumerate() {
            d.clear();
            if self.per_pos {
                d.resize(b * (h >> lvl) * e, 0.0);
            }
        }
        for (d, u) in self.dhin.iter_mut().zip(&self.hin) {
            d.clear();
            if self.heads {
                d.resize(u.len(), 0.0);
            }
        }
        for &op in self.ops.iter().rev() {
            match op {
                Op::Res { blk, x, y } => {
                    let gy = std::mem::take(&mut self.gacts[y]);
                    let l = self.shapes[x].0;
                    let lvl = self.blocks[blk].lvl;
                    let (pooled, dpooled) = if self.per_pos {
                        (
                            Some(self.pooled[lvl].as_slice()),
                            Some(self.dpooled[lvl].as_mut_slice()),
                        )
                    } else {
                        (None, None)
                    };
                    let dx = if x == 0 {
                        None
                    } else {
                        Some(self.gacts[x].as_mut_slice())
                    };
                    let heads_in = if self.heads {
                        Some((self.hin[lvl].as_slice(), self.dhin[lvl].as_mut_slice()))
                    } else {
                        None
                    };
                    self.blocks[blk].bwd(
                        par,
                        p,
                        g,
                        &self.acts[x],
                        &gy,
                        b,
                        l,
                        &self.shared,
                        pooled,
                        heads_in,
                        dx,
                        &mut self.dshared,
                        dpooled,
                        &mut self.ws,
                    );
                    self.gacts[y] = gy;
                }
                Op::Conv { conv, x, y } => {
                    let gy = std::mem::take(&mut self.gacts[y]);
                    let l = self.shapes[x].0;
                    let dx = if x == 0 {
                        None
                    } else {
                        Some(self.gacts[x].as_mut_slice())
                    };
                    self.convs[conv].bwd(par, p, g, &self.acts[x], &gy, b, l, dx, &mut self.ws.s0);
                    self.gacts[y] = gy;
                }
                Op::Cat { a, b: s, y } => {
                    let gy = std::mem::take(&mut self.gacts[y]);
                    let ca = self.shapes[a].1;
                    let cb = self.shapes[s].1;
                    for (r, row) in gy.chunks_exact(ca + cb).enumerate() {
                        for (d, &v) in self.gacts[a][r * ca..(r + 1) * ca]
                            .iter_mut()
                            .zip(&row[..ca])
                        {
                            *d += v;
                        }
                        for (d, &v) in self.gacts[s][r * cb..(r + 1) * cb]
                            .iter_mut()
                            .zip(&row[ca..])
                        {
                            *d += v;
                        }
                    }
                    self.gacts[y] = gy;
                }
                Op::Gn { gn, x, y } => {
                    let gy = std::mem::take(&mut self.gacts[y]);
                    let l = self.shapes[x].0;
                    self.gns[gn].bwd(par, p, g, &gy, b, l, &mut self.ws.t1);
                    for (d, &v) in self.gacts[x].iter_mut().zip(&self.ws.t1) {
                        *d += v;
                    }
                    self.gacts[y] = gy;
                }
            }
        }
        // Conditioning backward.
        let cs = self.cs;
        self.demb.clear();
        self.demb.resize(b * h * e, 0.0);
        if self.per_pos {
            // Pooled levels → full resolution, then through mish(emb).
            for lvl in 0..self.levels {
                let l = h >> lvl;
                let w = h / l;
                let inv = 1.0 / w as f32;
                let dp = &self.dpooled[lvl];
                for bi in 0..b {
                    for q in 0..h {
                        let src = &dp[(bi * l + q / w) * e..(bi * l + q / w + 1) * e];
                        for (d, &v) in self.demb[(bi * h + q) * e..(bi * h + q + 1) * e]
                            .iter_mut()
                            .zip(src)
                        {
                            *d += v * inv;
                        }
                    }
                }
            }
            for (d, &v) in self.demb.iter_mut().zip(&self.emb) {
                *d *= mish_and_grad(v).1;
            }
        }
        if self.heads {
            // Head inputs → slot means (through mish) → full resolution; global part → shared.
            for lvl in 0..self.levels {
                let l = h >> lvl;
                let w = h / l;
                let inv = 1.0 / w as f32;
                let (du, hm) = (&self.dhin[lvl], &self.hmean[lvl]);
                for li in 0..l {
                    for bi in 0..b {
                        let row = &du[(li * b + bi) * cs..(li * b + bi + 1) * cs];
                        let m = &hm[(li * b + bi) * e..(li * b + bi + 1) * e];
                        for q in li * w..(li + 1) * w {
                            let de = &mut self.demb[(bi * h + q) * e..(bi * h + q + 1) * e];
                            for k in 0..e {
                                de[k] += row[k] * mish_and_grad(m[k]).1 * inv;
                            }
                        }
                        for (d, &v) in self.dshared[bi * cs + e..(bi + 1) * cs]
                            .iter_mut()
                            .zip(&row[e..])
                        {
                            *d += v;
                        }
                    }
                }
            }
        }
        let dd = self.dvis_dim;
        let off_dvis = e + self.fe + self.sw;
        for bi in 0..b {
            let row = &self.dshared[bi * cs..(bi + 1) * cs];
            for k in 0..e {
                let dm = row[k] * mish_and_grad(self.mean[bi * e + k]).1 / h as f32;
                for pos in 0..h {
                    self.demb[(bi * h + pos) * e + k] += dm;
                }
            }
            let di = self.dvis_idx[bi] as usize;
            for (gd, &v) in g[self.dvis][di * dd..(di + 1) * dd]
                .iter_mut()
                .zip(&row[off_dvis..off_dvis + dd])
            {
                *gd += v;
            }
        }
        self.dm0.resize(self.m0.len(), 0.0);
        self.tau1.bwd(
            par,
            p,
            g,
            &self.m0,
            &self.demb,
            b * h,
            Some((self.dm0.as_mut_slice(), false)),
        );
        for (d, &t) in self.dm0.iter_mut().zip(&self.t0) {
            *d *= mish_and_grad(t).1;
        }
        self.tau0.bwd(par, p, g, &self.sin, &self.dm0, b * h, None);
    }
}

#[cfg(test)]
mod tests {
    use candle_core::Tensor;
    use pir2_runtime::model::{ModelInput, SlowInput};
    use pir2_schedule::Rng;

    use super::super::{kernels::parallelism, CandleModel};
    use crate::config::{Config, FilmMode, ModelConfig, SlowSpec, Spec, Stats, UNetConfig};

    fn model(slow: SlowSpec, film: FilmMode, seed: u64) -> CandleModel {
        let spec = Spec {
            horizon: 8,
            action_dim: 3,
            n_obs: 2,
            fast_dim: 4,
            slow,
            d_vis_max: 3,
        };
        let cfg = Config {
            spec,
            model: ModelConfig::UNet(UNetConfig {
                widths: vec![8, 16, 16],
                kernel: 5,
                groups: 4,
                tau_dim: 8,
                dvis_dim: 2,
                film,
            }),
        };
        let mut st = Stats::identity(&spec);
        st.fast.mean = vec![0.2; 4];
        let mut m = CandleModel::new(cfg, st, seed).unwrap();
        // Perturb every weight (zero-initialised ones included) so every path carries signal.
        let mut rng = Rng::new(seed + 100);
        for (_, v) in m.vars() {
            let t = v.as_tensor();
            let noise: Vec<f32> = (0..t.elem_count())
                .map(|_| rng.uniform_range(-0.3, 0.3))
                .collect();
            let noise = Tensor::from_vec(noise, t.dims(), t.device()).unwrap();
            v.set(&(t + noise).unwrap()).unwrap();
        }
        m.weights_changed();
        m
    }

    struct Owned {
        b: usize,
        x: Vec<f32>,
        tau: Vec<f32>,
        obs: Vec<f32>,
        slow: Vec<f32>,
        slow_spec: SlowSpec,
        dvis: Vec<u32>,
    }

    impl Owned {
        fn new(m: &CandleModel, b: usize, seed: u64) -> Self {
            let s = *m.spec();
            let mut rng = Rng::new(seed);
            let mut normal = |n: usize| {
                let mut v = vec![0f32; n];
                rng.fill_normal(&mut v);
                v
            };
            let x = normal(b * s.horizon * s.action_dim);
            let obs = normal(b * s.n_obs * s.fast_dim);
            let slow = normal(b * s.slow.len());
            let tau = (0..b * s.horizon)
                .map(|i| {
                    if i % s.horizon == 0 {
                        -1.0
                    } else {
                        ((i * 7) % 11) as f32 / 10.0
                    }
                })
                .collect();
            let dvis = (0..b as u32).map(|i| i % 5).collect();
            Self {
                b,
                x,
                tau,
                obs,
                slow,
                slow_spec: s.slow,
                dvis,
            }
        }
        fn view(&self, s: &Spec) -> ModelInput<'_> {
            ModelInput {
                batch: self.b,
                horizon: s.horizon,
                action_dim: s.action_dim,
                x: &self.x,
                tau: &self.tau,
                obs_fast: &self.obs,
                n_obs: s.n_obs,
                fast_dim: s.fast_dim,
                slow: match self.slow_spec {
                    SlowSpec::None => SlowInput::None,
                    SlowSpec::Vector { dim } => SlowInput::Vector {
                        data: &self.slow,
                        dim,
                    },
                    SlowSpec::Tokens { tokens, dim } => SlowInput::Tokens {
                        data: &self.slow,
                        tokens,
                        dim,
                    },
                },
                d_vis: &self.dvis,
            }
        }
    }

    fn variants() -> Vec<(SlowSpec, FilmMode)> {
        vec![
            (SlowSpec::Vector { dim: 2 }, FilmMode::PerPositionHeads),
            (SlowSpec::Vector { dim: 2 }, FilmMode::PerPositionTau),
            (
                SlowSpec::Tokens { tokens: 3, dim: 2 },
                FilmMode::PerPositionHeads,
            ),
            (SlowSpec::None, FilmMode::Shared),
        ]
    }

    fn close(what: &str, got: &[f32], want: &[f32], rtol: f32) {
        let scale = want.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-6);
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g - w).abs() <= rtol * scale,
                "{what}[{i}]: fused {g}, candle {w} (scale {scale})"
            );
        }
    }

    #[test]
    fn fused_forward_matches_the_candle_graph() {
        for (k, (slow, film)) in variants().into_iter().enumerate() {
            let mut m = model(slow, film, k as u64);
            let s = *m.spec();
            for b in [1, 4] {
                let o = Owned::new(&m, b, 7 + b as u64);
                let want = m
                    .forward_input(&o.view(&s))
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap();
                let mut got = vec![0f32; want.len()];
                assert!(m.fused());
                m.velocity_into(&o.view(&s), &mut got).unwrap();
                close(&format!("{slow:?}/{film:?} batch {b}"), &got, &want, 1e-4);
                assert!(want.iter().any(|v| v.abs() > 1e-2), "degenerate output");
                // The switch selects the candle graph.
                m.set_fused(false);
                let mut reference = vec![0f32; want.len()];
                m.velocity_into(&o.view(&s), &mut reference).unwrap();
                assert_eq!(reference, want);
                m.set_fused(true);
            }
        }
    }

    #[test]
    fn fused_gradients_match_candle_autograd() {
        for (k, (slow, film)) in variants().into_iter().enumerate() {
            let mut m = model(slow, film, 10 + k as u64);
            let s = *m.spec();
            let b = 3;
            let o = Owned::new(&m, b, 3);
            let n = b * s.horizon * s.action_dim;
            let w: Vec<f32> = (0..n).map(|i| (i as f32 * 1.3).cos()).collect();
            let wt =
                Tensor::from_slice(&w, (b, s.horizon, s.action_dim), &candle_core::Device::Cpu)
                    .unwrap();
            let grads = (m.forward_input(&o.view(&s)).unwrap() * &wt)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            let mut net = m.fast_unet().unwrap().unwrap();
            let params = m.host_params().unwrap();
            let mut g: Vec<Vec<f32>> = params.iter().map(|p| vec![0.0; p.len()]).collect();
            let par = parallelism(1);
            {
                let hb = m.host_batch(&o.view(&s)).unwrap();
                net.forward(par, &params, &hb);
            }
            net.backward(par, &params, &mut g, &w);
            for ((name, var), gf) in m.vars().iter().zip(&g) {
                let gc = grads
                    .get(var.as_tensor())
                    .unwrap_or_else(|| panic!("no candle gradient for {name}"))
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap();
                close(&format!("{slow:?}/{film:?} d{name}"), gf, &gc, 2e-4);
            }
        }
    }

    #[test]
    fn fused_gradients_match_finite_differences() {
        let mut m = model(SlowSpec::Vector { dim: 2 }, FilmMode::PerPositionHeads, 21);
        let s = *m.spec();
        let b = 2;
        let o = Owned::new(&m, b, 5);
        let n = b * s.horizon * s.action_dim;
        let w: Vec<f32> = (0..n).map(|i| (i as f32 * 0.7).sin()).collect();
        let mut net = m.fast_unet().unwrap().unwrap();
        let mut params = m.host_params().unwrap();
        let par = parallelism(1);
        let loss = |m: &mut CandleModel, net: &mut super::FastUNet, p: &[Vec<f32>]| -> f64 {
            let hb = m.host_batch(&o.view(&s)).unwrap();
            let y = net.forward(par, p, &hb);
            y.iter()
                .zip(&w)
                .map(|(a, b)| (*a as f64) * (*b as f64))
                .sum()
        };
        loss(&mut m, &mut net, &params);
        let mut g: Vec<Vec<f32>> = params.iter().map(|p| vec![0.0; p.len()]).collect();
        net.backward(par, &params, &mut g, &w);
        let names: Vec<String> = m.vars().iter().map(|(n, _)| n.clone()).collect();
        let mut bad = Vec::new();
        let mut checked = 0;
        for (t, name) in names.iter().enumerate() {
            // The largest-gradient element and one more of every tensor.
            let (kmax, _) = g[t]
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
                .unwrap();
            for k in [kmax, g[t].len() / 2] {
                let ga = g[t][k];
                let eps = 1e-2f32;
                let base = params[t][k];
                params[t][k] = base + eps;
                let lp = loss(&mut m, &mut net, &params);
                params[t][k] = base - eps;
                let lm = loss(&mut m, &mut net, &params);
                params[t][k] = base;
                let num = ((lp - lm) / (2.0 * eps as f64)) as f32;
                if (num - ga).abs() > 0.03 * ga.abs().max(num.abs()) + 3e-3 {
                    bad.push(format!("{name}[{k}]: analytic {ga}, numeric {num}"));
                }
                checked += 1;
            }
        }
        assert!(bad.is_empty(), "gradient mismatches:\n{}", bad.join("\n"));
        assert!(checked >= 2 * names.len());
    }
}
