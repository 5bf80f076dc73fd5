//! Config, camera, dynamics (momentum, friction, energy, servo, torque), pushes, seeding
//! and success on the ball-on-plate task.

use super::*;

fn quiet() -> BallPlateConfig {
    BallPlateConfig {
        push_rate: 0.0,
        ball_friction: 0.0,
        ..Default::default()
    }
}

#[test]
fn config_toml_roundtrip_and_partial() {
    let cfg = BallPlateConfig::from_toml_str("push_rate = 0.3\nsubsteps = 20\n").unwrap();
    assert_eq!(cfg.push_rate, 0.3);
    assert_eq!(cfg.substeps, 20);
    assert_eq!(cfg.servo_kp, 625.0);
    let s = toml::to_string(&BallPlateConfig::default()).unwrap();
    assert_eq!(
        BallPlateConfig::from_toml_str(&s).unwrap(),
        BallPlateConfig::default()
    );
    assert!(BallPlateConfig::from_toml_str("no_such_field = 1").is_err());
    assert!(matches!(
        BallPlateConfig::from_toml_str("substeps = 0"),
        Err(Error::ConfigValue {
            field: "substeps",
            ..
        })
    ));
}

#[test]
fn camera_reports_position_and_frame_difference_velocity() {
    // Noise-free camera, level plate held level, no friction: the ball rolls at constant
    // speed, and the tracker's velocity is exact from the first frame on.
    let cfg = BallPlateConfig {
        noise_camera: 0.0,
        ..quiet()
    };
    let mut env = BallPlate::new(cfg).unwrap();
    env.freeze = Freeze::Plate;
    env.reset(1);
    let (mut f, mut s) = ([0f32; FAST_DIM], [0f32; SLOW_DIM]);
    for _ in 0..5 {
        env.observe(&mut f, &mut s);
        let st = *env.state();
        for i in 0..2 {
            assert!((s[i] as f64 - st.pos[i]).abs() < 1e-7);
            assert!(
                (s[2 + i] as f64 - st.vel[i]).abs() < 1e-5,
                "{s:?} vs {st:?}"
            );
        }
        env.step(&[0.0, 0.0]);
    }
    // Observing twice within a tick gives the same camera frame.
    let (mut s1, mut s2) = ([0f32; SLOW_DIM], [0f32; SLOW_DIM]);
    let mut noisy = BallPlate::new(BallPlateConfig::default()).unwrap();
    noisy.observe(&mut f, &mut s1);
    noisy.observe(&mut f, &mut s2);
    assert_eq!(s1, s2);
}

#[test]
fn spec_matches_findings() {
    let env = BallPlate::new(BallPlateConfig::default()).unwrap();
    let spec = env.spec();
    assert_eq!((spec.fast_dim, spec.slow_dim, spec.action_dim), (6, 4, 2));
    assert_eq!(spec.control_period, 20_000_000);
    assert_eq!(spec.max_steps, 500);
    assert!((env.config().dt() - 0.002).abs() < 1e-15);
}

#[test]
fn level_plate_conserves_ball_momentum() {
    let mut env = BallPlate::new(quiet()).unwrap();
    env.freeze = Freeze::Plate;
    let s0 = BallPlateState {
        pos: [0.0, -0.01],
        vel: [0.012, 0.007],
        ..Default::default()
    };
    env.set_state(s0);
    for _ in 0..200 {
        env.step(&[0.0, 0.0]);
    }
    let s = env.state();
    assert_eq!(
        s.vel, s0.vel,
        "velocity must be exactly conserved on a level frictionless plate"
    );
    for i in 0..2 {
        let expect = s0.pos[i] + s0.vel[i] * 4.0;
        assert!(
            (s.pos[i] - expect).abs() < 1e-9,
            "axis {i}: {} vs {expect}",
            s.pos[i]
        );
    }
}

#[test]
fn friction_decays_momentum() {
    let mut env = BallPlate::new(BallPlateConfig {
        push_rate: 0.0,
        ..Default::default()
    })
    .unwrap();
    env.freeze = Freeze::Plate;
    env.set_state(BallPlateState {
        vel: [0.01, 0.0],
        ..Default::default()
    });
    for _ in 0..50 {
        env.step(&[0.0, 0.0]);
    }
    // v(t) = v0·exp(−c·t) at t = 1 s.
    let expect = 0.01 * (-0.1f64).exp();
    assert!(
        (env.state().vel[0] - expect).abs() < 1e-6,
        "{}",
        env.state().vel[0]
    );
}

