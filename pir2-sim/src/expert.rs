//! Experts that produce demonstrations: a discrete LQR for the ball-on-plate task.
//!
//! # The LQR
//!
//! Per axis the state is `s = (p, v, θ, ω)` and the input is the tilt target `u = r`.
//! Linearising `sin θ ≈ θ` in the dynamics of [`crate::ballplate`], one semi-implicit Euler
//! substep of length `dt` is the linear map
//!
//! ```text
//!   v' = v + dt·(a·θ − c·v)                     a = (5/7)·g
//!   ω' = ω + dt·(Kp·(u − θ) − Kd·ω + β·p)
//!   p' = p + dt·v'
//!   θ' = θ + dt·ω'
//! ```
//!
//! i.e. `s' = M·s + N·u`; the 50 Hz model is exactly the composition of the simulator's
//! substeps with the target held: `A = M^n`, `B = Σ_{k<n} M^k·N` (`n = 10`), so the servo is
//! part of the plant. The gain solves the discrete algebraic Riccati equation
//!
//! ```text
//!   P = Q + Aᵀ P A − Aᵀ P B (R + Bᵀ P B)⁻¹ Bᵀ P A,      K = (R + Bᵀ P B)⁻¹ Bᵀ P A
//! ```
//!
//! by fixed-point iteration from `P = Q` (with `faer` for the products and the solve), and
//! the control law is `r = −K·s`, clamped to the plate's range. For `Q = diag(400, 10, 0, 0)`
//! and `R = 1` the gain is `K ≈ [16.2, 4.21, 1.50, 0.028]` (positive: a ball at `+p` is sent
//! back by a negative tilt).
//!
//! The expert sees the true state with small Gaussian noise (σ 0.5 mm, 3 mm/s, 0.5 mrad,
//! 5 mrad/s) and can act on a state `delay` control ticks old (the latency study).

use std::collections::VecDeque;

use faer::prelude::*;
use faer::Mat;
use pir2_schedule::Rng;
use serde::{Deserialize, Serialize};

use crate::ballplate::{BallPlate, BallPlateConfig, ROLLING_FACTOR};
use crate::error::{Error, Result};

/// A policy with privileged access to an environment, used to record demonstrations.
pub trait Expert<E: ?Sized> {
    /// Start a new episode; the expert's own randomness derives from `seed`.
    fn reset(&mut self, seed: u64);
    /// Write the (clean) action for the environment's current state into `out`.
    fn act(&mut self, env: &E, out: &mut [f32]);
}

/// The linear 50 Hz model `s' = A·s + B·u` of one ball-on-plate axis (see the module docs).
pub fn discrete_axis_model(cfg: &BallPlateConfig) -> (Mat<f64>, Mat<f64>) {
    let dt = cfg.dt();
    let a = ROLLING_FACTOR * cfg.gravity;
    let (c, kp, kd, beta) = (
        cfg.ball_friction,
        cfg.servo_kp,
        cfg.servo_kd,
        cfg.load_coupling,
    );
    // Rows of the velocity update, then positions use the new velocities.
    let v_row = [0.0, 1.0 - dt * c, dt * a, 0.0];
    let w_row = [dt * beta, 0.0, -dt * kp, 1.0 - dt * kd];
    let (v_u, w_u) = (0.0, dt * kp);
    let m = Mat::from_fn(4, 4, |i, j| match i {
        0 => f64::from(j == 0) + dt * v_row[j],
        1 => v_row[j],
        2 => f64::from(j == 2) + dt * w_row[j],
        _ => w_row[j],
    });
    let n = Mat::from_fn(4, 1, |i, _| match i {
        0 => dt * v_u,
        1 => v_u,
        2 => dt * w_u,
        _ => w_u,
    });
    let mut a_d = Mat::<f64>::identity(4, 4);
    let mut b_d = Mat::<f64>::zeros(4, 1);
    for _ in 0..cfg.substeps {
        // (A, B) ← (M·A, M·B + N): apply one more substep after the ones so far.
        b_d = &m * &b_d + &n;
        a_d = &m * &a_d;
    }
    (a_d, b_d)
}

