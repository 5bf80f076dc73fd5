//! Host f32 kernels for the hand-written U-Net path ([`super::unet_fast`]): a strided GEMM
//! on the `gemm` crate, linear layers, 1-D convolutions as im2col + GEMM (forward and
//! backward), fused GroupNorm + Mish, and a vectorisable `exp` for Mish.
//!
//! Every buffer is a `Vec<f32>` owned by its layer and resized per call, so a warm call at an
//! unchanged batch size allocates nothing.
//!
//! One file on purpose: the kernels share their blocking constants and buffer conventions,
//! and their gradient checks live next to them.

use gemm::Parallelism;
use rayon::prelude::*;

/// `gemm` parallelism for `threads` (≤ 1: on the calling thread).
pub(crate) fn parallelism(threads: usize) -> Parallelism {
    if threads <= 1 {
        Parallelism::None
    } else {
        Parallelism::Rayon(threads)
    }
}

/// `dst[m×n] (+)= lhs[m×k] · rhs[k×n]`, `dst` row-major contiguous, operands given by their row
/// and column strides (so transposes are free).
#[allow(clippy::too_many_arguments)]
pub(crate) fn mm(
    par: Parallelism,
    m: usize,
    n: usize,
    k: usize,
    dst: &mut [f32],
    acc: bool,
    lhs: &[f32],
    l_rs: usize,
    l_cs: usize,
    rhs: &[f32],
    r_rs: usize,
    r_cs: usize,
) {
    if m == 0 || n == 0 {
        return;
    }
    assert!(dst.len() >= m * n, "gemm: dst too short");
    if k == 0 {
        if !acc {
            dst[..m * n].fill(0.0);
        }
        return;
    }
    assert!(
        lhs.len() > (m - 1) * l_rs + (k - 1) * l_cs,
        "gemm: lhs too short"
    );
    assert!(
        rhs.len() > (k - 1) * r_rs + (n - 1) * r_cs,
        "gemm: rhs too short"
    );
    // SAFETY: the asserts above bound every index the kernel reads or writes: dst is
    // m×n row-major, lhs element (i, p) at i·l_rs + p·l_cs, rhs element (p, j) at p·r_rs + j·r_cs.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            acc,
            lhs.as_ptr(),
            l_cs as isize,
            l_rs as isize,
            rhs.as_ptr(),
            r_cs as isize,
            r_rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            par,
        )
    }
}

/// Whether elementwise kernels split the batch over the rayon pool.
fn threaded(par: Parallelism) -> bool {
    matches!(par, Parallelism::Rayon(_))
}

/// Single-threaded calls with few rows (batch-1 inference) use [`mm_nt`].
fn small(par: Parallelism, m: usize) -> bool {
    matches!(par, Parallelism::None) && m <= 64
}

/// `exp(x)` for `x ≤ 88`, to ~2 ulp, written so loops over it vectorise (no libm call).
#[inline(always)]
pub(crate) fn fast_exp(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    // 2^n · e^r with n = round(x / ln 2), |r| ≤ ln2 / 2.
    // Round to nearest with the 1.5·2²³ trick (|x·log2 e| < 2²²): `f32::round` is a libm
    // call on baseline x86-64 and would stop the loops around this from vectorising.
    const MAGIC: f32 = 12_582_912.0;
    let n = (x * std::f32::consts::LOG2_E + MAGIC) - MAGIC;
    let r = x - n * 0.693_145_75 - n * 1.428_606_8e-6;
    let p = 1.987_569_1e-4;
    let p = p * r + 1.398_199_9e-3;
    let p = p * r + 8.333_452e-3;
    let p = p * r + 4.166_579_6e-2;
    let p = p * r + 1.666_666_5e-1;
    let p = p * r + 0.5;
    let p = p * r * r + r + 1.0;
    let bits = ((n as i32 + 127) as u32) << 23;
    p * f32::from_bits(bits)
}

/// Mish `y·tanh(softplus(y))` and its derivative, via `tanh(ln(1+e)) = (e²+2e)/(e²+2e+2)`.
#[inline(always)]
pub(crate) fn mish_and_grad(y: f32) -> (f32, f32) {
    let e = fast_exp(y.min(20.0));
    let n = e * (e + 2.0);
    let t = n / (n + 2.0);
    let sig = e / (1.0 + e);
    (y * t, t + y * (1.0 - t * t) * sig)
}

