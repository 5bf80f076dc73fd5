//! A small multi-layer perceptron with hand-written backpropagation, and Adam.
//!
//! Parameters live in one flat `f32` vector (per layer: the weight matrix `out × in`,
//! row-major, then the bias), so that the optimiser, gradient clipping and serialisation
//! treat a network as one slice. Activations are batched row-major (`batch × width`); the
//! matrix products run on the `gemm` crate's kernels (runtime-dispatched SIMD) on the
//! calling thread, so one call's result depends only on its inputs — callers split batches
//! into fixed chunks to use several threads without changing a bit of the result.

use pir2_schedule::Rng;

/// `dst (m × n, row-major) = [dst +] lhs · rhs`, where element `(i, p)` of `lhs` is
/// `lhs[i·lhs_rs + p·lhs_cs]` and element `(p, j)` of `rhs` is `rhs[p·rhs_rs + j·rhs_cs]`.
#[allow(clippy::too_many_arguments)]
fn matmul(
    m: usize,
    n: usize,
    k: usize,
    dst: &mut [f32],
    accumulate: bool,
    lhs: &[f32],
    (lhs_rs, lhs_cs): (usize, usize),
    rhs: &[f32],
    (rhs_rs, rhs_cs): (usize, usize),
) {
    if m == 0 || n == 0 {
        return;
    }
    assert!(dst.len() >= m * n, "matmul: dst too small");
    if k == 0 {
        if !accumulate {
            dst[..m * n].fill(0.0);
        }
        return;
    }
    assert!(
        (m - 1) * lhs_rs + (k - 1) * lhs_cs < lhs.len(),
        "matmul: lhs out of bounds"
    );
    assert!(
        (k - 1) * rhs_rs + (n - 1) * rhs_cs < rhs.len(),
        "matmul: rhs out of bounds"
    );
    // SAFETY: the asserts above keep every index gemm reads (`lhs`, `rhs`) or writes
    // (`dst`, m × n with row stride n) inside the slices; the slices do not alias (`dst` is
    // the only mutable borrow). gemm computes `dst = 1·dst + 1·lhs·rhs` (or `lhs·rhs` when
    // `accumulate` is false, without reading `dst`).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            1.0f32,
            1.0f32,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// Hidden-layer non-linearity (the output layer is linear).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// `x · sigmoid(x)` ("swish", the playground's choice).
    Silu,
    /// `tanh(x)`.
    Tanh,
}

impl Activation {
    /// Name used in weight files.
    pub fn name(self) -> &'static str {
        match self {
            Self::Silu => "silu",
            Self::Tanh => "tanh",
        }
    }

    /// Inverse of [`name`](Self::name).
    pub fn from_name(s: &str) -> Option<Self> {
        match s {
            "silu" => Some(Self::Silu),
            "tanh" => Some(Self::Tanh),
            _ => None,
        }
    }

    #[inline]
    fn apply(self, z: f32) -> f32 {
        match self {
            Self::Silu => z / (1.0 + (-z).exp()),
            Self::Tanh => z.tanh(),
        }
    }

    /// Derivative at pre-activation `z`.
    #[inline]
    fn grad(self, z: f32) -> f32 {
        match self {
            Self::Silu => {
                let s = 1.0 / (1.0 + (-z).exp());
                s * (1.0 + z * (1.0 - s))
            }
            Self::Tanh => {
                let t = z.tanh();
                1.0 - t * t
            }
        }
    }
}

/// A fully connected network `sizes[0] → … → sizes[last]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Mlp {
    sizes: Vec<usize>,
    act: Activation,
    /// Flat parameters (see the module docs).
    pub params: Vec<f32>,
}

/// Per-call scratch: the activations a backward pass needs.
#[derive(Debug, Clone, Default)]
pub struct MlpCache {
    batch: usize,
    /// `post[0]` is the input, `post[l + 1]` the output of layer `l` (after the activation
    /// for hidden layers).
    post: Vec<Vec<f32>>,
    /// Pre-activations of the hidden layers.
    pre: Vec<Vec<f32>>,
    /// Gradient scratch (two buffers, swapped layer by layer).
    d_a: Vec<f32>,
    d_b: Vec<f32>,
}

