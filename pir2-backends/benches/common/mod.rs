//! Timing helpers shared by the benchmarks (a plain timing loop, so every backend shares one
//! table): one NFE's per-call wall time, and the seconds of a training step.

use std::time::Instant;

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, Stats};
use pir2_backends::train::{Episode, TrainConfig, Trainer};
use pir2_runtime::{ModelInput, VelocityModel};

/// Median and 90th percentile of per-call wall time, µs.
pub struct Timing {
    pub median_us: f64,
    pub p90_us: f64,
}

/// Time `iters` calls of `model` on `input` after a warm-up.
pub fn time(model: &mut dyn VelocityModel, input: &ModelInput<'_>, iters: usize) -> Timing {
    let mut out = vec![0f32; input.batch * input.horizon * input.action_dim];
    for _ in 0..iters.div_ceil(5).max(5) {
        model.velocity(input, &mut out).expect("warm-up call");
    }
    let mut us: Vec<f64> = (0..iters)
        .map(|_| {
            let t = Instant::now();
            model.velocity(input, &mut out).expect("timed call");
            t.elapsed().as_secs_f64() * 1e6
        })
        .collect();
    us.sort_by(f64::total_cmp);
    Timing {
        median_us: us[us.len() / 2],
        p90_us: us[(us.len() * 9) / 10],
    }
}

/// Seconds per training step (batch 256, `fused`: the hand-written kernels) after one warm-up
/// step, on 20 random episodes of 100 frames.
pub fn train_step_s(cfg: &Config, fused: bool, steps: usize) -> f64 {
    let spec = cfg.spec;
    let mut rng = pir2_schedule::Rng::new(2);
    let data: Vec<Episode> = (0..20)
        .map(|_| {
            let mut ep = Episode::new(spec.fast_dim, spec.slow.len(), spec.action_dim);
            let mut f = vec![0.0; spec.fast_dim];
            let mut s = vec![0.0; spec.slow.len()];
            let mut a = vec![0.0; spec.action_dim];
            for _ in 0..100 {
                rng.fill_normal(&mut f);
                rng.fill_normal(&mut s);
                rng.fill_normal(&mut a);
                ep.push(&f, &s, &a);
            }
            ep
        })
        .collect();
    let mut m = CandleModel::new(cfg.clone(), Stats::identity(&spec), 0).expect("candle model");
    let tc = TrainConfig {
        steps: steps + 1,
        batch_size: 256,
        warmup: 1,
        ..TrainConfig::default()
    };
    let mut first = None;
    let mut last = Instant::now();
    Trainer::new(tc)
        .fused(fused)
        .on_progress(|p| {
            if p.step == 1 {
                first = Some(Instant::now());
            }
            last = Instant::now();
        })
        .run(&mut m, data.as_slice())
        .expect("training");
    last.duration_since(first.expect("ran")).as_secs_f64() / steps as f64
}