/// Mish only.
#[inline(always)]
pub(crate) fn mish1(y: f32) -> f32 {
    let e = fast_exp(y.min(20.0));
    let n = e * (e + 2.0);
    y * n / (n + 2.0)
}

/// `nn.Linear` on host rows: parameters `w` `[dout, din]`, `b` `[dout]` (indices into the
/// parameter list).
#[derive(Debug, Clone)]
pub(crate) struct Lin {
    pub(crate) w: usize,
    pub(crate) b: usize,
    pub(crate) din: usize,
    pub(crate) dout: usize,
}

impl Lin {
    /// `y[m, dout] = x[m, din] · Wᵀ + b`.
    pub(crate) fn fwd(
        &self,
        par: Parallelism,
        p: &[Vec<f32>],
        x: &[f32],
        m: usize,
        y: &mut Vec<f32>,
    ) {
        y.resize(m * self.dout, 0.0);
        linear_fwd(par, &p[self.w], &p[self.b], x, m, self.din, self.dout, y);
    }

    /// Accumulate `dW`, `db`; `dx` (if given) is overwritten (`acc = false`) or accumulated.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn bwd(
        &self,
        par: Parallelism,
        p: &[Vec<f32>],
        g: &mut [Vec<f32>],
        x: &[f32],
        dy: &[f32],
        m: usize,
        dx: Option<(&mut [f32], bool)>,
    ) {
        let (gw, gb) = two_mut(g, self.w, self.b);
        linear_bwd(par, &p[self.w], gw, gb, x, dy, m, self.din, self.dout, dx);
    }
}

/// `y[m, dout] = x[m, din] · wᵀ + b` into a `y` of `m·dout` values (`w` `[dout, din]`).
#[allow(clippy::too_many_arguments)]
fn linear_fwd(
    par: Parallelism,
    w: &[f32],
    b: &[f32],
    x: &[f32],
    m: usize,
    din: usize,
    dout: usize,
    y: &mut [f32],
) {
    for row in y[..m * dout].chunks_exact_mut(dout) {
        row.copy_from_slice(b);
    }
    if small(par, m) {
        mm_nt(m, dout, din, y, x, w);
    } else {
        mm(par, m, dout, din, y, true, x, din, 1, w, 1, din);
    }
}

/// Backward of [`linear_fwd`]: accumulate `gw += dyᵀ·x`, `gb += Σ dy`; `dx` (if given) is
/// overwritten (`acc = false`) or accumulated with `dy · w`.
#[allow(clippy::too_many_arguments)]
fn linear_bwd(
    par: Parallelism,
    w: &[f32],
    gw: &mut [f32],
    gb: &mut [f32],
    x: &[f32],
    dy: &[f32],
    m: usize,
    din: usize,
    dout: usize,
    dx: Option<(&mut [f32], bool)>,
) {
    mm(par, dout, din, m, gw, true, dy, 1, dout, x, din, 1);
    for row in dy[..m * dout].chunks_exact(dout) {
        for (d, &v) in gb.iter_mut().zip(row) {
            *d += v;
        }
    }
    if let Some((dx, acc)) = dx {
        mm(par, m, din, dout, dx, acc, dy, dout, 1, w, din, 1);
    }
}

/// Two distinct elements of `v` mutably.
fn two_mut(v: &mut [Vec<f32>], a: usize, b: usize) -> (&mut [f32], &mut [f32]) {
    assert_ne!(a, b, "two_mut: the same buffer twice");
    if a < b {
        let (lo, hi) = v.split_at_mut(b);
        (&mut lo[a], &mut hi[0])
    } else {
        let (lo, hi) = v.split_at_mut(a);
        (&mut hi[0], &mut lo[b])
    }
}

/// `L` linear heads applied slot by slot: weight `[L, out, in]`, bias `[L, out]` (the
/// per-position FiLM heads). Inputs and outputs are slot-major: `x [L, m, in]`, `y [L, m, out]`.
#[derive(Debug)]
pub(crate) struct Heads {
    pub(crate) w: usize,
    pub(crate) b: usize,
    pub(crate) l: usize,
    pub(crate) din: usize,
    pub(crate) dout: usize,
}