impl Mlp {
    /// A network with the given layer sizes (≥ 2 entries), weights drawn from
    /// `U(±√(1/fan_in))·gain` (hidden layers gain 1, the output layer `out_gain`), zero biases.
    pub fn new(sizes: &[usize], act: Activation, out_gain: f32, rng: &mut Rng) -> Self {
        assert!(sizes.len() >= 2, "Mlp needs an input and an output size");
        let n: usize = sizes.windows(2).map(|w| w[1] * (w[0] + 1)).sum();
        let mut params = Vec::with_capacity(n);
        let layers = sizes.len() - 1;
        for (l, w) in sizes.windows(2).enumerate() {
            let (fan_in, out) = (w[0], w[1]);
            let gain = if l + 1 == layers { out_gain } else { 1.0 };
            // Uniform with variance 2/fan_in (He) for hidden layers; scaled for the output.
            let bound = (6.0 / fan_in as f32).sqrt() * gain;
            for _ in 0..out * fan_in {
                params.push(rng.uniform_range(-bound, bound));
            }
            params.extend(std::iter::repeat_n(0.0, out));
        }
        Self {
            sizes: sizes.to_vec(),
            act,
            params,
        }
    }

    /// A network from its sizes, activation and flat parameters (length checked).
    pub fn from_params(sizes: &[usize], act: Activation, params: Vec<f32>) -> Option<Self> {
        let n: usize = sizes.windows(2).map(|w| w[1] * (w[0] + 1)).sum();
        (sizes.len() >= 2 && params.len() == n).then(|| Self {
            sizes: sizes.to_vec(),
            act,
            params,
        })
    }

    /// Layer sizes, input first.
    pub fn sizes(&self) -> &[usize] {
        &self.sizes
    }

    /// The hidden non-linearity.
    pub fn activation(&self) -> Activation {
        self.act
    }

    /// Input width.
    pub fn input_dim(&self) -> usize {
        self.sizes[0]
    }

    /// Output width.
    pub fn output_dim(&self) -> usize {
        *self.sizes.last().expect("sizes is non-empty")
    }

    /// Offsets of `(weights, bias)` of layer `l` in `params`.
    fn offsets(&self, l: usize) -> (usize, usize) {
        let mut off = 0;
        for w in self.sizes.windows(2).take(l) {
            off += w[1] * (w[0] + 1);
        }
        (off, off + self.sizes[l + 1] * self.sizes[l])
    }