/// Solve the discrete algebraic Riccati equation by fixed-point iteration and return the
/// gain `K` (`m × n`) of `u = −K·x`, together with `P`.
pub fn dlqr(
    a: &Mat<f64>,
    b: &Mat<f64>,
    q: &Mat<f64>,
    r: &Mat<f64>,
) -> Result<(Mat<f64>, Mat<f64>)> {
    const MAX_ITERS: usize = 200_000;
    let mut p = q.clone();
    let mut change = f64::INFINITY;
    for _ in 0..MAX_ITERS {
        let pa = &p * a;
        let pb = &p * b;
        let s = r + b.transpose() * &pb; // R + BᵀPB
        let bt_pa = b.transpose() * &pa; // BᵀPA
        let k = s.partial_piv_lu().solve(&bt_pa); // (R + BᵀPB)⁻¹ BᵀPA
        let next = q + a.transpose() * &pa - (a.transpose() * &pb) * &k;
        // Symmetrise against round-off drift.
        let next = Mat::from_fn(next.nrows(), next.ncols(), |i, j| {
            0.5 * (next[(i, j)] + next[(j, i)])
        });
        let diff = (&next - &p).norm_max();
        change = diff / next.norm_max().max(1e-300);
        p = next;
        if !change.is_finite() {
            break;
        }
        if change < 1e-13 {
            let pb = &p * b;
            let s = r + b.transpose() * &pb;
            let k = s.partial_piv_lu().solve(b.transpose() * (&p * a));
            return Ok((k, p));
        }
    }
    Err(Error::Riccati {
        iterations: MAX_ITERS,
        change,
    })
}

/// Configuration of the ball-on-plate LQR expert (defaults = the findings).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LqrConfig {
    /// State weights `diag(Q)` on `(p, v, θ, ω)`.
    pub q: [f64; 4],
    /// Input weight `R`.
    pub r: f64,
    /// σ of the noise on the state the expert sees: `(p, v, θ, ω)`.
    pub noise: [f64; 4],
    /// The expert acts on the state this many control ticks old (0 = current).
    pub delay: usize,
}

impl Default for LqrConfig {
    fn default() -> Self {
        Self {
            q: [400.0, 10.0, 0.0, 0.0],
            r: 1.0,
            noise: [5e-4, 3e-3, 5e-4, 5e-3],
            delay: 0,
        }
    }
}

/// The LQR gain `K` (row of 4) of one ball-on-plate axis.
pub fn ballplate_gain(task: &BallPlateConfig, q: [f64; 4], r: f64) -> Result<[f64; 4]> {
    let (a, b) = discrete_axis_model(task);
    let qm = Mat::from_fn(4, 4, |i, j| if i == j { q[i] } else { 0.0 });
    let rm = Mat::from_fn(1, 1, |_, _| r);
    let (k, _) = dlqr(&a, &b, &qm, &rm)?;
    Ok([k[(0, 0)], k[(0, 1)], k[(0, 2)], k[(0, 3)]])
}

/// The LQR expert of the ball-on-plate task: `r_i = −K·ŝ_i` per axis on a noisy,
/// optionally delayed state, clamped to the plate's range.
#[derive(Debug, Clone)]
pub struct LqrExpert {
    cfg: LqrConfig,
    gain: [f64; 4],
    max_target: f64,
    rng: Rng,
    /// Noisy states seen so far, newest last (at most `delay + 1`).
    history: VecDeque<[[f64; 4]; 2]>,
}

impl LqrExpert {
    /// Build the expert for a task configuration (solves the Riccati equation once).
    pub fn new(task: &BallPlateConfig, cfg: LqrConfig) -> Result<Self> {
        let gain = ballplate_gain(task, cfg.q, cfg.r)?;
        let history = VecDeque::with_capacity(cfg.delay + 1);
        Ok(Self {
            cfg,
            gain,
            max_target: task.max_target,
            rng: Rng::new(0),
            history,
        })
    }

    /// The gain `K` (shared by both axes).
    pub fn gain(&self) -> [f64; 4] {
        self.gain
    }

    /// The configuration.
    pub fn config(&self) -> &LqrConfig {
        &self.cfg
    }

