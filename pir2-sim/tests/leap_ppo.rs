//! PPO on the Leap cube: reward terms at known states, resume = uninterrupted (and the
//! thread count does not matter), the expert's weights file. Needs the native MuJoCo and
//! the scene: `source .native/env.sh`.
#![cfg(feature = "mujoco")]

use std::f64::consts::PI;
use std::sync::OnceLock;

use nalgebra::{UnitQuaternion, Vector3};
use pir2_sim::leap::math::{self, Quat};
use pir2_sim::leap::ppo::task::{actor_dim, critic_dim, tolerance_linear, PpoEnv};
use pir2_sim::leap::ppo::{evaluate, evaluate_delayed, PpoConfig, PpoExpert, Trainer};
use pir2_sim::leap::{LeapConfig, LeapModel, NU};
use pir2_sim::Error;

fn model() -> &'static LeapModel {
    static M: OnceLock<LeapModel> = OnceLock::new();
    M.get_or_init(|| {
        LeapModel::load(None)
            .expect("Leap-cube scene: run scripts/setup-native.sh and source .native/env.sh")
    })
}

fn tiny() -> PpoConfig {
    PpoConfig {
        seed: 7,
        n_envs: 4,
        rollout_len: 8,
        env_chunk: 2,
        segment_iters: 2,
        epochs: 2,
        minibatches: 2,
        grad_chunks: 2,
        actor_hidden: vec![16, 16],
        critic_hidden: vec![16, 16],
        ..PpoConfig::default()
    }
}