    /// Forward pass over `batch` rows of `x` (`batch × input_dim`), keeping what
    /// [`backward`](Self::backward) needs in `cache`; returns the output (`batch × output_dim`).
    pub fn forward<'c>(&self, x: &[f32], batch: usize, cache: &'c mut MlpCache) -> &'c [f32] {
        assert_eq!(
            x.len(),
            batch * self.input_dim(),
            "Mlp::forward: input size"
        );
        let layers = self.sizes.len() - 1;
        cache.batch = batch;
        cache.post.resize_with(layers + 1, Vec::new);
        cache.pre.resize_with(layers.saturating_sub(1), Vec::new);
        cache.post[0].clear();
        cache.post[0].extend_from_slice(x);
        for l in 0..layers {
            let (fi, fo) = (self.sizes[l], self.sizes[l + 1]);
            let (wo, bo) = self.offsets(l);
            let (inputs, outputs) = cache.post.split_at_mut(l + 1);
            let out = &mut outputs[0];
            out.resize(batch * fo, 0.0);
            // Y (B × fo) = X (B × fi) · Wᵀ (fi × fo)
            let w = &self.params[wo..bo];
            matmul(batch, fo, fi, out, false, &inputs[l], (fi, 1), w, (1, fi));
            let bias = &self.params[bo..bo + fo];
            for row in out.chunks_exact_mut(fo) {
                for (v, b) in row.iter_mut().zip(bias) {
                    *v += b;
                }
            }
            if l + 1 < layers {
                let pre = &mut cache.pre[l];
                pre.clear();
                pre.extend_from_slice(out);
                for v in out.iter_mut() {
                    *v = self.act.apply(*v);
                }
            }
        }
        &cache.post[layers]
    }

    /// Forward pass of one row `x` (`input_dim`) with a summation order fixed in the source
    /// (eight interleaved partial sums per output, added pairwise, then the bias), so that
    /// the result is the same on every CPU: [`forward`](Self::forward) runs on the `gemm`
    /// crate, whose kernels are chosen at run time (AVX2, AVX-512, …) and sum in a different
    /// order on different machines. Data generated with an expert (demonstrations) must not
    /// depend on the machine that generated them, so experts act through this path. It
    /// agrees with [`forward`](Self::forward) to rounding. `scratch` holds the two
    /// activation buffers between calls; returns the output (`output_dim`).
    pub fn forward_portable<'s>(&self, x: &[f32], scratch: &'s mut [Vec<f32>; 2]) -> &'s [f32] {
        assert_eq!(
            x.len(),
            self.input_dim(),
            "Mlp::forward_portable: input size"
        );
        let layers = self.sizes.len() - 1;
        let [a, b] = scratch;
        a.clear();
        a.extend_from_slice(x);
        for l in 0..layers {
            let (fi, fo) = (self.sizes[l], self.sizes[l + 1]);
            let (wo, bo) = self.offsets(l);
            let w = &self.params[wo..bo];
            let bias = &self.params[bo..bo + fo];
            b.clear();
            for (row, &bias) in w.chunks_exact(fi).zip(bias) {
                let mut lane = [0.0f32; 8];
                let mut wc = row.chunks_exact(8);
                let mut xc = a.chunks_exact(8);
                for (w8, x8) in (&mut wc).zip(&mut xc) {
                    for k in 0..8 {
                        lane[k] += w8[k] * x8[k];
                    }
                }
                for (k, (wv, xv)) in wc.remainder().iter().zip(xc.remainder()).enumerate() {
                    lane[k] += wv * xv;
                }
                let s = ((lane[0] + lane[1]) + (lane[2] + lane[3]))
                    + ((lane[4] + lane[5]) + (lane[6] + lane[7]));
                let z = s + bias;
                b.push(if l + 1 < layers { self.act.apply(z) } else { z });
            }
            std::mem::swap(a, b);
        }
        a
    }

    /// Backward pass for the last [`forward`](Self::forward) through `cache`: given
    /// `d_out = ∂L/∂output` (`batch × output_dim`), **adds** `∂L/∂params` to `grad`.
    pub fn backward(&self, cache: &mut MlpCache, d_out: &[f32], grad: &mut [f32]) {
        let batch = cache.batch;
        assert_eq!(
            d_out.len(),
            batch * self.output_dim(),
            "Mlp::backward: d_out"
        );
        assert_eq!(grad.len(), self.params.len(), "Mlp::backward: grad size");
        let layers = self.sizes.len() - 1;
        let mut dz = std::mem::take(&mut cache.d_a);
        let mut dx = std::mem::take(&mut cache.d_b);
        dz.clear();
        dz.extend_from_slice(d_out);
        for l in (0..layers).rev() {
            let (fi, fo) = (self.sizes[l], self.sizes[l + 1]);
            let (wo, bo) = self.offsets(l);
            if l + 1 < layers {
                for (d, &z) in dz.iter_mut().zip(&cache.pre[l]) {
                    *d *= self.act.grad(z);
                }
            }
            let (gw, gb) = grad[wo..bo + fo].split_at_mut(bo - wo);
            // dW (fo × fi) += dZᵀ (fo × B) · X (B × fi)
            matmul(
                fo,
                fi,
                batch,
                gw,
                true,
                &dz,
                (1, fo),
                &cache.post[l],
                (fi, 1),
            );
            for row in dz.chunks_exact(fo) {
                for (g, d) in gb.iter_mut().zip(row) {
                    *g += d;
                }
            }
            if l > 0 {
                // dX (B × fi) = dZ (B × fo) · W (fo × fi)
                dx.resize(batch * fi, 0.0);
                let w = &self.params[wo..bo];
                matmul(batch, fi, fo, &mut dx, false, &dz, (fo, 1), w, (fi, 1));
                std::mem::swap(&mut dz, &mut dx);
            }
        }
        cache.d_a = dz;
        cache.d_b = dx;
    }
}

/// Adam (Kingma & Ba) with bias correction, over one flat parameter slice.
#[derive(Debug, Clone, PartialEq)]
pub struct Adam {
    /// First-moment estimate.
    pub m: Vec<f32>,
    /// Second-moment estimate.
    pub v: Vec<f32>,
    /// Steps taken.
    pub t: u64,
    /// `β₁`.
    pub beta1: f32,
    /// `β₂`.
    pub beta2: f32,
    /// `ε`.
    pub eps: f32,
}