impl Heads {
    /// `y[l, i, :] = W_l · x[l, i, :] + b_l`.
    pub(crate) fn fwd(
        &self,
        par: Parallelism,
        p: &[Vec<f32>],
        x: &[f32],
        m: usize,
        y: &mut Vec<f32>,
    ) {
        let (din, dout) = (self.din, self.dout);
        y.resize(self.l * m * dout, 0.0);
        for li in 0..self.l {
            linear_fwd(
                par,
                &p[self.w][li * dout * din..(li + 1) * dout * din],
                &p[self.b][li * dout..(li + 1) * dout],
                &x[li * m * din..(li + 1) * m * din],
                m,
                din,
                dout,
                &mut y[li * m * dout..(li + 1) * m * dout],
            );
        }
    }

    /// Accumulate `dW_l`, `db_l` and `dx` (slot-major, accumulated).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn bwd(
        &self,
        par: Parallelism,
        p: &[Vec<f32>],
        g: &mut [Vec<f32>],
        x: &[f32],
        dy: &[f32],
        m: usize,
        dx: &mut [f32],
    ) {
        let (din, dout) = (self.din, self.dout);
        let (gw, gb) = two_mut(g, self.w, self.b);
        for li in 0..self.l {
            linear_bwd(
                par,
                &p[self.w][li * dout * din..(li + 1) * dout * din],
                &mut gw[li * dout * din..(li + 1) * dout * din],
                &mut gb[li * dout..(li + 1) * dout],
                &x[li * m * din..(li + 1) * m * din],
                &dy[li * m * dout..(li + 1) * m * dout],
                m,
                din,
                dout,
                Some((&mut dx[li * m * din..(li + 1) * m * din], true)),
            );
        }
    }
}

/// How a convolution maps output positions to input positions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ConvMode {
    /// Same-padded, stride 1.
    Same,
    /// Same-padded, stride 2 (every even output position).
    Down2,
    /// Nearest ×2 up-sampling followed by a same-padded stride-1 convolution.
    Up2,
}

impl ConvMode {
    pub(crate) fn lout(self, lin: usize) -> usize {
        match self {
            ConvMode::Same => lin,
            ConvMode::Down2 => lin / 2,
            ConvMode::Up2 => 2 * lin,
        }
    }
    /// Input position read by tap `j` of output position `pos` (`None`: zero padding).
    #[inline]
    fn src(self, k: usize, lin: usize, pos: usize, j: usize) -> Option<usize> {
        let off = j as isize - (k / 2) as isize;
        match self {
            ConvMode::Same => {
                let q = pos as isize + off;
                (q >= 0 && (q as usize) < lin).then_some(q as usize)
            }
            ConvMode::Down2 => {
                let q = 2 * pos as isize + off;
                (q >= 0 && (q as usize) < lin).then_some(q as usize)
            }
            ConvMode::Up2 => {
                let u = pos as isize + off;
                (u >= 0 && (u as usize) < 2 * lin).then_some(u as usize / 2)
            }
        }
    }
}

/// `nn.Conv1d` on channels-last `[B, L, C]` (weight `[out, in, k]`, PyTorch layout) as
/// im2col (column index `c·K + j`) + one GEMM. Keeps its im2col matrix for the backward.
#[derive(Debug, Clone)]
pub(crate) struct Conv {
    pub(crate) w: usize,
    pub(crate) b: usize,
    pub(crate) cin: usize,
    pub(crate) cout: usize,
    pub(crate) k: usize,
    pub(crate) mode: ConvMode,
    cols: Vec<f32>,
}

impl Conv {
    pub(crate) fn new(
        w: usize,
        b: usize,
        cin: usize,
        cout: usize,
        k: usize,
        mode: ConvMode,
    ) -> Self {
        Self {
            w,
            b,
            cin,
            cout,
            k,
            mode,
            cols: Vec::new(),
        }
    }

    fn direct(&self) -> bool {
        self.k == 1 && self.mode == ConvMode::Same
    }

