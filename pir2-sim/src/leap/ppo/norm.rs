//! Running observation normalisation (mean and variance over everything seen so far).

/// Per-dimension running mean and variance (Chan et al.'s parallel update, in `f64`).
#[derive(Debug, Clone, PartialEq)]
pub struct RunningNorm {
    /// Samples seen.
    pub count: f64,
    /// Running mean.
    pub mean: Vec<f64>,
    /// Running sum of squared deviations.
    pub m2: Vec<f64>,
}

/// Normalised values are clipped to `±CLIP`.
pub const CLIP: f32 = 10.0;
/// Standard deviations are floored at this value.
pub const MIN_STD: f64 = 1e-4;

impl RunningNorm {
    /// Empty statistics (normalising with them is the identity).
    pub fn new(dim: usize) -> Self {
        Self {
            count: 0.0,
            mean: vec![0.0; dim],
            m2: vec![0.0; dim],
        }
    }

    /// Width.
    pub fn dim(&self) -> usize {
        self.mean.len()
    }

    /// Fold in the rows of `x` (`rows × dim`, row-major), in order.
    pub fn update(&mut self, x: &[f32]) {
        let d = self.dim();
        assert_eq!(x.len() % d, 0, "RunningNorm::update: ragged input");
        let n = (x.len() / d) as f64;
        if n == 0.0 {
            return;
        }
        let mut bmean = vec![0.0f64; d];
        for row in x.chunks_exact(d) {
            for (m, &v) in bmean.iter_mut().zip(row) {
                *m += f64::from(v);
            }
        }
        bmean.iter_mut().for_each(|m| *m /= n);
        let mut bm2 = vec![0.0f64; d];
        for row in x.chunks_exact(d) {
            for k in 0..d {
                let e = f64::from(row[k]) - bmean[k];
                bm2[k] += e * e;
            }
        }
        let tot = self.count + n;
        for k in 0..d {
            let delta = bmean[k] - self.mean[k];
            self.mean[k] += delta * n / tot;
            self.m2[k] += bm2[k] + delta * delta * self.count * n / tot;
        }
        self.count = tot;
    }

    /// `(mean, std)` as `f32`, the frozen form used to normalise (identity while empty).
    pub fn frozen(&self) -> FrozenNorm {
        let d = self.dim();
        if self.count < 2.0 {
            return FrozenNorm {
                mean: vec![0.0; d],
                std: vec![1.0; d],
            };
        }
        FrozenNorm {
            mean: self.mean.iter().map(|&m| m as f32).collect(),
            std: self
                .m2
                .iter()
                .map(|&m2| (m2 / self.count).sqrt().max(MIN_STD) as f32)
                .collect(),
        }
    }
}

/// Fixed normalisation `clip((x − mean) / std, ±CLIP)`.
#[derive(Debug, Clone, PartialEq)]
pub struct FrozenNorm {
    /// Per-dimension mean.
    pub mean: Vec<f32>,
    /// Per-dimension standard deviation (floored).
    pub std: Vec<f32>,
}

impl FrozenNorm {
    /// Normalise `x` (any number of rows) into `out`.
    pub fn apply(&self, x: &[f32], out: &mut [f32]) {
        self.apply_clipped(x, out, CLIP);
    }

    /// [`apply`](Self::apply) with the bound `±clip` instead of `±CLIP` (`f32::INFINITY`:
    /// no bound).
    pub fn apply_clipped(&self, x: &[f32], out: &mut [f32], clip: f32) {
        let d = self.mean.len();
        assert_eq!(x.len(), out.len(), "FrozenNorm::apply: sizes");
        for (xr, or) in x.chunks_exact(d).zip(out.chunks_exact_mut(d)) {
            for k in 0..d {
                or[k] = ((xr[k] - self.mean[k]) / self.std[k]).clamp(-clip, clip);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn running_norm_matches_two_pass_statistics() {
        let data: Vec<f32> = (0..300).map(|i| ((i * 37) % 101) as f32 * 0.1).collect();
        let mut rn = RunningNorm::new(3);
        rn.update(&data[..90]);
        rn.update(&data[90..93]);
        rn.update(&data[93..]);
        for k in 0..3 {
            let col: Vec<f64> = data.iter().skip(k).step_by(3).map(|&v| v as f64).collect();
            let n = col.len() as f64;
            let mean = col.iter().sum::<f64>() / n;
            let var = col.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
            assert!((rn.mean[k] - mean).abs() < 1e-9);
            assert!((rn.m2[k] / rn.count - var).abs() < 1e-9);
        }
        let f = rn.frozen();
        let mut out = vec![0.0; 3];
        f.apply(&[f.mean[0], f.mean[1] + f.std[1], 1e9], &mut out);
        assert!(out[0].abs() < 1e-6 && (out[1] - 1.0).abs() < 1e-5 && out[2] == CLIP);
    }
}
