//! Analytic gradients of every architecture agree with finite differences (guards the
//! hand-built layers and candle's backward of conv/attention ops).

mod common;

use candle_core::Tensor;
use common::*;
use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, DitConfig, FilmMode, ModelConfig, Stats, UNetConfig};
use pir2_runtime::model::{ModelInput, SlowInput};

fn check(cfg: Config) {
    let spec = cfg.spec;
    let mut m = CandleModel::new(cfg, Stats::identity(&spec), 1).unwrap();
    // Make zero-initialised parameters non-zero so every path carries gradient.
    for (_, v) in m.vars() {
        let t = v.as_tensor();
        let n = t.elem_count();
        let bump: Vec<f32> = (0..n).map(|i| 0.05 * ((i as f32) * 1.7).sin()).collect();
        v.set(&(t + Tensor::from_vec(bump, t.shape(), t.device()).unwrap()).unwrap())
            .unwrap();
    }
    m.weights_changed();
    let (h, b) = (spec.horizon, 2);
    let x: Vec<f32> = (0..b * h * A).map(|i| (i as f32 * 0.91).sin()).collect();
    let tau: Vec<f32> = (0..b * h)
        .map(|i| {
            if i % h == 0 {
                -1.0
            } else {
                ((i * 7) % 10) as f32 / 10.0
            }
        })
        .collect();
    let obs: Vec<f32> = (0..b * 2 * F).map(|i| (i as f32 * 0.3).cos()).collect();
    let slow = [0.4f32, -0.3];
    let w: Vec<f32> = (0..b * h * A).map(|i| (i as f32 * 1.3).cos()).collect();
    let wt = Tensor::from_vec(w, (b, h, A), &candle_core::Device::Cpu).unwrap();
    let loss = |m: &mut CandleModel| -> Tensor {
        let input = ModelInput {
            batch: b,
            horizon: h,
            action_dim: A,
            x: &x,
            tau: &tau,
            obs_fast: &obs,
            n_obs: 2,
            fast_dim: F,
            slow: SlowInput::Vector {
                data: &slow,
                dim: 1,
            },
            d_vis: &[0, 2],
        };
        (m.forward_input(&input).unwrap() * &wt)
            .unwrap()
            .sum_all()
            .unwrap()
    };
    let grads = loss(&mut m).backward().unwrap();
    let mut checked = 0;
    let mut bad = Vec::new();
    for (name, var) in m.vars().to_vec() {
        let g = grads
            .get(var.as_tensor())
            .unwrap_or_else(|| panic!("no gradient for {name}"));
        let g = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let base = var
            .as_tensor()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        // Largest-gradient element of each tensor.
        let (k, &gk) = g
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
            .unwrap();
        if gk.abs() < 1e-3 {
            continue;
        }
        let eps = 1e-2f32;
        let mut eval = |delta: f32| {
            let mut p = base.clone();
            p[k] += delta;
            var.set(&Tensor::from_vec(p, var.shape(), var.device()).unwrap())
                .unwrap();
            loss(&mut m).to_scalar::<f32>().unwrap()
        };
        // Central differences at eps and eps/2, Richardson-extrapolated (error O(eps⁴)
        // instead of O(eps²): GroupNorm and Mish curve enough at eps = 1e-2 to miss by 5 %).
        let c1 = (eval(eps) - eval(-eps)) / (2.0 * eps);
        let c2 = (eval(eps / 2.0) - eval(-eps / 2.0)) / eps;
        let num = (4.0 * c2 - c1) / 3.0;
        var.set(&Tensor::from_vec(base.clone(), var.shape(), var.device()).unwrap())
            .unwrap();
        if (num - gk).abs() > 0.05 * gk.abs() + 2e-3 {
            bad.push(format!("{name}[{k}]: analytic {gk}, numeric {num}"));
        }
        checked += 1;
    }
    assert!(bad.is_empty(), "gradient mismatches:\n{}", bad.join("\n"));
    assert!(
        checked * 2 >= m.vars().len(),
        "only {checked} of {} tensors checked",
        m.vars().len()
    );
}

#[test]
fn unet_gradients_match_finite_differences() {
    check(Config {
        spec: spec(8),
        model: ModelConfig::UNet(UNetConfig {
            widths: vec![8, 16],
            kernel: 3,
            groups: 4,
            tau_dim: 8,
            dvis_dim: 2,
            film: FilmMode::PerPositionHeads,
        }),
    });
}

#[test]
fn dit_gradients_match_finite_differences() {
    check(Config {
        spec: spec(4),
        model: ModelConfig::Dit(DitConfig {
            width: 16,
            depth: 2,
            heads: 2,
            mlp_ratio: 2,
            tau_dim: 8,
            ada: FilmMode::PerPositionHeads,
        }),
    });
}

#[test]
fn mlp_gradients_match_finite_differences() {
    check(mlp_config(4));
}