    fn im2col(&mut self, par: Parallelism, x: &[f32], b: usize, lin: usize) {
        let (c, k, mode) = (self.cin, self.k, self.mode);
        let lo = mode.lout(lin);
        let ck = c * k;
        self.cols.resize(b * lo * ck, 0.0);
        // One sample: rows `[lo, ck]` from `x` `[lin, c]`.
        let one = |cols: &mut [f32], x: &[f32]| {
            for (pos, row) in cols.chunks_exact_mut(ck).enumerate() {
                for j in 0..k {
                    match mode.src(k, lin, pos, j) {
                        Some(q) => {
                            for (ci, &v) in x[q * c..(q + 1) * c].iter().enumerate() {
                                row[ci * k + j] = v;
                            }
                        }
                        None => {
                            for ci in 0..c {
                                row[ci * k + j] = 0.0;
                            }
                        }
                    }
                }
            }
        };
        let (cols, x) = (&mut self.cols[..b * lo * ck], &x[..b * lin * c]);
        if threaded(par) {
            cols.par_chunks_mut(lo * ck)
                .zip(x.par_chunks(lin * c))
                .for_each(|(cs, xs)| one(cs, xs));
        } else {
            for (cs, xs) in cols.chunks_mut(lo * ck).zip(x.chunks(lin * c)) {
                one(cs, xs);
            }
        }
    }

    /// `y[B, Lout, cout]` from `x[B, lin, cin]`.
    pub(crate) fn fwd(
        &mut self,
        par: Parallelism,
        p: &[Vec<f32>],
        x: &[f32],
        b: usize,
        lin: usize,
        y: &mut Vec<f32>,
    ) {
        let lo = self.mode.lout(lin);
        let m = b * lo;
        let (o, ck) = (self.cout, self.cin * self.k);
        y.resize(m * o, 0.0);
        for row in y.chunks_exact_mut(o) {
            row.copy_from_slice(&p[self.b]);
        }
        if !self.direct() {
            self.im2col(par, x, b, lin);
        }
        let lhs: &[f32] = if self.direct() { x } else { &self.cols };
        if small(par, m) {
            mm_nt(m, o, ck, y, lhs, &p[self.w]);
        } else {
            mm(par, m, o, ck, y, true, lhs, ck, 1, &p[self.w], 1, ck);
        }
    }

    /// Accumulate `dW`, `db` and `dx[B, lin, cin]` (`dx` is added to, not overwritten).
    /// `x` is the forward input; `scratch` is any reusable buffer.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn bwd(
        &self,
        par: Parallelism,
        p: &[Vec<f32>],
        g: &mut [Vec<f32>],
        x: &[f32],
        dy: &[f32],
        b: usize,
        lin: usize,
        dx: Option<&mut [f32]>,
        scratch: &mut Vec<f32>,
    ) {
        let lo = self.mode.lout(lin);
        let m = b * lo;
        let (o, c, k) = (self.cout, self.cin, self.k);
        let ck = c * k;
        let cols: &[f32] = if self.direct() { x } else { &self.cols };
        mm(par, o, ck, m, &mut g[self.w], true, dy, 1, o, cols, ck, 1);
        let db = &mut g[self.b];
        for row in dy[..m * o].chunks_exact(o) {
            for (d, &v) in db.iter_mut().zip(row) {
                *d += v;
            }
        }
        let Some(dx) = dx else { return };
        if self.direct() {
            mm(par, m, ck, o, dx, true, dy, o, 1, &p[self.w], ck, 1);
            return;
        }
        scratch.resize(m * ck, 0.0);
        mm(par, m, ck, o, scratch, false, dy, o, 1, &p[self.w], ck, 1);
        let mode = self.mode;
        // One sample: scatter-add rows `[lo, ck]` into `dx` `[lin, c]`.
        let one = |rows: &[f32], dx: &mut [f32]| {
            for (pos, row) in rows.chunks_exact(ck).enumerate() {
                for j in 0..k {
                    if let Some(q) = mode.src(k, lin, pos, j) {
                        for (ci, d) in dx[q * c..(q + 1) * c].iter_mut().enumerate() {
                            *d += row[ci * k + j];
                        }
                    }
                }
            }
        };
        let (rows, dx) = (&scratch[..m * ck], &mut dx[..b * lin * c]);
        if threaded(par) {
            rows.par_chunks(lo * ck)
                .zip(dx.par_chunks_mut(lin * c))
                .for_each(|(r, d)| one(r, d));
        } else {
            for (r, d) in rows.chunks(lo * ck).zip(dx.chunks_mut(lin * c)) {
                one(r, d);
            }
        }
    }
}