    /// Change the latency (ticks) for the following episodes.
    pub fn set_delay(&mut self, delay: usize) {
        self.cfg.delay = delay;
        self.history.clear();
    }

    /// The control law on a given per-axis state (no noise, no delay), clamped.
    pub fn law(&self, s: [f64; 4]) -> f64 {
        let u: f64 = -(0..4).map(|j| self.gain[j] * s[j]).sum::<f64>();
        u.clamp(-self.max_target, self.max_target)
    }
}

impl Expert<BallPlate> for LqrExpert {
    fn reset(&mut self, seed: u64) {
        self.rng = Rng::derive(seed, 2);
        self.history.clear();
    }

    fn act(&mut self, env: &BallPlate, out: &mut [f32]) {
        let st = env.state();
        let mut seen = [[0.0; 4]; 2];
        for (i, s) in seen.iter_mut().enumerate() {
            let x = st.axis(i);
            for j in 0..4 {
                s[j] = x[j] + self.cfg.noise[j] * self.rng.normal() as f64;
            }
        }
        if self.history.len() > self.cfg.delay {
            self.history.pop_front();
        }
        self.history.push_back(seen);
        // The oldest entry is `delay` ticks old once the history is full; before that, the
        // first state of the episode stands in.
        let used = self.history[0];
        for i in 0..2 {
            out[i] = self.law(used[i]) as f32;
        }
    }
}

/// Result of running a policy over many episodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SuccessRate {
    /// Episodes run.
    pub episodes: usize,
    /// Episodes that ended in success.
    pub successes: usize,
}

impl SuccessRate {
    /// Fraction of successful episodes.
    pub fn rate(&self) -> f64 {
        self.successes as f64 / self.episodes.max(1) as f64
    }
}

