//! What the paper's per-position FiLM heads cost, measured side by side in one run: the Leap-cube
//! study's U-Net (`H = 16`, widths 64/128/256, `E = 32`) with the shared head (the baselines),
//! the shared head on per-position τ (the ablation) and one head per position (the paper's):
//! parameters, one NFE at batch 1 on one thread (the deployment call), and a training step at
//! batch 256 (the hand-written kernels, `PIR2_BENCH_TRAIN_THREADS` threads, default 2).
//! Ratios are to the shared head.
//!
//! A second table puts the paper's widths (256/512/1024) beside the study's, both with the
//! paper's heads: what a run at the paper's scale would cost on this machine.
//!
//! `cargo bench -p pir2-backends --bench film` (`PIR2_BENCH_ITERS`, default 300 timed calls per
//! cell; `PIR2_BENCH_TRAIN_STEPS`, default 5 timed steps per cell, 0 skips training;
//! `PIR2_BENCH_PAPER_WIDTHS=0` skips the second table).

mod common;

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, FilmMode, ModelConfig, SlowSpec, Spec, Stats, UNetConfig};
use pir2_runtime::{ModelInput, SlowInput};

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

/// The study's U-Net widths (`studies/leap-cube/study.toml`).
const STUDY_WIDTHS: [usize; 3] = [64, 128, 256];
/// The paper's U-Net widths (its simulation appendix).
const PAPER_WIDTHS: [usize; 3] = [256, 512, 1024];

/// The Leap-cube study's U-Net (`pir2_cli::study::leap_cube`: widths from the study config,
/// `tau_dim` 32, `dvis_dim` 8, two slow frames of 9).
fn config(film: FilmMode) -> Config {
    config_with(film, &STUDY_WIDTHS)
}

/// The same U-Net at other widths.
fn config_with(film: FilmMode, widths: &[usize]) -> Config {
    Config {
        spec: spec(),
        model: ModelConfig::UNet(UNetConfig {
            widths: widths.to_vec(),
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

/// Per-call µs of one NFE at batch 1 (staircase τ).
fn nfe_us(m: &mut CandleModel, iters: usize) -> common::Timing {
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
    common::time(m, &input, iters)
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
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    let train_s = |cfg: &Config| {
        if steps > 0 {
            std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
            let s = pool.install(|| common::train_step_s(cfg, true, steps));
            std::env::set_var("RAYON_NUM_THREADS", "1");
            s
        } else {
            f64::NAN
        }
    };
    let train: Vec<f64> = rows.iter().map(|r| train_s(&r.4)).collect();
    println!(
        "Leap-cube study U-Net (H = 16, widths 64/128/256): {iters} batch-1 NFEs on 1 thread; \
         {steps} training steps at batch 256 on {threads} threads; ratio = / shared"
    );
    println!(
        "{:<20} {:>11} {:>11} {:>10} {:>10} {:>7} {:>10} {:>7}",
        "FiLM", "parameters", "FiLM params", "NFE µs", "p90 µs", "ratio", "s/step", "ratio"
    );
    let (base_us, base_step) = (rows[0].3.median_us, train[0]);
    for (r, t) in rows.iter().zip(&train) {
        println!(
            "{:<20} {:>11} {:>11} {:>10.1} {:>10.1} {:>6.2}x {:>10.3} {:>6.2}x",
            r.0,
            r.1,
            r.2,
            r.3.median_us,
            r.3.p90_us,
            r.3.median_us / base_us,
            t,
            t / base_step
        );
    }
    if env_usize("PIR2_BENCH_PAPER_WIDTHS", 1) == 0 {
        return;
    }
    // The paper's widths beside the study's, both with the paper's heads (the heads row above
    // is the study's; measured again here so that the two sit side by side).
    println!(
        "\nper-position heads at the study's widths {STUDY_WIDTHS:?} and the paper's {PAPER_WIDTHS:?}; \
         ratio = / the study's"
    );
    println!(
        "{:<20} {:>11} {:>10} {:>7} {:>10} {:>7}",
        "widths", "parameters", "NFE µs", "ratio", "s/step", "ratio"
    );
    let mut base = None;
    for widths in [&STUDY_WIDTHS, &PAPER_WIDTHS] {
        let cfg = config_with(FilmMode::PerPositionHeads, widths);
        let mut m = CandleModel::new(cfg.clone(), Stats::identity(&cfg.spec), 0).expect("model");
        let us = nfe_us(&mut m, iters).median_us;
        let t = train_s(&cfg);
        let (b_us, b_t) = *base.get_or_insert((us, t));
        println!(
            "{:<20} {:>11} {:>10.1} {:>6.2}x {:>10.3} {:>6.2}x",
            format!("{widths:?}"),
            m.num_params(),
            us,
            us / b_us,
            t,
            t / b_t
        );
    }
}