/// GroupNorm (biased variance, `eps = 1e-5`, affine) followed by Mish, on channels-last
/// `[B, L, C]`. Keeps the normalised values and `1/σ` per (sample, group) for the backward.
/// With a rayon [`Parallelism`] the batch is split over the pool; the backward reduces `dγ`,
/// `dβ` over a fixed chunking of the batch, so its bits do not depend on the thread count.
#[derive(Debug, Clone)]
pub(crate) struct GnMish {
    pub(crate) gamma: usize,
    pub(crate) beta: usize,
    pub(crate) groups: usize,
    pub(crate) c: usize,
    xn: Vec<f32>,
    rstd: Vec<f32>,
    part: Vec<f32>,
}

/// Chunks of the batch for the backward's parameter-gradient partial sums.
const GN_CHUNKS: usize = 16;

/// Forward of one sample: `z`, `xn`, `out` `[l, c]`, `rstd` `[groups]`.
#[allow(clippy::too_many_arguments)]
fn gn_fwd_one(
    z: &[f32],
    xn: &mut [f32],
    out: &mut [f32],
    rstd: &mut [f32],
    gamma: &[f32],
    beta: &[f32],
    l: usize,
    c: usize,
) {
    let gr = rstd.len();
    let cg = c / gr;
    let inv = 1.0 / (l * cg) as f32;
    for gi in 0..gr {
        let ch = gi * cg..(gi + 1) * cg;
        let mut s = 0.0f32;
        for pos in 0..l {
            s += z[pos * c + ch.start..pos * c + ch.end].iter().sum::<f32>();
        }
        let mean = s * inv;
        let mut v = 0.0f32;
        for pos in 0..l {
            v += z[pos * c + ch.start..pos * c + ch.end]
                .iter()
                .map(|&t| (t - mean) * (t - mean))
                .sum::<f32>();
        }
        let r = 1.0 / (v * inv + 1e-5).sqrt();
        rstd[gi] = r;
        for pos in 0..l {
            let rg = pos * c + ch.start..pos * c + ch.end;
            for (((x, o), &zz), (&ga, &be)) in xn[rg.clone()]
                .iter_mut()
                .zip(&mut out[rg.clone()])
                .zip(&z[rg])
                .zip(gamma[ch.clone()].iter().zip(&beta[ch.clone()]))
            {
                let t = (zz - mean) * r;
                *x = t;
                *o = mish1(t * ga + be);
            }
        }
    }
}

/// Backward of a run of samples: `dz` from `da`; adds `Σ dy·xn` and `Σ dy` per channel to
/// `part` `[2c]`.
#[allow(clippy::too_many_arguments)]
fn gn_bwd_chunk(
    da: &[f32],
    xn: &[f32],
    rstd: &[f32],
    dz: &mut [f32],
    part: &mut [f32],
    gamma: &[f32],
    beta: &[f32],
    l: usize,
    c: usize,
    gr: usize,
) {
    let cg = c / gr;
    let inv = 1.0 / (l * cg) as f32;
    let (pg, pb) = part.split_at_mut(c);
    for (((dz, xn), da), rstd) in dz
        .chunks_exact_mut(l * c)
        .zip(xn.chunks_exact(l * c))
        .zip(da.chunks_exact(l * c))
        .zip(rstd.chunks_exact(gr))
    {
        for ((dzr, xr), dar) in dz
            .chunks_exact_mut(c)
            .zip(xn.chunks_exact(c))
            .zip(da.chunks_exact(c))
        {
            for ci in 0..c {
                let y = xr[ci] * gamma[ci] + beta[ci];
                let dy = dar[ci] * mish_and_grad(y).1;
                pg[ci] += dy * xr[ci];
                pb[ci] += dy;
                dzr[ci] = dy * gamma[ci];
            }
        }
        for gi in 0..gr {
            let ch = gi * cg..(gi + 1) * cg;
            let (mut s1, mut s2) = (0.0f32, 0.0f32);
            for pos in 0..l {
                let r = pos * c + ch.start..pos * c + ch.end;
                for (&d, &x) in dz[r.clone()].iter().zip(&xn[r]) {
                    s1 += d;
                    s2 += d * x;
                }
            }
            let (m1, m2) = (s1 * inv, s2 * inv);
            let rs = rstd[gi];
            for pos in 0..l {
                let r = pos * c + ch.start..pos * c + ch.end;
                for (d, &x) in dz[r.clone()].iter_mut().zip(&xn[r]) {
                    *d = rs * (*d - m1 - x * m2);
                }
            }
        }
    }
}