/// Run an expert (executing its actions as they are) on `episodes` episodes with seeds
/// `seed0, seed0 + 1, …` and count successes.
pub fn evaluate_expert<E, X>(
    env: &mut E,
    expert: &mut X,
    episodes: usize,
    seed0: u64,
) -> SuccessRate
where
    E: pir2_runtime::Environment,
    X: Expert<E>,
{
    let spec = env.spec();
    let mut action = vec![0f32; spec.action_dim];
    let mut successes = 0;
    for e in 0..episodes as u64 {
        env.reset(seed0 + e);
        expert.reset(seed0 + e);
        for _ in 0..spec.max_steps {
            expert.act(env, &mut action);
            let r = env.step(&action);
            if r.done {
                successes += usize::from(r.success);
                break;
            }
        }
    }
    SuccessRate {
        episodes,
        successes,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pir2_runtime::Environment;

    #[test]
    fn gain_matches_findings() {
        let k = ballplate_gain(&BallPlateConfig::default(), [400.0, 10.0, 0.0, 0.0], 1.0).unwrap();
        let expect = [16.2, 4.21, 1.50, 0.028];
        for j in 0..4 {
            let rel = (k[j] - expect[j]).abs() / expect[j];
            assert!(rel < 0.03, "K = {k:?}, expected ≈ {expect:?}");
        }
    }

    #[test]
    fn riccati_solution_is_a_fixed_point_and_stabilises() {
        let cfg = BallPlateConfig::default();
        let (a, b) = discrete_axis_model(&cfg);
        let q = Mat::from_fn(4, 4, |i, j| {
            if i == j {
                [400.0, 10.0, 0.0, 0.0][i]
            } else {
                0.0
            }
        });
        let r = Mat::from_fn(1, 1, |_, _| 1.0);
        let (k, p) = dlqr(&a, &b, &q, &r).unwrap();
        let s = &r + b.transpose() * &p * &b;
        let k2 = s.partial_piv_lu().solve(b.transpose() * &p * &a);
        let resid = &q + a.transpose() * &p * &a - a.transpose() * &p * &b * &k2 - &p;
        assert!(
            resid.norm_max() < 1e-8 * p.norm_max(),
            "residual {}",
            resid.norm_max()
        );
        // Closed loop A − BK is stable: iterate and watch the state decay.
        let acl = &a - &b * &k;
        let mut x = Mat::from_fn(4, 1, |i, _| [0.05, 0.1, 0.02, 0.3][i]);
        for _ in 0..500 {
            x = &acl * &x;
        }
        assert!(
            x.norm_max() < 1e-6,
            "closed loop did not decay: {}",
            x.norm_max()
        );
    }

    #[test]
    fn discrete_model_matches_simulator_for_small_motions() {
        // With sin θ ≈ θ the simulator's control step is the linear model.
        let cfg = BallPlateConfig {
            push_rate: 0.0,
            ..Default::default()
        };
        let (a, b) = discrete_axis_model(&cfg);
        let mut env = BallPlate::new(cfg).unwrap();
        let s0 = crate::ballplate::BallPlateState {
            pos: [0.01, 0.0],
            vel: [-0.02, 0.0],
            tilt: [1e-3, 0.0],
            tilt_rate: [0.01, 0.0],
            target: [0.0; 2],
        };
        env.set_state(s0);
        env.step(&[2e-3, 0.0]);
        let x0 = s0.axis(0);
        let pred: Vec<f64> = (0..4)
            .map(|i| (0..4).map(|j| a[(i, j)] * x0[j]).sum::<f64>() + b[(i, 0)] * 2e-3)
            .collect();
        let got = env.state().axis(0);
        for i in 0..4 {
            assert!(
                (pred[i] - got[i]).abs() < 1e-8 * (1.0 + got[i].abs()),
                "{i}: {} vs {}",
                pred[i],
                got[i]
            );
        }
    }

    #[test]
    fn expert_stabilises_most_episodes() {
        let cfg = BallPlateConfig::default();
        let mut env = BallPlate::new(cfg.clone()).unwrap();
        let mut expert = LqrExpert::new(&cfg, LqrConfig::default()).unwrap();
        let r = evaluate_expert(&mut env, &mut expert, 40, 1000);
        assert!(r.rate() >= 0.85, "expert success {}", r.rate());
    }

    #[test]
    fn large_latency_breaks_the_expert() {
        let cfg = BallPlateConfig::default();
        let mut env = BallPlate::new(cfg.clone()).unwrap();
        let mut expert = LqrExpert::new(
            &cfg,
            LqrConfig {
                delay: 8,
                ..Default::default()
            },
        )
        .unwrap();
        let r = evaluate_expert(&mut env, &mut expert, 20, 1000);
        assert!(r.rate() <= 0.2, "delay-8 expert success {}", r.rate());
    }

    #[test]
    fn delay_uses_old_states() {
        let cfg = BallPlateConfig {
            push_rate: 0.0,
            ..Default::default()
        };
        let mut env = BallPlate::new(cfg.clone()).unwrap();
        let zero_noise = LqrConfig {
            noise: [0.0; 4],
            delay: 2,
            ..Default::default()
        };
        let mut delayed = LqrExpert::new(&cfg, zero_noise.clone()).unwrap();
        let fresh = LqrExpert::new(
            &cfg,
            LqrConfig {
                delay: 0,
                ..zero_noise
            },
        )
        .unwrap();
        env.reset(4);
        delayed.reset(4);
        let mut states = Vec::new();
        let mut out = [0f32; 2];
        for t in 0..10 {
            states.push(*env.state());
            delayed.act(&env, &mut out);
            let old = states[t.max(2) - 2];
            assert_eq!(out[0], fresh.law(old.axis(0)) as f32, "tick {t}");
            env.step(&out);
        }
    }

    #[test]
    fn expert_is_deterministic() {
        let cfg = BallPlateConfig::default();
        let run = || {
            let mut env = BallPlate::new(cfg.clone()).unwrap();
            let mut ex = LqrExpert::new(&cfg, LqrConfig::default()).unwrap();
            env.reset(9);
            ex.reset(9);
            let mut out = [0f32; 2];
            let mut bits = Vec::new();
            for _ in 0..100 {
                ex.act(&env, &mut out);
                bits.push((out[0].to_bits(), out[1].to_bits()));
                env.step(&out);
            }
            bits
        };
        assert_eq!(run(), run());
    }
}
