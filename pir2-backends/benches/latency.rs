//! One-NFE latency at batch 1, single thread, for the MLP and the U-Net of the Leap-cube stack
//! (`H = 16`, `A = 16`, `n_obs = 2`, 32-d fast + 9-d slow observation), on every enabled
//! backend with the same weights, printed side by side as ratios to ONNX Runtime.
//!
//! `cargo bench -p pir2-backends --features ort,tch --bench latency`
//! (`PIR2_BENCH_ITERS`, default 300, sets the timed iterations per cell). A plain timing loop
//! (warm-up, then median and p90 of per-call wall time), so that all backends share one table.

use std::time::Instant;

use pir2_backends::onnx::models::{Film, MlpSpec, ObsNorm, UnetSpec};
use pir2_backends::onnx::ops::NamedWeights;
use pir2_backends::onnx::{ContractDims, ModelSpec, SlowSpec};
use pir2_runtime::{ModelInput, SlowInput, VelocityModel};

fn leap_dims() -> ContractDims {
    ContractDims {
        horizon: 16,
        action_dim: 16,
        n_obs: 2,
        fast_dim: 32,
        slow: SlowSpec::Vector { dim: 9 },
        has_d_vis: true,
    }
}

fn specs() -> Vec<ModelSpec> {
    vec![
        ModelSpec::Mlp(MlpSpec {
            dims: leap_dims(),
            width: 256,
            depth: 3,
            tau_freqs: 2,
            dvis_dim: 8,
            d_vis_max: 5,
            norm: ObsNorm::identity(&leap_dims()),
        }),
        ModelSpec::Unet(UnetSpec {
            dims: leap_dims(),
            widths: vec![64, 128, 256],
            kernel: 5,
            groups: 8,
            tau_dim: 64,
            dvis_dim: 16,
            d_vis_max: 5,
            film: Film::PerPosition,
            norm: ObsNorm::identity(&leap_dims()),
        }),
    ]
}

struct Timing {
    median_us: f64,
    p90_us: f64,
}

fn time(model: &mut dyn VelocityModel, input: &ModelInput<'_>, iters: usize) -> Timing {
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

#[allow(unused_variables, unused_mut)]
fn backends(spec: &ModelSpec, weights: &NamedWeights) -> Vec<Box<dyn VelocityModel>> {
    let mut v: Vec<Box<dyn VelocityModel>> = Vec::new();
    #[cfg(feature = "ort")]
    {
        let bytes = pir2_backends::onnx::export(spec, weights)
            .expect("export")
            .encode();
        v.push(Box::new(
            pir2_backends::ort::OrtModel::from_bytes(&bytes, &Default::default())
                .expect("onnxruntime"),
        ));
    }
    #[cfg(feature = "tch")]
    {
        let path = std::env::temp_dir().join(format!(
            "pir2-bench-{}-{}.pt",
            spec.kind(),
            std::process::id()
        ));
        pir2_backends::tch::export_torchscript(spec, weights, &path).expect("trace");
        v.push(Box::new(
            pir2_backends::tch::TchModel::load(&path).expect("libtorch"),
        ));
    }
    v
}

fn main() {
    let iters: usize = std::env::var("PIR2_BENCH_ITERS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(300);
    println!("one NFE, batch 1, single thread, {iters} timed calls per cell (median / p90 in µs; ratio = median / onnxruntime median)");
    println!(
        "{:<6} {:<12} {:>10} {:>10} {:>8}",
        "model", "backend", "median", "p90", "ratio"
    );
    for spec in specs() {
        let weights = NamedWeights::random(&spec.weight_shapes(), 0);
        let n_params: usize = weights.iter().map(|(_, _, d)| d.len()).sum();
        let d = *spec.dims();
        let mut rng = pir2_schedule::Rng::new(1);
        let mut normal = |n: usize| {
            let mut v = vec![0f32; n];
            rng.fill_normal(&mut v);
            v
        };
        let x = normal(d.horizon * d.action_dim);
        let obs = normal(d.n_obs * d.fast_dim);
        let slow = normal(9);
        let tau: Vec<f32> = (0..d.horizon)
            .map(|p| 1.0 - p as f32 / d.horizon as f32)
            .collect();
        let input = ModelInput {
            batch: 1,
            horizon: d.horizon,
            action_dim: d.action_dim,
            x: &x,
            tau: &tau,
            obs_fast: &obs,
            n_obs: d.n_obs,
            fast_dim: d.fast_dim,
            slow: SlowInput::Vector {
                data: &slow,
                dim: 9,
            },
            d_vis: &[0],
        };
        let mut rows = Vec::new();
        for mut m in backends(&spec, &weights) {
            let t = time(m.as_mut(), &input, iters);
            rows.push((m.backend(), t));
        }
        let base = rows
            .iter()
            .find(|(b, _)| *b == "onnxruntime")
            .map(|(_, t)| t.median_us);
        for (b, t) in &rows {
            let ratio = base.map_or("-".to_string(), |o| format!("{:.2}x", t.median_us / o));
            println!(
                "{:<6} {:<12} {:>10.1} {:>10.1} {:>8}",
                spec.kind(),
                b,
                t.median_us,
                t.p90_us,
                ratio
            );
        }
        println!("{:<6} ({} parameters)", spec.kind(), n_params);
    }
}