impl GnMish {
    pub(crate) fn new(gamma: usize, beta: usize, groups: usize, c: usize) -> Self {
        Self {
            gamma,
            beta,
            groups,
            c,
            xn: Vec::new(),
            rstd: Vec::new(),
            part: Vec::new(),
        }
    }

    /// `out = mish(GN(z))`.
    pub(crate) fn fwd(
        &mut self,
        par: Parallelism,
        p: &[Vec<f32>],
        z: &[f32],
        b: usize,
        l: usize,
        out: &mut Vec<f32>,
    ) {
        let (c, gr) = (self.c, self.groups);
        let (lc, n) = (l * c, b * l * c);
        self.xn.resize(n, 0.0);
        self.rstd.resize(b * gr, 0.0);
        out.resize(n, 0.0);
        let (gamma, beta) = (&p[self.gamma][..], &p[self.beta][..]);
        let one = |z: &[f32], xn: &mut [f32], o: &mut [f32], r: &mut [f32]| {
            gn_fwd_one(z, xn, o, r, gamma, beta, l, c)
        };
        let (xn, rstd, z) = (&mut self.xn[..n], &mut self.rstd[..b * gr], &z[..n]);
        if threaded(par) {
            xn.par_chunks_mut(lc)
                .zip(out.par_chunks_mut(lc))
                .zip(z.par_chunks(lc))
                .zip(rstd.par_chunks_mut(gr))
                .for_each(|(((x, o), z), r)| one(z, x, o, r));
        } else {
            for (((x, o), z), r) in xn
                .chunks_mut(lc)
                .zip(out.chunks_mut(lc))
                .zip(z.chunks(lc))
                .zip(rstd.chunks_mut(gr))
            {
                one(z, x, o, r);
            }
        }
    }

    /// `dz` (overwritten) from `da`; accumulates `dγ`, `dβ`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn bwd(
        &mut self,
        par: Parallelism,
        p: &[Vec<f32>],
        g: &mut [Vec<f32>],
        da: &[f32],
        b: usize,
        l: usize,
        dz: &mut Vec<f32>,
    ) {
        let (c, gr) = (self.c, self.groups);
        let (lc, n) = (l * c, b * l * c);
        dz.resize(n, 0.0);
        let (gamma, beta) = (&p[self.gamma][..], &p[self.beta][..]);
        let per = b.div_ceil(GN_CHUNKS).max(1);
        let chunks = b.div_ceil(per);
        self.part.clear();
        self.part.resize(chunks * 2 * c, 0.0);
        let one = |da: &[f32], xn: &[f32], r: &[f32], dz: &mut [f32], part: &mut [f32]| {
            gn_bwd_chunk(da, xn, r, dz, part, gamma, beta, l, c, gr)
        };
        let (dzs, das, xns, rs) = (&mut dz[..n], &da[..n], &self.xn[..n], &self.rstd[..b * gr]);
        if threaded(par) {
            dzs.par_chunks_mut(per * lc)
                .zip(das.par_chunks(per * lc))
                .zip(xns.par_chunks(per * lc))
                .zip(rs.par_chunks(per * gr))
                .zip(self.part.par_chunks_mut(2 * c))
                .for_each(|((((dz, da), xn), r), part)| one(da, xn, r, dz, part));
        } else {
            for ((((dz, da), xn), r), part) in dzs
                .chunks_mut(per * lc)
                .zip(das.chunks(per * lc))
                .zip(xns.chunks(per * lc))
                .zip(rs.chunks(per * gr))
                .zip(self.part.chunks_mut(2 * c))
            {
                one(da, xn, r, dz, part);
            }
        }
        for part in self.part.chunks_exact(2 * c) {
            for (d, &v) in g[self.gamma].iter_mut().zip(&part[..c]) {
                *d += v;
            }
            for (d, &v) in g[self.beta].iter_mut().zip(&part[c..]) {
                *d += v;
            }
        }
    }
}