#[test]
fn tilted_plate_energy_balance() {
    // Rolling solid sphere: kinetic energy per unit mass (7/10)·v², potential g·Δh with
    // Δh = Δp·sin θ along the slope.
    let theta = 0.05;
    let mut env = BallPlate::new(BallPlateConfig {
        bound: 10.0,
        ..quiet()
    })
    .unwrap();
    env.freeze = Freeze::Plate;
    env.set_state(BallPlateState {
        tilt: [theta, -theta],
        ..Default::default()
    });
    for _ in 0..40 {
        env.step(&[0.0, 0.0]);
    }
    let g = env.config().gravity;
    for i in 0..2 {
        let s = env.state();
        let ke = 0.7 * s.vel[i] * s.vel[i];
        let pe_drop = g * s.pos[i] * s.tilt[i].sin();
        assert!(pe_drop > 0.01, "ball must roll downhill");
        let rel = (ke - pe_drop).abs() / pe_drop;
        assert!(
            rel < 5e-3,
            "axis {i}: KE {ke} vs PE drop {pe_drop} (rel {rel})"
        );
    }
}

#[test]
fn servo_settles_with_expected_damping() {
    let mut env = BallPlate::new(quiet()).unwrap();
    env.freeze = Freeze::Ball;
    env.set_state(BallPlateState::default());
    let r = 0.1;
    let mut peak = 0.0f64;
    for _ in 0..50 {
        env.step(&[r as f32, -r as f32]);
        peak = peak.max(env.state().tilt[0]);
        assert!(
            (env.state().tilt[0] + env.state().tilt[1]).abs() < 1e-12,
            "axes are symmetric"
        );
    }
    // ζ = 0.8: overshoot exp(−ζπ/√(1−ζ²)) ≈ 1.5 %.
    let overshoot = (peak - r) / r;
    let zeta = 40.0 / (2.0 * 625f64.sqrt());
    let expect = (-zeta * std::f64::consts::PI / (1.0 - zeta * zeta).sqrt()).exp();
    assert!(
        (overshoot - expect).abs() < 0.005,
        "overshoot {overshoot} vs {expect}"
    );
    assert!(
        (env.state().tilt[0] - r).abs() < 1e-6,
        "settled at {}",
        env.state().tilt[0]
    );
    assert!(env.state().tilt_rate[0].abs() < 1e-5);
    // The torque vanishes at rest when the ball is centred.
    assert!(env.torque(0).abs() < 1e-3);
}

#[test]
fn load_moment_shows_in_torque() {
    // Quasi-statically the servo torque balances the ball's load: τ = −β·p.
    let mut env = BallPlate::new(quiet()).unwrap();
    env.freeze = Freeze::Ball;
    env.set_state(BallPlateState {
        pos: [0.05, -0.02],
        ..Default::default()
    });
    for _ in 0..100 {
        env.step(&[0.0, 0.0]);
    }
    assert!(
        (env.torque(0) + 40.0 * 0.05).abs() < 1e-6,
        "{}",
        env.torque(0)
    );
    assert!(
        (env.torque(1) - 40.0 * 0.02).abs() < 1e-6,
        "{}",
        env.torque(1)
    );
}

#[test]
fn clamps_actions() {
    let mut env = BallPlate::new(quiet()).unwrap();
    env.step(&[1.0, -f32::NAN]);
    assert_eq!(env.state().target, [0.15, 0.0]);
    env.step(&[-3.0, 0.01]);
    assert_eq!(env.state().target[0], -0.15);
    assert!((env.state().target[1] - 0.01).abs() < 1e-9);
}

