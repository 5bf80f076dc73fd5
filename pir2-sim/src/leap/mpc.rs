//! The stock expert: sampling-based predictive control ("predictive sampling") over MuJoCo
//! rollouts with privileged state.
//!
//! A plan is a piecewise-linear spline of absolute motor targets with `knots` knots spread
//! over `horizon` control steps. Each replanning step evaluates `samples` plans — the
//! previous best, time-shifted (warm start), plus Gaussian perturbations of it (σ rad,
//! clipped to the control range) — by simulating each from the current state with exactly
//! the environment's actuation (targets move at most `action_scale` per step, as an action
//! in `[−1, 1]` allows), and keeps the cheapest. The action sent is
//! `a = clamp((u − target)/action_scale, −1, 1)` for the plan's target `u` now.
//!
//! Cost per control step, summed over the horizon:
//! * `w_orientation ·` orientation error to the nearest goal,
//! * `w_position · ‖cube − grasp site‖`,
//! * `w_disc · (e + 100·e²)` where `e` is how far the cube's horizontal distance from the
//!   grasp site exceeds `disc_radius` (keeps it from rolling off the palm),
//! * `w_drop` once the cube is 5 cm below the grasp site,
//! * `w_control · Σ Δtarget²`;
//!
//! plus `w_terminal ·` the orientation error at the end of the horizon.
//!
//! Rollouts run on `threads` scoped threads, one `MjData` each. Perturbations are drawn on
//! the calling thread from a seeded [`Rng`] and every rollout starts from a full copy of the
//! integration state, so the result does not depend on the thread count: same seed → same
//! actions.

use std::sync::Arc;

use mujoco_rs::prelude::*;
use pir2_schedule::Rng;

use super::env::LeapCubeEnv;
use super::math::{self, Quat};
use super::model::{LeapModel, NU};
use crate::error::{Error, Result};

const STATE_SPEC: u32 = MjtState::mjSTATE_INTEGRATION as u32;

/// Parameters of [`MpcExpert`] (defaults: the recipe that reached 94% on the paper variant).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MpcConfig {
    /// Plans evaluated per replanning step (the first is the warm-started nominal).
    pub samples: usize,
    /// Planning horizon in control steps.
    pub horizon: usize,
    /// Spline knots per plan (≥ 2).
    pub knots: usize,
    /// Standard deviation of the knot perturbations (rad).
    pub sigma: f64,
    /// Replan every this many control steps (1 = every step).
    pub replan_every: usize,
    /// Rollout threads (one `MjData` each).
    pub threads: usize,
    /// Weight of the orientation error per step.
    pub w_orientation: f64,
    /// Weight of the final orientation error.
    pub w_terminal: f64,
    /// Weight of the cube's distance to the grasp site (per m).
    pub w_position: f64,
    /// Radius of the disc around the grasp site the cube should stay in (m).
    pub disc_radius: f64,
    /// Weight of the (linear + quadratic) excess beyond the disc.
    pub w_disc: f64,
    /// Penalty per step once the cube is 5 cm below the grasp site.
    pub w_drop: f64,
    /// Weight of the squared motor-target change.
    pub w_control: f64,
    /// Keep the first knot (the target now) of every sampled plan at the nominal: only later
    /// knots are perturbed, so the executed targets move smoothly. With `false` the action
    /// sent carries the winning sample's fresh σ-perturbation of the target every replanning
    /// step, i.e. it is mostly sampling noise — fine for control, but a behaviour-cloning
    /// policy trained on such actions learns noise. Demonstrations are collected with `true`.
    pub pin_first_knot: bool,
}

impl Default for MpcConfig {
    fn default() -> Self {
        Self {
            samples: 32,
            horizon: 20,
            knots: 4,
            sigma: 0.3,
            replan_every: 1,
            threads: 2,
            w_orientation: 1.0,
            w_terminal: 3.0,
            w_position: 10.0,
            disc_radius: 0.03,
            w_disc: 100.0,
            w_drop: 20.0,
            w_control: 0.01,
            pin_first_knot: false,
        }
    }
}

impl MpcConfig {
    /// The cheaper recipe (16 samples, 0.3 s at 50 Hz, replan every 2 steps).
    pub fn fast() -> Self {
        Self {
            samples: 16,
            horizon: 15,
            replan_every: 2,
            ..Self::default()
        }
    }

    fn validate(&self) -> Result<()> {
        if self.samples == 0 || self.horizon == 0 || self.knots < 2 || self.replan_every == 0 {
            return Err(Error::LeapInvalid(format!(
                "MpcConfig needs samples ≥ 1, horizon ≥ 1, knots ≥ 2, replan_every ≥ 1: {self:?}"
            )));
        }
        Ok(())
    }
}

