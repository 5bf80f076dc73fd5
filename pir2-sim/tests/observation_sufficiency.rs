//! The ball-on-plate observations carry what the expert acts on: a *linear* policy fitted by
//! least squares to expert demonstrations on `[o_fast, o_fast − o_fast_prev, o_slow]` keeps
//! the ball on the plate at zero delay. Without the camera tracker's velocity (the slow
//! channel's last two entries) the same fit fails: the learned policies of `pir2 demo` all
//! scored 0 until the slow channel carried it.

use faer::prelude::*;
use faer::Mat;
use pir2_runtime::Environment;
use pir2_sim::ballplate::{BallPlate, BallPlateConfig, FAST_DIM, SLOW_DIM};
use pir2_sim::dataset::{collect_episodes, CollectConfig, Episode};
use pir2_sim::expert::{LqrConfig, LqrExpert};

/// Features used by the linear policy: fast, fast difference, and the first `slow_used`
/// slow entries, then a bias.
fn features(f: &[f32], pf: &[f32], s: &[f32], slow_used: usize, out: &mut Vec<f64>) {
    out.clear();
    out.extend(f.iter().map(|&v| v as f64));
    out.extend(f.iter().zip(pf).map(|(a, b)| (a - b) as f64));
    out.extend(s[..slow_used].iter().map(|&v| v as f64));
    out.push(1.0);
}

/// Ridge-regularised least squares `W = (XᵀX + λI)⁻¹ XᵀY`.
fn fit(demos: &[Episode], slow_used: usize) -> Mat<f64> {
    let n = 2 * FAST_DIM + slow_used + 1;
    let mut xtx = Mat::<f64>::zeros(n, n);
    let mut xty = Mat::<f64>::zeros(n, 2);
    let mut x = Vec::new();
    for e in demos {
        for t in 1..e.len() {
            features(e.fast(t), e.fast(t - 1), e.slow(t), slow_used, &mut x);
            for i in 0..n {
                for j in 0..n {
                    xtx[(i, j)] += x[i] * x[j];
                }
                for k in 0..2 {
                    xty[(i, k)] += x[i] * e.action(t)[k] as f64;
                }
            }
        }
    }
    for i in 0..n {
        xtx[(i, i)] += 1e-6;
    }
    xtx.partial_piv_lu().solve(&xty)
}

fn closed_loop_success(w: &Mat<f64>, slow_used: usize, episodes: u64) -> usize {
    let mut env = BallPlate::new(BallPlateConfig::default()).unwrap();
    let (mut f, mut s) = ([0f32; FAST_DIM], [0f32; SLOW_DIM]);
    let mut x = Vec::new();
    let mut ok = 0;
    for ep in 0..episodes {
        env.reset(10_000 + ep);
        env.observe(&mut f, &mut s);
        let mut pf = f;
        loop {
            env.observe(&mut f, &mut s);
            features(&f, &pf, &s, slow_used, &mut x);
            let a: Vec<f32> = (0..2)
                .map(|k| (0..x.len()).map(|i| x[i] * w[(i, k)]).sum::<f64>() as f32)
                .collect();
            pf = f;
            let st = env.step(&a);
            if st.done {
                ok += st.success as usize;
                break;
            }
        }
    }
    ok
}

#[test]
fn linear_policy_needs_and_gets_the_camera_velocity() {
    let task = BallPlateConfig::default();
    let mut env = BallPlate::new(task.clone()).unwrap();
    let mut expert = LqrExpert::new(&task, LqrConfig::default()).unwrap();
    let cfg = CollectConfig {
        episodes: 60,
        seed: 3,
        ..CollectConfig::default()
    };
    let demos = collect_episodes(&mut env, &mut expert, &cfg, &mut |_| {}).unwrap();
    let with = closed_loop_success(&fit(&demos, SLOW_DIM), SLOW_DIM, 30);
    let without = closed_loop_success(&fit(&demos, 2), 2, 30);
    eprintln!("with {with} without {without}");
    assert!(with >= 24, "with the camera velocity: {with}/30");
    assert!(without <= 6, "positions only: {without}/30");
}