impl Adam {
    /// Zero moments for `n` parameters (β₁ 0.9, β₂ 0.999, ε 1e-8).
    pub fn new(n: usize) -> Self {
        Self {
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        }
    }

    /// One update `params −= lr · m̂ / (√v̂ + ε)`.
    pub fn step(&mut self, params: &mut [f32], grad: &[f32], lr: f32) {
        assert_eq!(params.len(), self.m.len(), "Adam::step: parameter count");
        assert_eq!(grad.len(), self.m.len(), "Adam::step: gradient size");
        self.t += 1;
        let (b1, b2) = (self.beta1, self.beta2);
        let c1 = 1.0 - b1.powi(self.t.min(i32::MAX as u64) as i32);
        let c2 = 1.0 - b2.powi(self.t.min(i32::MAX as u64) as i32);
        let step = lr / c1;
        let c2s = c2.sqrt();
        for i in 0..params.len() {
            let g = grad[i];
            self.m[i] = b1 * self.m[i] + (1.0 - b1) * g;
            self.v[i] = b2 * self.v[i] + (1.0 - b2) * g * g;
            params[i] -= step * self.m[i] / (self.v[i].sqrt() / c2s + self.eps);
        }
    }
}

/// Scale `grads` (several slices, one global norm) so that their joint L2 norm is at most
/// `max_norm`; returns the norm before clipping.
pub fn clip_global_norm(grads: &mut [&mut [f32]], max_norm: f32) -> f32 {
    let sq: f64 = grads
        .iter()
        .flat_map(|g| g.iter())
        .map(|&v| f64::from(v) * f64::from(v))
        .sum();
    let norm = sq.sqrt() as f32;
    if norm > max_norm && norm.is_finite() {
        let s = max_norm / norm;
        for g in grads.iter_mut() {
            g.iter_mut().for_each(|v| *v *= s);
        }
    }
    norm
}

#[cfg(test)]
mod tests {
    use super::*;

    /// L = Σ c ⊙ out with fixed random c, so ∂L/∂out = c.
    fn loss(net: &Mlp, x: &[f32], batch: usize, c: &[f32]) -> f64 {
        let mut cache = MlpCache::default();
        let out = net.forward(x, batch, &mut cache);
        out.iter()
            .zip(c)
            .map(|(o, c)| f64::from(*o) * f64::from(*c))
            .sum()
    }

    fn check_grad(act: Activation) {
        let mut rng = Rng::new(11);
        let net = Mlp::new(&[5, 7, 6, 3], act, 1.0, &mut rng);
        let batch = 4;
        let x: Vec<f32> = (0..batch * 5).map(|_| rng.normal()).collect();
        let c: Vec<f32> = (0..batch * 3).map(|_| rng.normal()).collect();
        let mut cache = MlpCache::default();
        net.forward(&x, batch, &mut cache);
        let mut grad = vec![0.0; net.params.len()];
        net.backward(&mut cache, &c, &mut grad);
        // f64 reference by central differences on an f64 copy is overkill: f32 with a
        // relative step is accurate to ~1e-3 here.
        let mut worst = 0.0f64;
        for i in 0..net.params.len() {
            let h = 1e-2f32;
            let mut p = net.clone();
            p.params[i] += h;
            let lp = loss(&p, &x, batch, &c);
            p.params[i] -= 2.0 * h;
            let lm = loss(&p, &x, batch, &c);
            let fd = (lp - lm) / (2.0 * f64::from(h));
            let err = (fd - f64::from(grad[i])).abs() / (1.0 + fd.abs());
            worst = worst.max(err);
        }
        assert!(
            worst < 2e-3,
            "{act:?}: worst relative gradient error {worst}"
        );
        // The gradient is not trivially zero.
        assert!(grad.iter().any(|g| g.abs() > 1e-2));
    }

    #[test]
    fn mlp_backward_matches_finite_differences_silu() {
        check_grad(Activation::Silu);
    }

    #[test]
    fn mlp_backward_matches_finite_differences_tanh() {
        check_grad(Activation::Tanh);
    }