/// Sampling-based MPC expert for [`LeapCubeEnv`] (see the module docs).
#[derive(Debug)]
pub struct MpcExpert {
    cfg: MpcConfig,
    lm: LeapModel,
    workers: Vec<MjData<Arc<MjModel>>>,
    rng: Rng,
    state: Vec<f64>,
    nominal: Vec<f64>,
    shifted: Vec<f64>,
    plans: Vec<f64>,
    costs: Vec<f64>,
    elapsed: usize,
    planned: bool,
    rollout_steps: u64,
}

/// A saved plan state of an [`MpcExpert`] (see [`MpcExpert::snapshot`]).
#[derive(Debug, Clone)]
pub struct MpcSnapshot {
    nominal: Vec<f64>,
    elapsed: usize,
    planned: bool,
    rng: Rng,
}

/// Everything a rollout reads besides its plan.
struct Ctx<'a> {
    lm: &'a LeapModel,
    cfg: &'a MpcConfig,
    state: &'a [f64],
    targets: [f64; NU],
    goals: &'a [Quat],
    ctrl_dt: f64,
    scale: f64,
    n_sub: usize,
}

/// Linear spline through `knots` knots of `NU` values spread over `[0, span]`, at `t`.
fn eval(plan: &[f64], knots: usize, span: f64, t: f64, out: &mut [f64; NU]) {
    let h = span / (knots - 1) as f64;
    let s = (t / h).max(0.0);
    let j = (s.floor() as usize).min(knots - 2);
    let f = (s - j as f64).clamp(0.0, 1.0);
    let (a, b) = (
        &plan[j * NU..(j + 1) * NU],
        &plan[(j + 1) * NU..(j + 2) * NU],
    );
    for i in 0..NU {
        out[i] = a[i] + f * (b[i] - a[i]);
    }
}

fn rollout(data: &mut MjData<Arc<MjModel>>, plan: &[f64], cx: &Ctx<'_>) -> f64 {
    if data.set_state(cx.state, STATE_SPEC).is_err() {
        return f64::INFINITY;
    }
    let (lm, cfg) = (cx.lm, cx.cfg);
    let span = cfg.horizon as f64 * cx.ctrl_dt;
    let g = lm.grasp_pos;
    let mut targets = cx.targets;
    let mut u = [0.0; NU];
    let mut cost = 0.0;
    let mut err = 0.0;
    for k in 0..cfg.horizon {
        eval(plan, cfg.knots, span, k as f64 * cx.ctrl_dt, &mut u);
        let mut dctrl = 0.0;
        for i in 0..NU {
            let next = (targets[i] + (u[i] - targets[i]).clamp(-cx.scale, cx.scale))
                .clamp(lm.lo[i], lm.hi[i]);
            dctrl += (next - targets[i]).powi(2);
            targets[i] = next;
        }
        data.ctrl_mut().copy_from_slice(&targets);
        for _ in 0..cx.n_sub {
            data.step();
        }
        let q = &data.qpos()[lm.cube_qadr..lm.cube_qadr + 7];
        let (p, quat) = ([q[0], q[1], q[2]], [q[3], q[4], q[5], q[6]]);
        if !(p[2].is_finite() && quat[0].is_finite()) {
            return f64::INFINITY;
        }
        err = math::nearest_goal_error(&quat, cx.goals);
        let d = ((p[0] - g[0]).powi(2) + (p[1] - g[1]).powi(2) + (p[2] - g[2]).powi(2)).sqrt();
        let dxy = ((p[0] - g[0]).powi(2) + (p[1] - g[1]).powi(2)).sqrt();
        let excess = (dxy - cfg.disc_radius).max(0.0);
        cost += cfg.w_orientation * err
            + cfg.w_position * d
            + cfg.w_disc * (excess + 100.0 * excess * excess)
            + if p[2] < g[2] - 0.05 { cfg.w_drop } else { 0.0 }
            + cfg.w_control * dctrl;
    }
    cost + cfg.w_terminal * err
}

