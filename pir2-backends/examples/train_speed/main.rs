//! U-Net training step time (batch 256) and batch-1 NFE latency, candle's autograd graph
//! next to the hand-written kernels, one configuration per run (a focused target for `perf`).
//!
//! `cargo run --release -p pir2-backends --example train_speed -- --widths 64,128,256 --path both --steps 5 --threads 2`

use std::time::Instant;

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, ModelConfig, SlowSpec, Spec, Stats, UNetConfig};
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

fn data() -> Vec<Episode> {
    let mut rng = Rng::new(2);
    (0..20)
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
        .collect()
}

fn train(cfg: &Config, fused: bool, steps: usize) -> anyhow::Result<(f64, f32)> {
    let mut m = CandleModel::new(cfg.clone(), Stats::identity(&cfg.spec), 0)?;
    let tc = TrainConfig {
        steps: steps + 1,
        batch_size: 256,
        warmup: 1,
        ..TrainConfig::default()
    };
    let mut first = None;
    let mut last = Instant::now();
    let data = data();
    let report = Trainer::new(tc)
        .fused(fused)
        .on_progress(|p| {
            if p.step == 1 {
                first = Some(Instant::now());
            }
            last = Instant::now();
        })
        .run(&mut m, data.as_slice())?;
    let dt = last.duration_since(first.expect("ran")).as_secs_f64() / steps as f64;
    Ok((dt, report.losses.last().map(|l| l.1).unwrap_or(f32::NAN)))
}

fn nfe(cfg: &Config, fused: bool, iters: usize) -> anyhow::Result<f64> {
    let spec = cfg.spec;
    let mut m = CandleModel::new(cfg.clone(), Stats::identity(&spec), 0)?;
    m.set_fused(fused);
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
    let mut t: Vec<f64> = (0..iters)
        .map(|_| {
            let s = Instant::now();
            m.velocity(&input, &mut out).expect("velocity");
            s.elapsed().as_secs_f64() * 1e6
        })
        .collect();
    t.sort_by(f64::total_cmp);
    Ok(t[iters / 2])
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let get = |k: &str, d: &str| -> String {
        args.iter()
            .position(|a| a == k)
            .and_then(|i| args.get(i + 1).cloned())
            .unwrap_or_else(|| d.to_owned())
    };
    let widths: Vec<usize> = get("--widths", "64,128,256")
        .split(',')
        .map(|w| w.parse())
        .collect::<Result<_, _>>()?;
    let path = get("--path", "both");
    let steps: usize = get("--steps", "5").parse()?;
    let threads: usize = get("--threads", "2").parse()?;
    let iters: usize = get("--nfe", "200").parse()?;
    std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let cfg = Config {
        spec: spec(),
        model: ModelConfig::UNet(UNetConfig {
            widths: widths.clone(),
            ..UNetConfig::default()
        }),
    };
    let paths: Vec<bool> = match path.as_str() {
        "graph" => vec![false],
        "fused" => vec![true],
        _ => vec![false, true],
    };
    println!("U-Net {widths:?}, batch 256, {threads} threads");
    for fused in paths {
        let name = if fused { "fused" } else { "graph" };
        if steps > 0 {
            let (dt, loss) = pool.install(|| train(&cfg, fused, steps))?;
            println!(
                "{name:<6} training step {dt:.4} s ({:.2} steps/s, final loss {loss:.4})",
                1.0 / dt
            );
        }
        if iters > 0 {
            std::env::set_var("RAYON_NUM_THREADS", "1");
            let us = one.install(|| nfe(&cfg, fused, iters))?;
            std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
            println!("{name:<6} one NFE batch 1 (single thread): p50 {us:.1} us");
        }
    }
    Ok(())
}
