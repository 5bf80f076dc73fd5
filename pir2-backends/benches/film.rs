//! What the paper's per-position FiLM heads cost, measured side by side in one run: the Leap-cube
//! study's U-Net (`H = 16`, widths 64/128/256, `E = 32`) with the shared head (the baselines),
//! the shared head on per-position τ (the ablation) and one head per position (the paper's):
//! parameters, one NFE at batch 1 on one thread (the deployment call), and a training step at
//! batch 256 (the hand-written kernels, `PIR2_BENCH_TRAIN_THREADS` threads, default 2).
//! Ratios are to the shared head.
//!
//! `cargo bench -p pir2-backends --bench film` (`PIR2_BENCH_ITERS`, default 300 timed calls per
//! cell; `PIR2_BENCH_TRAIN_STEPS`, default 5 timed steps per cell, 0 skips training).

use std::time::Instant;

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, FilmMode, ModelConfig, SlowSpec, Spec, Stats, UNetConfig};
use pir2_backends::train::{Episode, TrainConfig, Trainer};
use pir2_runtime::{ModelInput, SlowInput, VelocityModel};

fn spec() -> Spec {
    Spec {
        horizon: 16,
        action_dim: 16,
        n_obs: 2,
        fast_dim: 32,
        slow: SlowSpec::Vector { dim: 18 },
        d_vis_max: 0,
    }
}

/// The Leap-cube study's U-Net (`pir2_cli::study::leap_cube`: widths from the study config,
/// `tau_dim` 32, `dvis_dim` 8, two slow frames of 9).
fn config(film: FilmMode) -> Config {
    Config {
        spec: spec(),
        model: ModelConfig::UNet(UNetConfig {
            widths: vec![64, 128, 256],
            groups: 8,
            tau_dim: 32,
            dvis_dim: 8,
            film,
            ..UNetConfig::default()
        }),
    }
}

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// Median µs of one NFE at batch 1 (staircase τ).
fn nfe_us(m: &mut CandleModel, iters: usize) -> f64 {
    let s = spec();
    let mut rng = pir2_schedule::Rng::new(1);
    let mut normal = |n: usize| {
        let mut v = vec![0f32; n];
        rng.fill_normal(&mut v);
        v
    };
    let x = normal(s.horizon * s.action_dim);
    let obs = normal(s.n_obs * s.fast_dim);
    let slow = normal(18);
    let tau: Vec<f32> = (0..s.horizon)
        .map(|p| 1.0 - p as f32 / s.horizon as f32)
        .collect();
    let input = ModelInput {
        batch: 1,
        horizon: s.horizon,
        action_dim: s.action_dim,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: s.n_obs,
        fast_dim: s.fast_dim,
        slow: SlowInput::Vector {
            data: &slow,
            dim: 18,
        },
        d_vis: &[0],
    };
    let mut out = vec![0f32; s.horizon * s.action_dim];
    for _ in 0..iters.div_ceil(5).max(5) {
        m.velocity(&input, &mut out).expect("warm-up call");
    }
    let mut us: Vec<f64> = (0..iters)
        .map(|_| {
            let t = Instant::now();
            m.velocity(&input, &mut out).expect("timed call");
            t.elapsed().as_secs_f64() * 1e6
        })
        .collect();
    us.sort_by(f64::total_cmp);
    us[us.len() / 2]
}

/// Seconds per training step (batch 256) after one warm-up step.
fn train_step_s(cfg: &Config, steps: usize) -> f64 {
    let s = cfg.spec;
    let mut rng = pir2_schedule::Rng::new(2);
    let data: Vec<Episode> = (0..20)
        .map(|_| {
            let mut ep = Episode::new(s.fast_dim, s.slow.len(), s.action_dim);
            let mut f = vec![0.0; s.fast_dim];
            let mut sl = vec![0.0; s.slow.len()];
            let mut a = vec![0.0; s.action_dim];
            for _ in 0..100 {
                rng.fill_normal(&mut f);
                rng.fill_normal(&mut sl);
                rng.fill_normal(&mut a);
                ep.push(&f, &sl, &a);
            }
            ep
        })
        .collect();
    let mut m = CandleModel::new(cfg.clone(), Stats::identity(&s), 0).expect("candle model");
    let tc = TrainConfig {
        steps: steps + 1,
        batch_size: 256,
        warmup: 1,
        ..TrainConfig::default()
    };
    let mut first = None;
    let mut last = Instant::now();
    Trainer::new(tc)
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

fn main() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
    let iters = env_usize("PIR2_BENCH_ITERS", 300);
    let steps = env_usize("PIR2_BENCH_TRAIN_STEPS", 5);
    let threads = env_usize("PIR2_BENCH_TRAIN_THREADS", 2);
    let films = [
        ("shared", FilmMode::Shared),
        ("per_position_tau", FilmMode::PerPositionTau),
        ("per_position_heads", FilmMode::PerPositionHeads),
    ];
    let mut rows = Vec::new();
    for (label, film) in films {
        let cfg = config(film);
        let mut m = CandleModel::new(cfg.clone(), Stats::identity(&cfg.spec), 0).expect("model");
        let params = m.num_params();
        let film_params: usize = m
            .vars()
            .iter()
            .filter(|(n, _)| n.contains(".film"))
            .map(|(_, v)| v.elem_count())
            .sum();
        let us = nfe_us(&mut m, iters);
        rows.push((label, params, film_params, us, cfg));
    }
    let train: Vec<f64> = if steps > 0 {
        std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        rows.iter()
            .map(|r| pool.install(|| train_step_s(&r.4, steps)))
            .collect()
    } else {
        vec![f64::NAN; rows.len()]
    };
    println!(
        "Leap-cube study U-Net (H = 16, widths 64/128/256): {iters} batch-1 NFEs on 1 thread; \
         {steps} training steps at batch 256 on {threads} threads; ratio = / shared"
    );
    println!(
        "{:<20} {:>11} {:>11} {:>10} {:>7} {:>10} {:>7}",
        "FiLM", "parameters", "FiLM params", "NFE µs", "ratio", "s/step", "ratio"
    );
    let (base_us, base_step) = (rows[0].3, train[0]);
    for (r, t) in rows.iter().zip(&train) {
        println!(
            "{:<20} {:>11} {:>11} {:>10.1} {:>6.2}x {:>10.3} {:>6.2}x",
            r.0,
            r.1,
            r.2,
            r.3,
            r.3 / base_us,
            t,
            t / base_step
        );
    }
}