impl MpcExpert {
    /// A new expert for `model` with `cfg`, seeded with `seed`.
    pub fn new(model: &LeapModel, cfg: MpcConfig, seed: u64) -> Result<Self> {
        cfg.validate()?;
        let threads = cfg.threads.clamp(1, cfg.samples);
        let plan_len = cfg.knots * NU;
        Ok(Self {
            workers: (0..threads).map(|_| model.make_data()).collect(),
            lm: model.clone(),
            rng: Rng::new(seed),
            state: vec![0.0; model.model.state_size(STATE_SPEC)],
            nominal: vec![0.0; plan_len],
            shifted: vec![0.0; plan_len],
            plans: vec![0.0; cfg.samples * plan_len],
            costs: vec![0.0; cfg.samples],
            elapsed: 0,
            planned: false,
            rollout_steps: 0,
            cfg,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &MpcConfig {
        &self.cfg
    }

    /// Start a new episode: reseed and warm-start from the environment's motor targets.
    /// Call after [`Environment::reset`](pir2_runtime::Environment::reset).
    pub fn reset(&mut self, env: &LeapCubeEnv, seed: u64) {
        self.rng = Rng::new(seed);
        let t = env.motor_targets();
        for j in 0..self.cfg.knots {
            self.nominal[j * NU..(j + 1) * NU].copy_from_slice(t);
        }
        self.elapsed = 0;
        self.planned = false;
    }

    /// The expert's plan state (nominal plan, steps since the last replan, RNG): everything
    /// [`act`](Self::act) reads besides the environment. With [`restore`](Self::restore) it
    /// lets a caller ask "what would the expert have done from here with another seed"
    /// (the repeatability diagnosis) without disturbing the episode.
    pub fn snapshot(&self) -> MpcSnapshot {
        MpcSnapshot {
            nominal: self.nominal.clone(),
            elapsed: self.elapsed,
            planned: self.planned,
            rng: self.rng.clone(),
        }
    }

    /// Return to a state taken with [`snapshot`](Self::snapshot).
    pub fn restore(&mut self, s: &MpcSnapshot) {
        self.nominal.copy_from_slice(&s.nominal);
        self.elapsed = s.elapsed;
        self.planned = s.planned;
        self.rng = s.rng.clone();
    }

    /// Replace the sampling RNG (the plan state is kept).
    pub fn reseed(&mut self, seed: u64) {
        self.rng = Rng::new(seed);
    }

    /// Physics steps simulated in rollouts since construction.
    pub fn rollout_steps(&self) -> u64 {
        self.rollout_steps
    }

    /// The action for the environment's current state, in `[−1, 1]^16`.
    pub fn act(&mut self, env: &LeapCubeEnv) -> [f32; NU] {
        let ctrl_dt = env.config().ctrl_dt;
        let span = self.cfg.horizon as f64 * ctrl_dt;
        let k = self.cfg.knots;
        if !self.planned || self.elapsed >= self.cfg.replan_every {
            // Warm start: the nominal plan shifted by the steps executed since it was made.
            let mut shifted = std::mem::take(&mut self.shifted);
            let mut v = [0.0; NU];
            for j in 0..k {
                let t = j as f64 * span / (k - 1) as f64 + self.elapsed as f64 * ctrl_dt;
                eval(&self.nominal, k, span, t, &mut v);
                shifted[j * NU..(j + 1) * NU].copy_from_slice(&v);
            }
            self.plan(env, &shifted);
            self.shifted = shifted;
            self.elapsed = 0;
            self.planned = true;
        }
        let mut u = [0.0; NU];
        eval(
            &self.nominal,
            k,
            span,
            self.elapsed as f64 * ctrl_dt,
            &mut u,
        );
        self.elapsed += 1;
        let t = env.motor_targets();
        let scale = env.config().action_scale;
        std::array::from_fn(|i| ((u[i] - t[i]) / scale).clamp(-1.0, 1.0) as f32)
    }

    fn plan(&mut self, env: &LeapCubeEnv, nominal: &[f64]) {
        let plan_len = self.cfg.knots * NU;
        let (lo, hi) = (&self.lm.lo, &self.lm.hi);
        for (s, plan) in self.plans.chunks_mut(plan_len).enumerate() {
            plan.copy_from_slice(nominal);
            if s > 0 {
                let first = if self.cfg.pin_first_knot { NU } else { 0 };
                for (idx, v) in plan.iter_mut().enumerate().skip(first) {
                    let i = idx % NU;
                    *v = (*v + self.cfg.sigma * self.rng.normal() as f64).clamp(lo[i], hi[i]);
                }
            }
        }
        env.data().read_state_into(STATE_SPEC, &mut self.state);
        let cx = Ctx {
            lm: &self.lm,
            cfg: &self.cfg,
            state: &self.state,
            targets: *env.motor_targets(),
            goals: env.goals(),
            ctrl_dt: env.config().ctrl_dt,
            scale: env.config().action_scale,
            n_sub: env.substeps(),
        };
        let per = self.cfg.samples.div_ceil(self.workers.len());
        let plans = &self.plans;
        let costs = &mut self.costs;
        let mut jobs = self
            .workers
            .iter_mut()
            .zip(plans.chunks(per * plan_len).zip(costs.chunks_mut(per)));
        let run = |data: &mut MjData<Arc<MjModel>>, ps: &[f64], cs: &mut [f64]| {
            for (p, c) in ps.chunks(plan_len).zip(cs.iter_mut()) {
                *c = rollout(data, p, &cx);
            }
        };
        if let Some((d0, (p0, c0))) = jobs.next() {
            std::thread::scope(|sc| {
                for (d, (p, c)) in jobs {
                    sc.spawn(move || run(d, p, c));
                }
                run(d0, p0, c0);
            });
        }
        self.rollout_steps += (self.cfg.samples * self.cfg.horizon * env.substeps()) as u64;
        let best = (0..self.cfg.samples)
            .min_by(|&a, &b| self.costs[a].total_cmp(&self.costs[b]))
            .unwrap_or(0);
        self.nominal
            .copy_from_slice(&self.plans[best * plan_len..(best + 1) * plan_len]);
    }
}
