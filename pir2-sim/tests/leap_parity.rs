//! Parity of `pir2_sim::leap` with MuJoCo Playground's LeapCubeReorient and the paper's
//! variant. Needs the native MuJoCo and the scene: `source .native/env.sh`.
#![cfg(feature = "mujoco")]

use std::sync::OnceLock;

use pir2_runtime::Environment;
use pir2_schedule::Rng;
use pir2_sim::leap::math::{self, Quat};
use pir2_sim::leap::{
    collect, CollectConfig, LeapConfig, LeapCubeEnv, LeapModel, MpcConfig, MpcExpert, NoiseConfig,
    NU,
};

fn model() -> &'static LeapModel {
    static M: OnceLock<LeapModel> = OnceLock::new();
    M.get_or_init(|| {
        LeapModel::load(None)
            .expect("Leap-cube scene: run scripts/setup-native.sh and source .native/env.sh")
    })
}

fn env(cfg: LeapConfig) -> LeapCubeEnv {
    LeapCubeEnv::new(model(), cfg).unwrap()
}

fn noiseless(mut cfg: LeapConfig) -> LeapConfig {
    cfg.noise = NoiseConfig::NONE;
    cfg
}

fn obs(e: &mut LeapCubeEnv) -> (Vec<f32>, Vec<f32>) {
    let (f, s) = e.config().obs_dims();
    let (mut fast, mut slow) = (vec![0.0; f], vec![0.0; s]);
    e.observe(&mut fast, &mut slow);
    (fast, slow)
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

#[test]
fn model_matches_the_playground_scene() {
    let m = model();
    let strip = m.strip_report();
    assert_eq!(strip.meshes.len(), 10, "{strip:?}");
    assert_eq!(strip.geoms, 21);
    let mm = m.mj_model();
    let f = mm.ffi();
    assert_eq!((f.nq, f.nv, f.nu), (23, 22, 16));
    assert_eq!(m.timestep(), 0.01);
    let collidable = mm
        .geom_contype()
        .iter()
        .zip(mm.geom_conaffinity())
        .filter(|(t, a)| **t != 0 || **a != 0)
        .count();
    assert_eq!(collidable, 37);
    assert_eq!(f.opt.iterations, 5);
    // Home pose of the keyframe, and the control range.
    let (lo, hi) = m.ctrl_range();
    assert_eq!(m.home()[0], 0.8);
    assert_eq!(m.home()[15], 0.0);
    for i in 0..NU {
        assert!(lo[i] < m.home()[i] && m.home()[i] < hi[i]);
    }
    let g = m.grasp_pos();
    assert!(
        close(g[0], 0.11, 1e-9) && close(g[1], 0.0, 1e-9) && close(g[2], 0.03, 1e-9),
        "{g:?}"
    );
}

#[test]
fn specs_of_both_configurations() {
    let p = env(LeapConfig::paper()).spec();
    assert_eq!(
        (p.fast_dim, p.slow_dim, p.action_dim, p.max_steps),
        (32, 9, 16, 600)
    );
    assert_eq!(p.control_period, 20_000_000);
    let o = env(LeapConfig::playground()).spec();
    assert_eq!(
        (o.fast_dim, o.slow_dim, o.action_dim, o.max_steps),
        (57, 0, 16, 1000)
    );
    assert_eq!(o.control_period, 50_000_000);
    assert_eq!(env(LeapConfig::paper()).substeps(), 2);
    assert_eq!(env(LeapConfig::playground()).substeps(), 5);
}

#[test]
fn paper_observation_layout() {
    let mut e = env(noiseless(LeapConfig::paper()));
    e.reset(5);
    let mut rng = Rng::new(9);
    for step in 0..6 {
        let (fast, _) = obs(&mut e);
        let q = e.hand_q();
        let t = e.motor_targets();
        for i in 0..NU {
            assert!(close(fast[i] as f64, q[i], 1e-6), "step {step} joint {i}");
            assert!(
                close(fast[NU + i] as f64, q[i] - t[i], 1e-6),
                "step {step} error {i}"
            );
        }
        // The cube sensors lag one substep behind qpos after a step; `set_cube_pose` runs
        // mj_forward, after which they agree exactly.
        let (p, quat) = e.cube_pose();
        e.set_cube_pose(p, quat);
        let (_, slow) = obs(&mut e);
        let g = model().grasp_pos();
        for k in 0..3 {
            assert!(
                close(slow[k] as f64, g[k] - p[k], 1e-6),
                "step {step} pos {k}: {slow:?}"
            );
        }
        let rows = math::rot_rows_23(&quat);
        for k in 0..6 {
            assert!(
                close(slow[3 + k] as f64, rows[k], 1e-6),
                "step {step} rot {k}"
            );
        }
        let a: Vec<f32> = (0..NU).map(|_| rng.uniform_range(-1.0, 1.0)).collect();
        e.step(&a);
    }
}

#[test]
fn playground_observation_layout() {
    let mut e = env(noiseless(LeapConfig::playground()));
    e.reset(11);
    let (fast, slow) = obs(&mut e);
    assert_eq!((fast.len(), slow.len()), (57, 0));
    let (_, quat) = e.cube_pose();
    let goal = e.goals()[0];
    let rows = math::rot_rows_23(&math::mul_inv(&quat, &goal));
    for k in 0..6 {
        assert!(close(fast[35 + k] as f64, rows[k], 1e-6));
    }
    assert!(fast[41..].iter().all(|v| *v == 0.0));
    let a1 = [0.25f32; NU];
    let a2 = [-0.5f32; NU];
    e.step(&a1);
    let (f1, _) = obs(&mut e);
    assert!(
        f1[41..].iter().all(|v| *v == 0.0),
        "obs after step 1 holds the action before a1"
    );
    e.step(&a2);
    let (f2, _) = obs(&mut e);
    assert_eq!(
        &f2[41..],
        &a1[..],
        "obs after step 2 holds a1 (the playground's last_act)"
    );
}

#[test]
fn noise_model_matches_the_reference() {
    let mut e = env(LeapConfig::paper());
    e.reset(3);
    let q = e.hand_q();
    let t = *e.motor_targets();
    let (p, quat) = e.cube_pose();
    let g = model().grasp_pos();
    let n = 3000;
    let (mut jmin, mut jmax, mut jsum, mut jsq) = (f64::MAX, f64::MIN, 0.0, 0.0);
    let (mut pmin, mut pmax) = (f64::MAX, f64::MIN);
    let mut rot_sq = 0.0;
    let true_rows = math::rot_rows_23(&quat);
    for _ in 0..n {
        let (fast, slow) = obs(&mut e);
        for i in 0..NU {
            let d = fast[i] as f64 - q[i];
            jmin = jmin.min(d);
            jmax = jmax.max(d);
            jsum += d;
            jsq += d * d;
            // The error channel carries the same noisy angle.
            assert!(close(fast[NU + i] as f64, fast[i] as f64 - t[i], 1e-5));
        }
        for k in 0..3 {
            let d = (g[k] - p[k]) - slow[k] as f64;
            pmin = pmin.min(d);
            pmax = pmax.max(d);
        }
        for k in 0..6 {
            rot_sq += (slow[3 + k] as f64 - true_rows[k]).powi(2);
        }
    }
    let m = (n * NU) as f64;
    assert!(
        jmin >= -0.05 - 1e-6 && jmax <= 0.05 + 1e-6,
        "joint noise range {jmin}..{jmax}"
    );
    assert!(
        jmin < -0.049 && jmax > 0.049,
        "joint noise does not reach ±0.05"
    );
    assert!((jsum / m).abs() < 0.002);
    let var = jsq / m;
    assert!(
        close(var, 0.05f64.powi(2) / 3.0, 0.1 * 0.05f64.powi(2) / 3.0),
        "joint var {var}"
    );
    assert!(pmin >= -0.02 - 1e-6 && pmax <= 0.02 + 1e-6 && pmin < -0.019 && pmax > 0.019);
    // Quaternion noise: compare with the specified model N(0, 0.1) + renormalise.
    let mut rng = Rng::new(1);
    let mut ref_sq = 0.0;
    for _ in 0..n {
        let mut nq: Quat = std::array::from_fn(|k| quat[k] + 0.1 * rng.normal() as f64);
        let norm = nq.iter().map(|v| v * v).sum::<f64>().sqrt();
        nq.iter_mut().for_each(|v| *v /= norm);
        let r = math::rot_rows_23(&nq);
        ref_sq += (0..6).map(|k| (r[k] - true_rows[k]).powi(2)).sum::<f64>();
    }
    let ratio = rot_sq / ref_sq;
    assert!(
        (0.85..1.15).contains(&ratio),
        "orientation noise power ratio {ratio}"
    );
}

#[test]
fn reset_distribution_matches_the_playground() {
    let mut e = env(LeapConfig::paper());
    let m = model();
    let (lo, hi) = m.ctrl_range();
    let n = 300;
    let mut qsum = [0.0; NU];
    let mut psum = [0.0; 3];
    let mut mom = [[0.0; 4]; 4];
    for seed in 0..n {
        e.reset(seed);
        let q = e.hand_q();
        assert_eq!(&q, e.motor_targets(), "motor targets start at the pose");
        assert!(e.data().qvel().iter().all(|v| *v == 0.0));
        assert_eq!(e.data().ctrl(), &q[..]);
        for i in 0..NU {
            assert!(lo[i] <= q[i] && q[i] <= hi[i]);
            qsum[i] += q[i] / n as f64;
        }
        let (p, quat) = e.cube_pose();
        for k in 0..3 {
            let c = [0.1, 0.0, 0.05][k];
            assert!((p[k] - c).abs() <= 0.01 + 1e-9, "cube pos {p:?}");
            psum[k] += (p[k] - c) / n as f64;
        }
        for i in 0..4 {
            for j in 0..4 {
                mom[i][j] += quat[i] * quat[j] / n as f64;
            }
        }
    }
    for i in 0..NU {
        // Joints whose home sits at a range limit are clipped (biased); others are centred.
        if m.home()[i] - 0.25 > lo[i] && m.home()[i] + 0.25 < hi[i] {
            assert!(
                (qsum[i] - m.home()[i]).abs() < 0.025,
                "joint {i} mean {}",
                qsum[i]
            );
        }
    }
    assert!(psum.iter().all(|v| v.abs() < 0.002), "{psum:?}");
    for (i, row) in mom.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            let want = if i == j { 0.25 } else { 0.0 };
            assert!(
                (v - want).abs() < 0.07,
                "quaternion moment [{i}][{j}] = {v}"
            );
        }
    }
}

