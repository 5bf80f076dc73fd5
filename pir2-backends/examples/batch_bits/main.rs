//! Batched inference of the U-Net against batch-1 calls, on the Leap-cube spec (H = 16,
//! A = 16, fast 2×32, slow 9, d_vis_max = 5): whether each row of one batch-`B` call has the
//! bits of the same row run alone, and the time per row of both, side by side in one run.
//!
//! `cargo run --release -p pir2-backends --example batch_bits [-- B ...]` (default 8 32)

use std::time::Instant;

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, ModelConfig, SlowSpec, Spec, Stats, UNetConfig};
use pir2_runtime::model::{ModelInput, SlowInput, VelocityModel};
use pir2_schedule::Rng;

const H: usize = 16;
const A: usize = 16;
const FAST: usize = 2 * 32;
const SLOW: usize = 9;

fn spec() -> Spec {
    Spec {
        horizon: H,
        action_dim: A,
        n_obs: 2,
        fast_dim: 32,
        slow: SlowSpec::Vector { dim: SLOW },
        d_vis_max: 5,
    }
}

/// Random inputs of `b` rows (seeded).
struct Rows {
    x: Vec<f32>,
    tau: Vec<f32>,
    fast: Vec<f32>,
    slow: Vec<f32>,
    dvis: Vec<u32>,
}

impl Rows {
    fn new(b: usize, seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let mut r = Self {
            x: vec![0.0; b * H * A],
            tau: (0..b * H)
                .map(|i| 1.0 - (i % H) as f32 / H as f32)
                .collect(),
            fast: vec![0.0; b * FAST],
            slow: vec![0.0; b * SLOW],
            dvis: (0..b).map(|i| (i % 6) as u32).collect(),
        };
        rng.fill_normal(&mut r.x);
        rng.fill_normal(&mut r.fast);
        rng.fill_normal(&mut r.slow);
        r
    }

    /// Rows `i..i + n` as a model input.
    fn input(&self, i: usize, n: usize) -> ModelInput<'_> {
        ModelInput {
            batch: n,
            horizon: H,
            action_dim: A,
            x: &self.x[i * H * A..(i + n) * H * A],
            tau: &self.tau[i * H..(i + n) * H],
            obs_fast: &self.fast[i * FAST..(i + n) * FAST],
            n_obs: 2,
            fast_dim: 32,
            slow: SlowInput::Vector {
                data: &self.slow[i * SLOW..(i + n) * SLOW],
                dim: SLOW,
            },
            d_vis: &self.dvis[i..i + n],
        }
    }
}

fn main() -> anyhow::Result<()> {
    let sizes: Vec<usize> = std::env::args()
        .skip(1)
        .map(|a| a.parse())
        .collect::<Result<_, _>>()?;
    let sizes = if sizes.is_empty() { vec![8, 32] } else { sizes };
    println!(
        "U-Net [64,128,256] k5, fused host kernels; RAYON_NUM_THREADS={}",
        std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "unset".into())
    );
    let spec = spec();
    let config = Config {
        spec,
        model: ModelConfig::UNet(UNetConfig::default()),
    };
    let mut m = CandleModel::new(config, Stats::identity(&spec), 0)?;
    for b in sizes {
        let rows = Rows::new(b, 7 + b as u64);
        let mut one = vec![0.0f32; b * H * A];
        let mut all = vec![0.0f32; b * H * A];
        for i in 0..b {
            m.velocity(&rows.input(i, 1), &mut one[i * H * A..(i + 1) * H * A])?;
        }
        m.velocity(&rows.input(0, b), &mut all)?;
        let same_bits = one
            .iter()
            .zip(&all)
            .filter(|(a, b)| a.to_bits() == b.to_bits())
            .count();
        let max_diff = one
            .iter()
            .zip(&all)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        // Time: `reps` rounds of b batch-1 calls, then of one batch-b call, interleaved.
        let reps = (256 / b).max(3);
        let (mut t_one, mut t_all) = (0.0, 0.0);
        for _ in 0..reps {
            let s = Instant::now();
            for i in 0..b {
                m.velocity(&rows.input(i, 1), &mut one[i * H * A..(i + 1) * H * A])?;
            }
            t_one += s.elapsed().as_secs_f64();
            let s = Instant::now();
            m.velocity(&rows.input(0, b), &mut all)?;
            t_all += s.elapsed().as_secs_f64();
        }
        let per_row = |t: f64| t / (reps * b) as f64 * 1e6;
        println!(
            "B = {b:>3}: {same_bits}/{} outputs bit-equal to batch 1 (max |diff| {max_diff:.2e}); \
             per row: batch 1 {:.0} us, batched {:.0} us, ratio {:.2}",
            one.len(),
            per_row(t_one),
            per_row(t_all),
            t_one / t_all
        );
    }
    Ok(())
}