fn trajectory(seed: u64) -> Vec<u32> {
    let mut env = BallPlate::new(BallPlateConfig::default()).unwrap();
    env.reset(seed);
    let mut bits = Vec::new();
    let (mut f, mut s) = ([0f32; FAST_DIM], [0f32; SLOW_DIM]);
    let mut act = Rng::new(seed ^ 99);
    for _ in 0..300 {
        env.observe(&mut f, &mut s);
        bits.extend(f.iter().chain(s.iter()).map(|v| v.to_bits()));
        // A weak stabilising feedback so that the ball stays on the plate for a while.
        let a = [
            -1.5 * s[0] + 0.01 * act.normal(),
            -1.5 * s[1] + 0.01 * act.normal(),
        ];
        if env.step(&a).done {
            break;
        }
    }
    bits
}

#[test]
fn same_seed_same_bits() {
    assert_eq!(trajectory(5), trajectory(5));
    assert_ne!(trajectory(5), trajectory(6));
}

#[test]
fn observing_does_not_change_physics() {
    let mut a = BallPlate::new(BallPlateConfig::default()).unwrap();
    let mut b = a.clone();
    a.reset(3);
    b.reset(3);
    let (mut f, mut s) = ([0f32; FAST_DIM], [0f32; SLOW_DIM]);
    for k in 0..100 {
        if k % 3 == 0 {
            a.observe(&mut f, &mut s);
        }
        a.step(&[0.01, -0.01]);
        b.step(&[0.01, -0.01]);
    }
    assert_eq!(a.state(), b.state());
}

#[test]
fn pushes_are_poisson_in_window() {
    let cfg = BallPlateConfig::default();
    let mut env = BallPlate::new(cfg.clone()).unwrap();
    let n = 2000;
    let mut count = 0usize;
    for seed in 0..n {
        env.reset(seed);
        for p in env.pushes() {
            assert!(p.t >= cfg.push_start && p.t < cfg.push_end);
            let speed = p.dv[0].hypot(p.dv[1]);
            assert!(speed >= cfg.push_min - 1e-12 && speed <= cfg.push_max + 1e-12);
        }
        count += env.pushes().len();
    }
    // Expected 0.6 · 7.5 = 4.5 pushes per episode; σ of the mean ≈ √(4.5/2000) ≈ 0.047.
    let mean = count as f64 / n as f64;
    assert!((mean - 4.5).abs() < 0.25, "mean pushes per episode {mean}");
}

#[test]
fn pushes_change_ball_velocity() {
    let mut env = BallPlate::new(BallPlateConfig {
        ball_friction: 0.0,
        bound: 100.0,
        ..Default::default()
    })
    .unwrap();
    env.freeze = Freeze::Plate;
    env.reset(11);
    env.set_state(BallPlateState::default());
    let total: [f64; 2] = env
        .pushes()
        .iter()
        .fold([0.0, 0.0], |a, p| [a[0] + p.dv[0], a[1] + p.dv[1]]);
    assert!(!env.pushes().is_empty());
    for _ in 0..env.config().max_steps() {
        env.step(&[0.0, 0.0]);
    }
    for i in 0..2 {
        assert!((env.state().vel[i] - total[i]).abs() < 1e-12);
    }
}

#[test]
fn leaving_the_plate_fails_at_once() {
    let mut env = BallPlate::new(quiet()).unwrap();
    env.reset(1);
    let mut steps = 0;
    loop {
        steps += 1;
        let r = env.step(&[0.15, 0.0]);
        if r.done {
            assert!(!r.success);
            assert!(env.left_bound());
            break;
        }
        assert!(
            steps < env.config().max_steps(),
            "should have left the plate"
        );
    }
    assert!(steps < 100);
    // Further steps keep reporting the end.
    let again = env.step(&[0.0, 0.0]);
    assert!(again.done && !again.success);
}

#[test]
fn final_distance_decides_success() {
    for (pos, ok) in [([0.03, 0.03], true), ([0.04, 0.04], false)] {
        let mut env = BallPlate::new(quiet()).unwrap();
        env.freeze = Freeze::Ball;
        env.reset(0);
        env.set_state(BallPlateState {
            pos,
            ..Default::default()
        });
        let mut last = EnvStep::default();
        for k in 0..env.config().max_steps() {
            assert!(!last.done, "ended early at {k}");
            last = env.step(&[0.0, 0.0]);
        }
        assert!(last.done);
        assert_eq!(last.success, ok, "pos {pos:?}");
    }
}
