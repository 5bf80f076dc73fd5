//! Diagnostic: how far does the simplest behaviour cloning get on the Leap cube?
//!
//! A ridge-regression policy `a_t = W·[fast_t, fast_{t−1}, slow_t, 1]` fitted on the
//! demonstrations, run closed loop at zero latency (one action per step, fresh observation).
//! The same check on the ball-plate task (issue 5) showed a missing observation channel; here
//! it tells whether the observation carries what the expert's actions depend on.
//!
//! It also runs the do-nothing policy (`a = 0`: the motor targets stay where they are) on the
//! same episodes: the floor any learned policy has to beat (a cube that settles blue side up
//! near one of the four yaw goals counts as a success).
//!
//! `cargo run --release -p pir2-cli --features mujoco --example leap_linear_bc -- DATA [EPISODES] [LAMBDA]`

use anyhow::{Context, Result};
use pir2_runtime::Environment;
use pir2_sim::leap::{LeapConfig, LeapCubeEnv, LeapModel};

const F: usize = 32;
const S: usize = 9;
const A: usize = 16;
const D: usize = 2 * F + S + 1;

fn features(cur: &[f32], prev: &[f32], slow: &[f32], out: &mut [f64; D]) {
    for i in 0..F {
        out[i] = cur[i] as f64;
        out[F + i] = prev[i] as f64;
    }
    for i in 0..S {
        out[2 * F + i] = slow[i] as f64;
    }
    out[D - 1] = 1.0;
}

/// The features of frame `t` of a demonstration (the first frame is its own predecessor).
fn frame_features(e: &pir2_sim::dataset::Episode, t: usize, out: &mut [f64; D]) {
    let p = t.saturating_sub(1);
    features(
        &e.fast[t * F..(t + 1) * F],
        &e.fast[p * F..(p + 1) * F],
        &e.slow[t * S..(t + 1) * S],
        out,
    );
}

/// Solve `(XᵀX + λI) W = XᵀY` (Cholesky), `W` is `[D, A]`.
fn ridge(xtx: &[f64], xty: &[f64], lambda: f64) -> Vec<f64> {
    let mut l = xtx.to_vec();
    for i in 0..D - 1 {
        l[i * D + i] += lambda;
    }
    for j in 0..D {
        let mut s = l[j * D + j];
        for k in 0..j {
            s -= l[j * D + k] * l[j * D + k];
        }
        let d = s.max(1e-12).sqrt();
        l[j * D + j] = d;
        for i in j + 1..D {
            let mut s = l[i * D + j];
            for k in 0..j {
                s -= l[i * D + k] * l[j * D + k];
            }
            l[i * D + j] = s / d;
        }
    }
    let mut w = vec![0.0; D * A];
    for a in 0..A {
        let mut y: Vec<f64> = (0..D).map(|i| xty[i * A + a]).collect();
        for i in 0..D {
            for k in 0..i {
                y[i] -= l[i * D + k] * y[k];
            }
            y[i] /= l[i * D + i];
        }
        for i in (0..D).rev() {
            for k in i + 1..D {
                y[i] -= l[k * D + i] * y[k];
            }
            y[i] /= l[i * D + i];
        }
        for i in 0..D {
            w[i * A + a] = y[i];
        }
    }
    w
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let data = args
        .get(1)
        .context("usage: leap_linear_bc DATA [EPISODES] [LAMBDA]")?;
    let episodes: u64 = args.get(2).map_or(Ok(40), |s| s.parse())?;
    let lambda: f64 = args.get(3).map_or(Ok(1e-3), |s| s.parse())?;
    let demos = pir2_cli::study::leap_cube::load_demos(std::path::Path::new(data))?;
    let (mut xtx, mut xty) = (vec![0.0; D * D], vec![0.0; D * A]);
    let (mut n, mut sse, mut sst) = (0usize, 0.0, 0.0);
    let mut x = [0.0; D];
    let mut mean = [0.0f64; A];
    for e in &demos {
        for t in 0..e.len() {
            frame_features(e, t, &mut x);
            let y = &e.action[t * A..(t + 1) * A];
            for i in 0..D {
                for j in 0..D {
                    xtx[i * D + j] += x[i] * x[j];
                }
                for a in 0..A {
                    xty[i * A + a] += x[i] * y[a] as f64;
                }
            }
            for a in 0..A {
                mean[a] += y[a] as f64;
            }
            n += 1;
        }
    }
    for m in &mut mean {
        *m /= n as f64;
    }
    let w = ridge(&xtx, &xty, lambda * n as f64);
    for e in &demos {
        for t in 0..e.len() {
            frame_features(e, t, &mut x);
            for a in 0..A {
                let pred: f64 = (0..D).map(|i| x[i] * w[i * A + a]).sum();
                let y = e.action[t * A + a] as f64;
                sse += (pred - y).powi(2);
                sst += (y - mean[a]).powi(2);
            }
        }
    }
    println!(
        "{} demos, {n} frames; training R² of the linear fit: {:.3}",
        demos.len(),
        1.0 - sse / sst
    );

    let model = LeapModel::load(None)?;
    let mut env = LeapCubeEnv::new(&model, LeapConfig::paper())?;
    for (name, linear) in [("linear BC", true), ("do nothing (a = 0)", false)] {
        let (mut fast, mut prev, mut slow) = (vec![0.0; F], vec![0.0; F], vec![0.0; S]);
        let mut act = vec![0.0f32; A];
        let (mut wins, mut steps) = (0, 0usize);
        for ep in 0..episodes {
            env.reset(1_000_000 + ep);
            env.observe(&mut fast, &mut slow);
            prev.copy_from_slice(&fast);
            loop {
                if linear {
                    features(&fast, &prev, &slow, &mut x);
                    for a in 0..A {
                        let v: f64 = (0..D).map(|i| x[i] * w[i * A + a]).sum();
                        act[a] = (v as f32).clamp(-1.0, 1.0);
                    }
                }
                let r = env.step(&act);
                steps += 1;
                if r.done {
                    wins += usize::from(r.success);
                    break;
                }
                prev.copy_from_slice(&fast);
                env.observe(&mut fast, &mut slow);
            }
        }
        println!(
            "{name}, zero latency: {wins}/{episodes} successes ({:.3}), {:.0} steps per episode",
            wins as f64 / episodes as f64,
            steps as f64 / episodes as f64
        );
    }
    Ok(())
}
