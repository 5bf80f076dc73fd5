//! One-NFE latency at batch 1 (MLP, U-Net, DiT) and U-Net training steps/s at batch 256, on the
//! Leap-cube spec (H = 16, A = 16, fast 2×32, slow 9, d_vis_max = 5).
//!
//! Run single-threaded for the latency figures:
//! `RAYON_NUM_THREADS=1 cargo run --release -p pir2-backends --example nfe`

use std::time::Instant;

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{
    Config, DitConfig, MlpConfig, ModelConfig, SlowSpec, Spec, Stats, UNetConfig,
};
use pir2_backends::train::{Episode, TrainConfig, Trainer};
use pir2_runtime::model::{ModelInput, SlowInput, VelocityModel};
use pir2_schedule::Rng;

fn spec() -> Spec {
    Spec {
        horizon: 16,
        action_dim: 16,
        n_obs: 2,
        fast_dim: 32,
        slow: SlowSpec::Vector { dim: 9 },
        d_vis_max: 5,
    }
}

fn latency(name: &str, model: ModelConfig, iters: usize) -> anyhow::Result<()> {
    let spec = spec();
    let mut m = CandleModel::new(Config { spec, model }, Stats::identity(&spec), 0)?;
    let mut rng = Rng::new(1);
    let mut x = vec![0.0; 16 * 16];
    rng.fill_normal(&mut x);
    let tau: Vec<f32> = (0..16).map(|p| 1.0 - p as f32 / 16.0).collect();
    let mut obs = vec![0.0; 64];
    rng.fill_normal(&mut obs);
    let slow = [0.1f32; 9];
    let input = ModelInput {
        batch: 1,
        horizon: 16,
        action_dim: 16,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: 2,
        fast_dim: 32,
        slow: SlowInput::Vector {
            data: &slow,
            dim: 9,
        },
        d_vis: &[2],
    };
    let mut out = vec![0.0; 256];
    for _ in 0..iters / 10 + 3 {
        m.velocity(&input, &mut out)?;
    }
    let mut t = Vec::with_capacity(iters);
    for _ in 0..iters {
        let s = Instant::now();
        m.velocity(&input, &mut out)?;
        t.push(s.elapsed().as_secs_f64() * 1e6);
    }
    t.sort_by(f64::total_cmp);
    println!(
        "{name:<28} params {:>9}  one NFE batch 1: p50 {:>8.1} us  p90 {:>8.1} us  p99 {:>8.1} us",
        m.num_params(),
        t[iters / 2],
        t[iters * 9 / 10],
        t[iters * 99 / 100]
    );
    Ok(())
}

fn train_rate(name: &str, model: ModelConfig, steps: usize) -> anyhow::Result<()> {
    let spec = spec();
    let mut rng = Rng::new(2);
    let data: Vec<Episode> = (0..20)
        .map(|_| {
            let mut ep = Episode::new(32, 9, 16);
            let (mut f, mut s, mut a) = (vec![0.0; 32], vec![0.0; 9], vec![0.0; 16]);
            for _ in 0..100 {
                rng.fill_normal(&mut f);
                rng.fill_normal(&mut s);
                rng.fill_normal(&mut a);
                ep.push(&f, &s, &a);
            }
            ep
        })
        .collect();
    let mut m = CandleModel::new(Config { spec, model }, Stats::identity(&spec), 0)?;
    let tc = TrainConfig {
        steps: steps + 1,
        batch_size: 256,
        warmup: 1,
        ..TrainConfig::default()
    };
    let mut first = None;
    let mut last = Instant::now();
    let report = Trainer::new(tc)
        .on_progress(|p| {
            if p.step == 1 {
                first = Some(Instant::now());
            }
            last = Instant::now();
        })
        .run(&mut m, data.as_slice())?;
    let dt = last.duration_since(first.expect("ran")).as_secs_f64();
    println!(
        "{name:<28} training batch 256: {:.2} steps/s ({steps} steps, final loss {:.3})",
        steps as f64 / dt,
        report.losses.last().map(|l| l.1).unwrap_or(f32::NAN)
    );
    Ok(())
}

fn main() -> anyhow::Result<()> {
    println!(
        "RAYON_NUM_THREADS={}",
        std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "unset".into())
    );
    let mlp = ModelConfig::Mlp(MlpConfig::default());
    let unet = ModelConfig::UNet(UNetConfig::default());
    let dit = ModelConfig::Dit(DitConfig::default());
    latency("MLP 3x256", mlp.clone(), 2000)?;
    latency("U-Net [64,128,256] k5", unet.clone(), 300)?;
    latency("DiT 128x4, 4 heads", dit.clone(), 300)?;
    let steps = std::env::var("PIR2_TRAIN_STEPS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(5);
    train_rate("MLP 3x256", mlp, steps * 4)?;
    train_rate("U-Net [64,128,256] k5", unet, steps)?;
    Ok(())
}
