//! Shared fixtures: a synthetic dataset whose actions are a known function of the observation.
#![allow(dead_code)]

use pir2_backends::config::{Config, MlpConfig, ModelConfig, SlowSpec, Spec};
use pir2_backends::train::Episode;
use pir2_schedule::Rng;

pub const F: usize = 2;
pub const A: usize = 2;

/// The function the policy must learn: actions depend on the fast obs (c0) and the slow
/// feature (c1); constant over an episode so a chunk is predictable from one observation.
pub fn target(c0: f32, c1: f32) -> [f32; A] {
    [(2.0 * c0).sin(), 0.5 * c0 + c1]
}

pub fn spec(h: usize) -> Spec {
    Spec {
        horizon: h,
        action_dim: A,
        n_obs: 2,
        fast_dim: F,
        slow: SlowSpec::Vector { dim: 1 },
        d_vis_max: 2,
    }
}

pub fn mlp_config(h: usize) -> Config {
    Config {
        spec: spec(h),
        model: ModelConfig::Mlp(MlpConfig {
            width: 64,
            depth: 2,
            tau_freqs: 2,
            dvis_dim: 4,
        }),
    }
}

/// `n` episodes of `len` frames: fast obs `[c0, c0 + 0.1·sin t]`, slow `[c1]`, action `target(c0, c1)`.
pub fn dataset(n: usize, len: usize, seed: u64) -> Vec<Episode> {
    let mut rng = Rng::new(seed);
    (0..n)
        .map(|_| {
            let (c0, c1) = (rng.uniform_range(-1.0, 1.0), rng.uniform_range(-1.0, 1.0));
            let mut ep = Episode::new(F, 1, A);
            for t in 0..len {
                ep.push(&[c0, c0 + 0.1 * (t as f32).sin()], &[c1], &target(c0, c1));
            }
            ep
        })
        .collect()
}

/// Fast history `[o_{t−1}, o_t]` for an episode with parameters `(c0, c1)` at `t = 5`.
pub fn obs(c0: f32) -> Vec<f32> {
    vec![c0, c0 + 0.1 * 4f32.sin(), c0, c0 + 0.1 * 5f32.sin()]
}