#[test]
fn same_seed_same_bits() {
    let run = |seed: u64| {
        let mut e = env(LeapConfig::paper());
        e.reset(seed);
        let mut rng = Rng::new(77);
        let mut bits = Vec::new();
        for _ in 0..25 {
            let (f, s) = obs(&mut e);
            bits.extend(f.iter().chain(&s).map(|v| v.to_bits()));
            let a: Vec<f32> = (0..NU).map(|_| rng.uniform_range(-1.0, 1.0)).collect();
            bits.push(e.step(&a).reward.to_bits());
        }
        bits
    };
    assert_eq!(run(4), run(4));
    assert_ne!(run(4), run(5));
}

#[test]
fn paper_success_criterion_and_drop() {
    let goals = math::blue_side_up_goals();
    let tilt = |angle: f64, g: &Quat| -> Quat {
        let h = angle / 2.0;
        let r = math::to_na(&[h.cos(), h.sin(), 0.0, 0.0]) * math::to_na(g);
        math::from_na(&r)
    };
    let mut e = env(LeapConfig::paper());
    for (k, g) in goals.iter().enumerate() {
        e.reset(k as u64);
        e.set_cube_pose([0.11, 0.0, 0.07], tilt(0.12, g));
        assert!(e.orientation_error() < 0.2);
        let st = e.step(&[0.0; NU]);
        assert!(st.done && st.success, "goal {k}: {st:?}");
        assert!(st.reward > 50.0, "success bonus: {}", st.reward);
        // After done, step repeats the outcome.
        assert_eq!(e.step(&[0.0; NU]), st);
        e.reset(k as u64);
        e.set_cube_pose([0.11, 0.0, 0.07], tilt(0.6, g));
        let st = e.step(&[0.0; NU]);
        assert!(!st.done && !st.success, "0.6 rad off goal {k}: {st:?}");
    }
    e.reset(1);
    e.set_cube_pose([0.3, 0.3, -0.2], goals[0]);
    let st = e.step(&[0.0; NU]);
    assert!(
        st.done && !st.success,
        "a dropped cube ends the episode in failure: {st:?}"
    );
}