/// `y[m×n] += x[m×k] · wᵀ` with `x` and `w` (`[n×k]`) row-major: the GEMM of a forward layer
/// at small `m` (batch-1 inference), allocation-free (the `gemm` crate allocates its packing
/// buffers on every call). AVX2 + FMA where the CPU has them, portable loops otherwise.
pub(crate) fn mm_nt(m: usize, n: usize, k: usize, y: &mut [f32], x: &[f32], w: &[f32]) {
    assert!(
        y.len() >= m * n && x.len() >= m * k && w.len() >= n * k,
        "mm_nt: short operand"
    );
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports AVX2 and FMA (checked above); operand lengths are
            // asserted above and every access below stays within `m·k`, `n·k`, `m·n`.
            unsafe { mm_nt_avx2(m, n, k, y, x, w) };
            return;
        }
    }
    mm_nt_portable(m, n, k, y, x, w);
}

fn mm_nt_portable(m: usize, n: usize, k: usize, y: &mut [f32], x: &[f32], w: &[f32]) {
    for i in 0..m {
        let xr = &x[i * k..(i + 1) * k];
        for j in 0..n {
            y[i * n + j] += dot_portable(xr, &w[j * k..(j + 1) * k]);
        }
    }
}

#[inline]
fn dot_portable(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for t in 0..8 {
            acc[t] += x[t] * y[t];
        }
    }
    let mut s = (acc[0] + acc[4]) + (acc[1] + acc[5]) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn hsum256(v: std::arch::x86_64::__m256) -> f32 {
    use std::arch::x86_64::*;
    let lo = _mm256_castps256_ps128(v);
    let hi = _mm256_extractf128_ps::<1>(v);
    let s = _mm_add_ps(lo, hi);
    let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    let s = _mm_add_ss(s, _mm_shuffle_ps::<0b01>(s, s));
    _mm_cvtss_f32(s)
}