fn tmp_dir(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("pir2-leap-ppo-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn rotated(axis: [f64; 3], angle: f64, q: &Quat) -> Quat {
    let r = UnitQuaternion::from_axis_angle(
        &nalgebra::Unit::new_normalize(Vector3::new(axis[0], axis[1], axis[2])),
        angle,
    );
    math::from_na(&(r.into_inner() * math::to_na(q)))
}

#[test]
fn reward_terms_sum_to_the_environment_reward_along_random_rollouts() {
    let mut env = PpoEnv::new(model(), LeapConfig::paper(), false).unwrap();
    let dt = LeapConfig::paper().ctrl_dt;
    let mut rng = pir2_schedule::Rng::new(3);
    let mut checked = 0;
    for ep in 0..3 {
        env.reset(ep);
        for _ in 0..150 {
            let a: Vec<f32> = (0..NU).map(|_| rng.uniform_range(-1.2, 1.2)).collect();
            let out = env.step(&a);
            let total = out.terms.total(dt);
            assert!(
                (total - f64::from(out.reward)).abs() < 1e-4 * (1.0 + total.abs()),
                "terms {:?} sum to {total}, environment reward {}",
                out.terms,
                out.reward
            );
            checked += 1;
            if out.ending != pir2_sim::leap::ppo::task::Ending::Running {
                break;
            }
        }
    }
    assert!(checked > 100);
}

#[test]
fn reward_terms_at_known_states() {
    let mut env = PpoEnv::new(model(), LeapConfig::paper(), false).unwrap();
    env.reset(1);
    let grasp = model().grasp_pos();
    let goals = math::blue_side_up_goals();
    let zero = [0.0f32; NU];
    // Cube on the grasp site exactly at a goal: full orientation and position terms, success.
    env.env_mut().set_cube_pose(grasp, goals[2]);
    let t = env.reward_terms(&zero);
    assert!((t.orientation - 1.0).abs() < 1e-9, "{t:?}");
    assert!((t.position - 1.0).abs() < 1e-9, "{t:?}");
    assert_eq!((t.termination, t.success), (0.0, 1.0));
    // At rest right after a reset: no power, hand pose = Σ(q − home)² of the reset noise.
    assert!(t.energy.abs() < 1e-12, "{t:?}");
    let q = env.env().hand_q();
    let hp: f64 = (0..NU).map(|i| (q[i] - model().home()[i]).powi(2)).sum();
    assert!((t.hand_pose - hp).abs() < 1e-12 && hp > 0.0);
    // Tilted 1.2 rad from goal 0 about the world x axis (≥ 1.2 rad from every other goal),
    // 4 cm from the grasp site: tol(1.2; 0.2, π) and tol(0.04; 0.02, 0.05).
    let tilted = rotated([1.0, 0.0, 0.0], 1.2, &goals[0]);
    env.env_mut()
        .set_cube_pose([grasp[0] + 0.04, grasp[1], grasp[2]], tilted);
    let t = env.reward_terms(&zero);
    assert!(
        (t.orientation - (1.0 - 0.9 * 1.0 / PI)).abs() < 1e-6,
        "{t:?}"
    );
    assert!((t.orientation - tolerance_linear(1.2, 0.2, PI)).abs() < 1e-6);
    assert!((t.position - 0.64).abs() < 1e-6, "{t:?}");
    assert_eq!(t.success, 0.0);
    // Dropped below −5 cm: the termination term.
    env.env_mut().set_cube_pose([0.1, 0.0, -0.1], tilted);
    let t = env.reward_terms(&zero);
    assert_eq!(t.termination, 1.0);
    assert!(env.dropped());
    // Action rate after a reset (previous actions 0): Σ (a² + a²) = 16 · 0.5 for a = 0.5.
    let t = env.reward_terms(&[0.5; NU]);
    assert!((t.action_rate - 8.0).abs() < 1e-9, "{t:?}");
    // Weighted total: 100 for success dominates, the shaped part is scaled by ctrl_dt.
    let mut terms = t;
    terms.termination = 0.0;
    terms.success = 1.0;
    let dt = 0.02;
    let shaped = 5.0 * terms.orientation + 0.5 * terms.position
        - 0.5 * terms.hand_pose
        - 0.001 * terms.action_rate
        - 0.001 * terms.energy;
    assert!((terms.total(dt) - (shaped * dt + 100.0)).abs() < 1e-9);
}

#[test]
fn observations_have_the_documented_widths_and_the_actor_sees_the_env_observation() {
    for prev in [false, true] {
        let mut env = PpoEnv::new(model(), LeapConfig::paper(), prev).unwrap();
        env.reset(5);
        let mut a = vec![f32::NAN; actor_dim(prev)];
        let mut c = vec![f32::NAN; critic_dim(prev)];
        env.actor_obs(&mut a);
        env.critic_obs(&mut c);
        assert!(a.iter().chain(&c).all(|v| v.is_finite()));
        let (fast, slow) = env.observation();
        assert_eq!(&a[..32], &fast[..]);
        assert_eq!(&a[32..41], &slow[..]);
        assert_eq!(&c[..a.len()], &a[..]);
        env.step(&[0.3; NU]);
        env.actor_obs(&mut a);
        if prev {
            assert_eq!(&a[41..], &[0.3f32; NU][..]);
        }
    }
}

#[test]
fn resume_continues_bit_identically_and_threads_do_not_matter() {
    let m = model();
    let mut straight = Trainer::new(m, tiny(), 2).unwrap();
    for _ in 0..4 {
        straight.iterate().unwrap();
    }
    let want = straight.state_fingerprint();

    let dir = tmp_dir("resume");
    let path = dir.join("checkpoint.safetensors");
    let mut first = Trainer::new(m, tiny(), 2).unwrap();
    first.iterate().unwrap();
    // Inside a segment: refused.
    assert!(first.save_checkpoint(&path).is_err());
    first.iterate().unwrap();
    first.save_checkpoint(&path).unwrap();
    drop(first);
    // Resumed on one thread.
    let mut resumed = Trainer::load_checkpoint(m, &path, 1).unwrap();
    assert_eq!(resumed.iteration(), 2);
    for _ in 0..2 {
        resumed.iterate().unwrap();
    }
    assert_eq!(resumed.state_fingerprint(), want);

    // A different seed gives different bits (the fingerprint can fail).
    let mut other = Trainer::new(m, PpoConfig { seed: 8, ..tiny() }, 2).unwrap();
    for _ in 0..4 {
        other.iterate().unwrap();
    }
    assert_ne!(other.state_fingerprint(), want);
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn expert_weights_round_trip_and_act_deterministically() {
    let m = model();
    let mut tr = Trainer::new(m, tiny(), 2).unwrap();
    tr.iterate().unwrap();
    tr.iterate().unwrap();
    let mut ex = tr.expert();
    let dir = tmp_dir("expert");
    let path = dir.join("expert.safetensors");
    ex.save(&path).unwrap();
    let mut back = PpoExpert::load(&path).unwrap();
    assert_eq!(back.trained(), (2, 64));
    let mut env = PpoEnv::new(m, LeapConfig::paper(), false).unwrap();
    env.reset(9);
    let (fast, slow) = env.observation();
    let a = ex.act(fast, slow);
    assert_eq!(back.act(fast, slow), a);
    assert_eq!(ex.act(fast, slow), a, "same observation, same action");
    assert!(a.iter().all(|v| (-1.0..=1.0).contains(v)));
    // A short evaluation runs and does not depend on the thread count.
    let r1 = evaluate(m, &ex, 0..2, 0, 1).unwrap();
    let r2 = evaluate(m, &ex, 0..2, 0, 2).unwrap();
    assert_eq!(r1, r2);
    assert_eq!(r1.episodes, 2);
    assert_eq!(evaluate_delayed(m, &ex, 0..2, 0, 1, 0).unwrap(), r1);
    // Delayed actions: each episode starts its own queue, so the thread count (which
    // episodes follow which on a thread) does not change the result either.
    let d1 = evaluate_delayed(m, &ex, 0..3, 0, 1, 3).unwrap();
    assert_eq!(d1, evaluate_delayed(m, &ex, 0..3, 0, 2, 3).unwrap());
    assert_eq!(d1.episodes, 3);
    // A checkpoint is not an expert file and vice versa: one clear error.
    let ck = dir.join("checkpoint.safetensors");
    tr.save_checkpoint(&ck).unwrap();
    match PpoExpert::load(&ck) {
        Err(Error::PpoFormat { message, .. }) => assert!(message.contains("format"), "{message}"),
        other => panic!("loading a checkpoint as an expert: {other:?}"),
    }
    assert!(Trainer::load_checkpoint(m, &path, 1).is_err());
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn environments_start_segments_from_different_states() {
    let cfg = PpoConfig {
        rollout_len: 1,
        ..tiny()
    };
    let mut tr = Trainer::new(model(), cfg, 2).unwrap();
    tr.iterate().unwrap();
    let quats: Vec<Quat> = tr.envs().iter().map(|e| e.env().cube_pose().1).collect();
    for i in 0..quats.len() {
        for j in 0..i {
            let d = math::orientation_error(&quats[i], &quats[j]);
            assert!(d > 0.3, "envs {i} and {j} start {d} rad apart");
        }
    }
}