#[test]
fn episode_times_out_at_max_steps() {
    let mut cfg = LeapConfig::paper();
    cfg.max_steps = 4;
    cfg.success_threshold = 0.0;
    let mut e = env(cfg);
    e.reset(2);
    for i in 0..4 {
        let st = e.step(&[0.0; NU]);
        assert_eq!(st.done, i == 3, "step {i}");
        assert!(!st.success);
    }
    assert_eq!(e.steps(), 4);
}

#[test]
fn actions_move_motor_targets_by_half_a_radian_at_most() {
    let mut e = env(LeapConfig::paper());
    e.reset(8);
    let t0 = *e.motor_targets();
    let (lo, hi) = model().ctrl_range();
    e.step(&[3.0; NU]); // clamped to 1
    for i in 0..NU {
        assert!(close(e.motor_targets()[i], (t0[i] + 0.5).min(hi[i]), 1e-12));
    }
    let t1 = *e.motor_targets();
    e.step(&[-0.2; NU]);
    for i in 0..NU {
        assert!(close(e.motor_targets()[i], (t1[i] - 0.1).max(lo[i]), 1e-6));
    }
}

fn tiny_mpc(threads: usize) -> MpcConfig {
    MpcConfig {
        samples: 6,
        horizon: 5,
        threads,
        ..MpcConfig::default()
    }
}