/// Register tile: 4 rows of `x` × 2 rows of `w`, 8 lanes along `k`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn mm_nt_avx2(m: usize, n: usize, k: usize, y: &mut [f32], x: &[f32], w: &[f32]) {
    use std::arch::x86_64::*;
    let k8 = k / 8 * 8;
    let xp = x.as_ptr();
    let wp = w.as_ptr();
    // SAFETY (whole body): indices are bounded by the caller's length asserts: rows i < m,
    // j < n, lanes p + 8 ≤ k8 ≤ k.
    unsafe {
        let dot1 = |i: usize, j: usize| -> f32 {
            let (xr, wr) = (xp.add(i * k), wp.add(j * k));
            let mut a0 = _mm256_setzero_ps();
            let mut a1 = _mm256_setzero_ps();
            let mut p = 0;
            while p + 16 <= k8 {
                a0 = _mm256_fmadd_ps(_mm256_loadu_ps(xr.add(p)), _mm256_loadu_ps(wr.add(p)), a0);
                a1 = _mm256_fmadd_ps(
                    _mm256_loadu_ps(xr.add(p + 8)),
                    _mm256_loadu_ps(wr.add(p + 8)),
                    a1,
                );
                p += 16;
            }
            while p < k8 {
                a0 = _mm256_fmadd_ps(_mm256_loadu_ps(xr.add(p)), _mm256_loadu_ps(wr.add(p)), a0);
                p += 8;
            }
            let mut s = hsum256(_mm256_add_ps(a0, a1));
            for q in k8..k {
                s += *xr.add(q) * *wr.add(q);
            }
            s
        };
        let mut i = 0;
        while i + 4 <= m {
            let mut j = 0;
            while j + 2 <= n {
                let x0 = xp.add(i * k);
                let x1 = xp.add((i + 1) * k);
                let x2 = xp.add((i + 2) * k);
                let x3 = xp.add((i + 3) * k);
                let w0 = wp.add(j * k);
                let w1 = wp.add((j + 1) * k);
                let mut c00 = _mm256_setzero_ps();
                let mut c01 = _mm256_setzero_ps();
                let mut c10 = _mm256_setzero_ps();
                let mut c11 = _mm256_setzero_ps();
                let mut c20 = _mm256_setzero_ps();
                let mut c21 = _mm256_setzero_ps();
                let mut c30 = _mm256_setzero_ps();
                let mut c31 = _mm256_setzero_ps();
                let mut p = 0;
                while p < k8 {
                    let b0 = _mm256_loadu_ps(w0.add(p));
                    let b1 = _mm256_loadu_ps(w1.add(p));
                    let a = _mm256_loadu_ps(x0.add(p));
                    c00 = _mm256_fmadd_ps(a, b0, c00);
                    c01 = _mm256_fmadd_ps(a, b1, c01);
                    let a = _mm256_loadu_ps(x1.add(p));
                    c10 = _mm256_fmadd_ps(a, b0, c10);
                    c11 = _mm256_fmadd_ps(a, b1, c11);
                    let a = _mm256_loadu_ps(x2.add(p));
                    c20 = _mm256_fmadd_ps(a, b0, c20);
                    c21 = _mm256_fmadd_ps(a, b1, c21);
                    let a = _mm256_loadu_ps(x3.add(p));
                    c30 = _mm256_fmadd_ps(a, b0, c30);
                    c31 = _mm256_fmadd_ps(a, b1, c31);
                    p += 8;
                }
                let acc = [[c00, c01], [c10, c11], [c20, c21], [c30, c31]];
                for (a, row) in acc.iter().enumerate() {
                    for (b, v) in row.iter().enumerate() {
                        let mut s = hsum256(*v);
                        let (xr, wr) = (xp.add((i + a) * k), wp.add((j + b) * k));
                        for q in k8..k {
                            s += *xr.add(q) * *wr.add(q);
                        }
                        y[(i + a) * n + j + b] += s;
                    }
                }
                j += 2;
            }
            while j < n {
                for a in 0..4 {
                    y[(i + a) * n + j] += dot1(i + a, j);
                }
                j += 1;
            }
            i += 4;
        }
        while i < m {
            for j in 0..n {
                y[i * n + j] += dot1(i, j);
            }
            i += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mm_nt_matches_a_naive_product_on_ragged_shapes() {
        for &(m, n, k) in &[(7, 5, 19), (4, 2, 8), (16, 33, 1280), (1, 1, 3), (9, 4, 40)] {
            let x: Vec<f32> = (0..m * k)
                .map(|i| ((i * 7 % 13) as f32 - 6.0) * 0.1)
                .collect();
            let w: Vec<f32> = (0..n * k)
                .map(|i| ((i * 5 % 11) as f32 - 5.0) * 0.1)
                .collect();
            let mut y = vec![0.5f32; m * n];
            mm_nt(m, n, k, &mut y, &x, &w);
            for i in 0..m {
                for j in 0..n {
                    let want: f64 = 0.5
                        + (0..k)
                            .map(|p| x[i * k + p] as f64 * w[j * k + p] as f64)
                            .sum::<f64>();
                    let got = y[i * n + j] as f64;
                    assert!(
                        (got - want).abs() < 1e-4 * (1.0 + want.abs()),
                        "({m},{n},{k})[{i},{j}]: {got} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn fast_exp_and_mish_match_libm() {
        for i in -2000..=2000 {
            let x = i as f32 * 0.01;
            let (e, r) = (fast_exp(x), x.exp());
            assert!((e - r).abs() <= 4e-7 * r, "exp({x}): {e} vs {r}");
            let reference = x * (x.max(0.0) + (-x.abs()).exp().ln_1p()).tanh();
            let (mv, dm) = mish_and_grad(x);
            assert!(
                (mv - reference).abs() <= 1e-6 * (1.0 + reference.abs()),
                "mish({x})"
            );
            let h = 1e-3f32;
            let num = (mish1(x + h) as f64 - mish1(x - h) as f64) / (2.0 * h as f64);
            assert!((dm as f64 - num).abs() < 2e-3, "mish'({x}): {dm} vs {num}");
        }
    }
}
