//! One-NFE latency at batch 1, single thread, for the MLP and the U-Net of the Leap-cube stack
//! (`H = 16`, `A = 16`, `n_obs = 2`, 32-d fast + 9-d slow observation), on every enabled
//! backend with the same weights (a candle model, exported to ONNX and traced to TorchScript),
//! printed side by side with ratios to ONNX Runtime; then U-Net training steps/s at batch 256
//! on two threads, candle's autograd graph next to the hand-written kernels.
//!
//! `cargo bench -p pir2-backends --features ort,tch --bench latency`
//! (`PIR2_BENCH_ITERS`, default 300, sets the timed calls per cell; `PIR2_BENCH_TRAIN_STEPS`,
//! default 5, the timed training steps per cell, 0 skips training; `PIR2_BENCH_TRAIN_THREADS`,
//! default 2). A plain timing loop (warm-up, then median and p90 of per-call wall time) so that
//! all backends share one table. Single thread: `RAYON_NUM_THREADS=1` for candle (set here
//! before candle starts its pool), intra/inter-op 1 for ONNX Runtime and libtorch (their
//! defaults in this crate). `candle-graph` is candle's op-by-op graph (the path before the
//! hand-written kernels), `candle` the default (hand-written kernels for the U-Net).

mod common;

use common::{time, train_step_s};
use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, MlpConfig, ModelConfig, SlowSpec, Spec, Stats};

use pir2_runtime::{ModelInput, SlowInput, VelocityModel};

fn leap_spec() -> Spec {
    Spec {
        horizon: 16,
        action_dim: 16,
        n_obs: 2,
        fast_dim: 32,
        slow: SlowSpec::Vector { dim: 9 },
        d_vis_max: 5,
    }
}

fn configs() -> Vec<(&'static str, Config)> {
    // The shipped Leap-cube U-Net config (widths [32, 64, 128]), the paper-sized widths, and
    // the default MLP on the Leap-cube spec.
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/leap_cube_unet.toml");
    let leap = Config::from_file(&path).expect("configs/leap_cube_unet.toml");
    let mut paper = leap.clone();
    if let ModelConfig::UNet(u) = &mut paper.model {
        u.widths = vec![64, 128, 256];
    }
    vec![
        (
            "mlp",
            Config {
                spec: leap_spec(),
                model: ModelConfig::Mlp(MlpConfig::default()),
            },
        ),
        ("unet", leap),
        ("unet-L", paper),
    ]
}

#[allow(unused_variables, unused_mut)]
fn native(kind: &str, model: &CandleModel) -> Vec<Box<dyn VelocityModel>> {
    let mut v: Vec<Box<dyn VelocityModel>> = Vec::new();
    let spec = pir2_backends::candle::export::spec_from_config(model.config(), model.stats())
        .expect("exportable");
    #[cfg(feature = "ort")]
    {
        let bytes = pir2_backends::export::export(&spec, model)
            .expect("export")
            .encode();
        v.push(Box::new(
            pir2_backends::ort::OrtModel::from_bytes(&bytes, &Default::default())
                .expect("onnxruntime"),
        ));
    }
    #[cfg(feature = "tch")]
    {
        let path =
            std::env::temp_dir().join(format!("pir2-bench-{kind}-{}.pt", std::process::id()));
        pir2_backends::tch::export_torchscript(&spec, model, &path).expect("trace");
        v.push(Box::new(
            pir2_backends::tch::TchModel::load(&path).expect("libtorch"),
        ));
        let _ = std::fs::remove_file(&path);
    }
    v
}

fn main() {
    // Before candle's first use: its CPU kernels use a rayon pool.
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
    let iters: usize = std::env::var("PIR2_BENCH_ITERS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(300);
    println!("one NFE, batch 1, single thread, {iters} timed calls per cell (µs; ratio = median / onnxruntime median)");
    println!(
        "{:<7} {:<12} {:>10} {:>10} {:>8}",
        "model", "backend", "median", "p90", "ratio"
    );
    for (kind, cfg) in configs() {
        let spec = cfg.spec;
        let candle = CandleModel::new(cfg, Stats::identity(&spec), 0).expect("candle model");
        let n_params = candle.num_params();
        let mut rng = pir2_schedule::Rng::new(1);
        let mut normal = |n: usize| {
            let mut v = vec![0f32; n];
            rng.fill_normal(&mut v);
            v
        };
        let x = normal(spec.horizon * spec.action_dim);
        let obs = normal(spec.n_obs * spec.fast_dim);
        let slow = normal(9);
        let tau: Vec<f32> = (0..spec.horizon)
            .map(|p| 1.0 - p as f32 / spec.horizon as f32)
            .collect();
        let input = ModelInput {
            batch: 1,
            horizon: spec.horizon,
            action_dim: spec.action_dim,
            x: &x,
            tau: &tau,
            obs_fast: &obs,
            n_obs: spec.n_obs,
            fast_dim: spec.fast_dim,
            slow: SlowInput::Vector {
                data: &slow,
                dim: 9,
            },
            d_vis: &[0],
        };
        let mut models = native(kind, &candle);
        let mut graph = CandleModel::new(candle.config().clone(), candle.stats().clone(), 0)
            .expect("candle model");
        graph.set_fused(false);
        let mut labels: Vec<&str> = models.iter().map(|m| m.backend()).collect();
        models.insert(0, Box::new(candle));
        labels.insert(0, "candle");
        if kind != "mlp" {
            models.insert(0, Box::new(graph));
            labels.insert(0, "candle-graph");
        }
        let mut rows = Vec::new();
        for (m, label) in models.iter_mut().zip(labels) {
            let t = time(m.as_mut(), &input, iters);
            rows.push((label, t));
        }
        let base = rows
            .iter()
            .find(|(b, _)| *b == "onnxruntime")
            .map(|(_, t)| t.median_us);
        for (b, t) in &rows {
            let ratio = base.map_or("-".to_string(), |o| format!("{:.2}x", t.median_us / o));
            println!(
                "{:<7} {:<12} {:>10.1} {:>10.1} {:>8}",
                kind, b, t.median_us, t.p90_us, ratio
            );
        }
        println!("{kind:<7} ({n_params} parameters)");
    }
    let steps: usize = std::env::var("PIR2_BENCH_TRAIN_STEPS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(5);
    if steps > 0 {
        train_table(steps);
    }
}

fn train_table(steps: usize) {
    let threads: usize = std::env::var("PIR2_BENCH_TRAIN_THREADS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(2);
    // candle's kernels read RAYON_NUM_THREADS per call; both paths run inside one pool.
    std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    println!();
    println!("U-Net training step, batch 256, {threads} threads, {steps} timed steps per cell (s/step; ratio = graph / fused)");
    println!(
        "{:<7} {:>14} {:>14} {:>8} {:>12}",
        "model", "candle-graph", "candle", "ratio", "fused steps/s"
    );
    for (kind, cfg) in configs().into_iter().filter(|(k, _)| *k != "mlp") {
        let (graph, fused) = pool.install(|| {
            (
                train_step_s(&cfg, false, steps),
                train_step_s(&cfg, true, steps),
            )
        });
        println!(
            "{:<7} {:>14.3} {:>14.3} {:>7.2}x {:>12.2}",
            kind,
            graph,
            fused,
            graph / fused,
            1.0 / fused
        );
    }
}