    #[test]
    fn mlp_rows_are_independent_of_the_batch_split() {
        let mut rng = Rng::new(5);
        let net = Mlp::new(&[9, 33, 17, 4], Activation::Silu, 0.1, &mut rng);
        let x: Vec<f32> = (0..40 * 9).map(|_| rng.normal()).collect();
        let mut cache = MlpCache::default();
        let all = net.forward(&x, 40, &mut cache).to_vec();
        let mut parts = Vec::new();
        for chunk in x.chunks(8 * 9) {
            parts.extend_from_slice(net.forward(chunk, chunk.len() / 9, &mut cache));
        }
        // Not required to be bit-equal across batch sizes; close to rounding.
        for (a, b) in all.iter().zip(&parts) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
    }

    #[test]
    fn portable_forward_agrees_with_the_batched_one() {
        let mut rng = Rng::new(7);
        let net = Mlp::new(&[57, 61, 33, 16], Activation::Silu, 0.5, &mut rng);
        let mut cache = MlpCache::default();
        let mut scratch = Default::default();
        for _ in 0..5 {
            let x: Vec<f32> = (0..57).map(|_| rng.normal()).collect();
            let want = net.forward(&x, 1, &mut cache).to_vec();
            let got = net.forward_portable(&x, &mut scratch).to_vec();
            assert_eq!(got.len(), 16);
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-5 * (1.0 + w.abs()), "{g} vs {w}");
            }
        }
    }

    /// The portable path's bits are fixed by the source, not by the CPU: a golden value
    /// (computed once; the weights span many binades, so a different order of the sums would
    /// round differently).
    #[test]
    fn portable_forward_bits_are_fixed() {
        let sizes = [19, 11, 3];
        let n: usize = sizes.windows(2).map(|w| w[1] * (w[0] + 1)).sum();
        // Weights spanning many binades so that summation order changes the rounding.
        let params: Vec<f32> = (0..n)
            .map(|i| {
                let e = (i * 7 % 23) as i32 - 11;
                let s = if i % 3 == 0 { -1.0 } else { 1.0 };
                s * (1.0 + (i % 5) as f32 / 7.0) * 2f32.powi(e)
            })
            .collect();
        let net = Mlp::from_params(&sizes, Activation::Tanh, params).expect("sizes");
        let x: Vec<f32> = (0..19).map(|i| i as f32 * 0.37 - 3.1).collect();
        let out = net.forward_portable(&x, &mut Default::default()).to_vec();
        let bits: Vec<u32> = out.iter().map(|v| v.to_bits()).collect();
        assert_eq!(bits, GOLDEN_PORTABLE_BITS, "{out:?}");
        // The golden value does pin the order: summing each row left to right instead
        // changes the bits of at least one output.
        let mut h: Vec<f32> = Vec::new();
        let (w1, b1) = (&net.params[..19 * 11], &net.params[19 * 11..20 * 11]);
        for (row, b) in w1.chunks_exact(19).zip(b1) {
            let s = row.iter().zip(&x).fold(0.0f32, |s, (w, v)| s + w * v);
            h.push((s + b).tanh());
        }
        let (w2, b2) = (
            &net.params[20 * 11..20 * 11 + 33],
            &net.params[20 * 11 + 33..],
        );
        let seq: Vec<u32> = w2
            .chunks_exact(11)
            .zip(b2)
            .map(|(row, b)| (row.iter().zip(&h).fold(0.0f32, |s, (w, v)| s + w * v) + b).to_bits())
            .collect();
        assert_ne!(
            seq, bits,
            "the test weights do not make the summation order visible"
        );
    }

    const GOLDEN_PORTABLE_BITS: [u32; 3] = [1153209119, 1151165958, 1163006705];

    #[test]
    fn adam_descends_a_quadratic() {
        let mut p = vec![3.0f32, -2.0];
        let mut opt = Adam::new(2);
        for _ in 0..2000 {
            let g = vec![2.0 * p[0], 2.0 * p[1]];
            opt.step(&mut p, &g, 1e-2);
        }
        assert!(p[0].abs() < 1e-2 && p[1].abs() < 1e-2, "{p:?}");
    }

    #[test]
    fn clip_global_norm_scales_to_the_bound() {
        let mut a = [3.0f32];
        let mut b = [4.0f32];
        let n = clip_global_norm(&mut [&mut a[..], &mut b[..]], 1.0);
        assert!((n - 5.0).abs() < 1e-6);
        assert!((a[0] - 0.6).abs() < 1e-6 && (b[0] - 0.8).abs() < 1e-6);
    }
}