#[test]
fn mpc_is_seeded_and_independent_of_thread_count() {
    let run = |threads: usize, seed: u64| {
        let mut e = env(LeapConfig::paper());
        e.reset(3);
        let mut x = MpcExpert::new(model(), tiny_mpc(threads), 0).unwrap();
        x.reset(&e, seed);
        let mut acts = Vec::new();
        for _ in 0..4 {
            let a = x.act(&e);
            assert!(a.iter().all(|v| (-1.0..=1.0).contains(v)));
            acts.extend(a.iter().map(|v| v.to_bits()));
            e.step(&a);
        }
        acts
    };
    let one = run(1, 42);
    assert_eq!(one, run(2, 42));
    assert_ne!(one, run(2, 43));
}

#[test]
fn collect_records_frames_and_resumes_by_episode_index() {
    let mut env_cfg = LeapConfig::paper();
    env_cfg.max_steps = 3;
    let cfg = CollectConfig {
        env: env_cfg,
        mpc: tiny_mpc(2),
        seed: 7,
    };
    let mut seen = Vec::new();
    let all = collect(model(), &cfg, 0..2, |ep| seen.push(ep.index)).unwrap();
    assert_eq!(seen, vec![0, 1]);
    let resumed = collect(model(), &cfg, 1..2, |_| {}).unwrap();
    assert_eq!(resumed[0], all[1]);
    assert_ne!(all[0].env_seed, all[1].env_seed);
    for ep in &all {
        assert_eq!(ep.frames.len(), 3);
        for (i, f) in ep.frames.iter().enumerate() {
            assert_eq!((f.episode_index, f.frame_index), (ep.index, i));
            assert_eq!((f.fast.len(), f.slow.len(), f.action.len()), (32, 9, 16));
            assert_eq!(f.done, i == 2);
        }
    }
}

#[test]
fn env_and_expert_can_move_to_a_worker_thread() {
    fn assert_send<T: Send>() {}
    assert_send::<LeapCubeEnv>();
    assert_send::<MpcExpert>();
    let mut e = env(LeapConfig::paper());
    let h = std::thread::spawn(move || {
        e.reset(1);
        e.step(&[0.0; NU])
    });
    assert!(!h.join().unwrap().done);
}

#[test]
fn saved_state_continues_bit_identically() {
    // Branching an episode (the labels' repeatability diagnosis) relies on this.
    let mut e = env(LeapConfig::paper());
    e.reset(11);
    let mut rng = Rng::new(5);
    let mut act = || -> [f32; NU] { std::array::from_fn(|_| 2.0 * rng.uniform() - 1.0) };
    for _ in 0..10 {
        e.step(&act());
    }
    let saved = e.save();
    let actions: Vec<[f32; NU]> = (0..20).map(|_| act()).collect();
    let run = |e: &mut LeapCubeEnv| {
        let mut trace = Vec::new();
        for a in &actions {
            let st = e.step(a);
            let (f, s) = obs(e);
            trace.push((f, s, st.reward.to_bits(), e.cube_pose()));
        }
        trace
    };
    let first = run(&mut e);
    e.restore(&saved).unwrap();
    let second = run(&mut e);
    assert_eq!(first.len(), second.len());
    for (t, (a, b)) in first.iter().zip(&second).enumerate() {
        assert!(
            a.0 == b.0 && a.1 == b.1 && a.2 == b.2 && a.3 == b.3,
            "step {t} differs after restore"
        );
    }
}
