//! The cube-reorientation environment ([`pir2_runtime::Environment`]).
//!
//! Two configurations ([`LeapConfig::playground`], [`LeapConfig::paper`]):
//!
//! | | playground (parity) | paper |
//! |---|---|---|
//! | control rate | 20 Hz (5 substeps of 10 ms) | 50 Hz (2 substeps) |
//! | goal | one uniform random orientation, re-drawn (drifted) after each success | any of the four blue-side-up yaws |
//! | episode | 1000 steps; ends early only on a drop | 600 steps; ends at the first success (error < 0.2 rad) or a drop |
//! | `observe` | `fast` = the 57-d policy state, `slow` = empty | `fast` = 32, `slow` = 9 |
//!
//! Observation layout (all noisy, drawn afresh at every [`observe`](Environment::observe)):
//! * `[0..16)` joint angles + U(±0.05) rad (actuator order),
//! * `[16..32)` those noisy angles minus the current motor targets,
//! * then `palm − cube position` (cube position + U(±0.02) m, 3),
//! * then rows 2–3 of a rotation matrix (6): of `q_cube ⊗ q_goal⁻¹` (playground) or of
//!   `q_cube` itself (paper), with `q_cube` + N(0, 0.1) per component, renormalised,
//! * playground only: the action of the previous control step (16) — as in the playground,
//!   where the observation is built before `last_act` is updated.
//!
//! In the paper configuration `fast` holds the first 32 values and `slow` the 9 cube values.
//! The cube pose is read from the sensors, which MuJoCo evaluates at the start of the last
//! substep (as the playground does); joint angles are read from `qpos`.
//!
//! Action: `a ∈ [−1, 1]^16` (clamped), motor target ← clip(target + 0.5·a, ctrlrange), held
//! for all substeps. Reward: the playground's shaped reward (see [`LeapCubeEnv::step`]),
//! informational. Differences from the playground: `reset` runs `mj_forward` so the first
//! observation sees valid sensors (MJX's reset state has zero sensor data), and the
//! perturbation machinery (disabled in the playground's default config) is absent.

use std::sync::Arc;

use mujoco_rs::prelude::*;
use pir2_runtime::io::EnvSpec;
use pir2_runtime::{EnvStep, Environment};
use pir2_schedule::Rng;

use super::math::{self, Quat};
use super::model::{LeapModel, NU};
use crate::error::{Error, Result};

/// Which task definition.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Variant {
    /// MuJoCo Playground's LeapCubeReorient (random goal, 57-d observation).
    Playground,
    /// The paper's variant: four blue-side-up yaw goals, 41-d observation split 32 / 9.
    BlueSideUp,
}

/// Sensing noise magnitudes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseConfig {
    /// Half-width of the uniform joint-angle noise (rad).
    pub joint_pos: f64,
    /// Half-width of the uniform cube-position noise (m).
    pub cube_pos: f64,
    /// Standard deviation of the Gaussian added to each quaternion component.
    pub cube_ori: f64,
}

impl NoiseConfig {
    /// The playground's (and the paper's) noise: 0.05 rad, 0.02 m, 0.1.
    pub const DEFAULT: Self = Self {
        joint_pos: 0.05,
        cube_pos: 0.02,
        cube_ori: 0.1,
    };
    /// No noise (for experts and tests).
    pub const NONE: Self = Self {
        joint_pos: 0.0,
        cube_pos: 0.0,
        cube_ori: 0.0,
    };
}

/// Configuration of [`LeapCubeEnv`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LeapConfig {
    /// Task definition.
    pub variant: Variant,
    /// Control period (s); a multiple of the model's 10 ms time step.
    pub ctrl_dt: f64,
    /// Scale from action to motor-target increment (rad).
    pub action_scale: f64,
    /// Episode length in control steps.
    pub max_steps: usize,
    /// Orientation error counted as success (rad).
    pub success_threshold: f64,
    /// Sensing noise.
    pub noise: NoiseConfig,
}

impl LeapConfig {
    /// MuJoCo Playground's LeapCubeReorient defaults (20 Hz, 1000 steps, 0.1 rad).
    pub fn playground() -> Self {
        Self {
            variant: Variant::Playground,
            ctrl_dt: 0.05,
            action_scale: 0.5,
            max_steps: 1000,
            success_threshold: 0.1,
            noise: NoiseConfig::DEFAULT,
        }
    }

    /// The paper's variant (50 Hz, 600 steps, 0.2 rad, four blue-side-up goals).
    pub fn paper() -> Self {
        Self {
            variant: Variant::BlueSideUp,
            ctrl_dt: 0.02,
            action_scale: 0.5,
            max_steps: 600,
            success_threshold: 0.2,
            noise: NoiseConfig::DEFAULT,
        }
    }

    /// `(fast, slow)` observation dimensions.
    pub fn obs_dims(&self) -> (usize, usize) {
        match self.variant {
            Variant::Playground => (57, 0),
            Variant::BlueSideUp => (32, 9),
        }
    }
}

/// Reward scales of the playground (`reward_config.scales`).
mod reward {
    pub const ORIENTATION: f64 = 5.0;
    pub const POSITION: f64 = 0.5;
    pub const TERMINATION: f64 = -100.0;
    pub const HAND_POSE: f64 = -0.5;
    pub const ACTION_RATE: f64 = -0.001;
    pub const ENERGY: f64 = -1e-3;
    pub const SUCCESS: f64 = 100.0;
}

/// dm_control's `tolerance(x, (0, hi), margin, sigmoid="linear")` with value 0.1 at margin.
pub(crate) fn tolerance_linear(x: f64, hi: f64, margin: f64) -> f64 {
    if x <= hi {
        1.0
    } else {
        (1.0 - 0.9 * (x - hi) / margin).max(0.0)
    }
}

/// MuJoCo's full integration state (what [`LeapCubeEnv::save`] keeps of the physics).
const STATE_SPEC: u32 = MjtState::mjSTATE_INTEGRATION as u32;

/// A saved [`LeapCubeEnv`] state (see [`LeapCubeEnv::save`]).
#[derive(Debug, Clone)]
pub struct LeapEnvState {
    physics: Vec<f64>,
    sensors: Vec<f64>,
    rng: Rng,
    targets: [f64; NU],
    last_act: [f32; NU],
    last_last_act: [f32; NU],
    goal: Quat,
    goal_dquat: [f64; 3],
    goals: Vec<Quat>,
    steps: usize,
    successes: usize,
    ended: Option<EnvStep>,
}

/// The LEAP hand holding a cube, as a lock-step [`Environment`].
#[derive(Debug)]
pub struct LeapCubeEnv {
    cfg: LeapConfig,
    lm: LeapModel,
    data: MjData<Arc<MjModel>>,
    n_sub: usize,
    rng: Rng,
    targets: [f64; NU],
    last_act: [f32; NU],
    last_last_act: [f32; NU],
    goal: Quat,
    goal_dquat: [f64; 3],
    goals: Vec<Quat>,
    steps: usize,
    successes: usize,
    ended: Option<EnvStep>,
}

impl LeapCubeEnv {
    /// A new environment on `model` (call [`reset`](Environment::reset) before use).
    pub fn new(model: &LeapModel, cfg: LeapConfig) -> Result<Self> {
        let ratio = cfg.ctrl_dt / model.timestep();
        let n_sub = ratio.round() as usize;
        if n_sub == 0 || (ratio - n_sub as f64).abs() > 1e-6 {
            return Err(Error::LeapInvalid(format!(
                "ctrl_dt {} is not a positive multiple of the time step {}",
                cfg.ctrl_dt,
                model.timestep()
            )));
        }
        let mut env = Self {
            cfg,
            lm: model.clone(),
            data: model.make_data(),
            n_sub,
            rng: Rng::new(0),
            targets: model.home,
            last_act: [0.0; NU],
            last_last_act: [0.0; NU],
            goal: math::blue_side_up_goals()[0],
            goal_dquat: [0.0; 3],
            goals: math::blue_side_up_goals().to_vec(),
            steps: 0,
            successes: 0,
            ended: None,
        };
        env.reset(0);
        Ok(env)
    }

    /// Load the scene from `$PIR2_LEAP_CUBE_DIR` and build the paper's variant.
    pub fn paper() -> Result<Self> {
        Self::new(&LeapModel::load(None)?, LeapConfig::paper())
    }

    /// The configuration.
    pub fn config(&self) -> &LeapConfig {
        &self.cfg
    }

    /// The shared model.
    pub fn model(&self) -> &LeapModel {
        &self.lm
    }

    /// The simulation state (privileged; for experts and tests).
    pub fn data(&self) -> &MjData<Arc<MjModel>> {
        &self.data
    }

    /// Physics substeps per control step.
    pub fn substeps(&self) -> usize {
        self.n_sub
    }

    /// Current motor targets (actuator order).
    pub fn motor_targets(&self) -> &[f64; NU] {
        &self.targets
    }

    /// The goal orientations that count: the four blue-side-up yaws (paper) or the current
    /// goal (playground).
    pub fn goals(&self) -> &[Quat] {
        &self.goals
    }

    /// Control steps taken in this episode.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// True cube position `(x, y, z)` and orientation `(w, x, y, z)` from `qpos`.
    pub fn cube_pose(&self) -> ([f64; 3], Quat) {
        let q = &self.data.qpos()[self.lm.cube_qadr..self.lm.cube_qadr + 7];
        ([q[0], q[1], q[2]], [q[3], q[4], q[5], q[6]])
    }

    /// True hand joint angles (actuator order).
    pub fn hand_q(&self) -> [f64; NU] {
        let qpos = self.data.qpos();
        std::array::from_fn(|i| qpos[self.lm.hand_qadr[i]])
    }

    /// Orientation error of the (sensed, noise-free) cube to the nearest goal (rad).
    pub fn orientation_error(&self) -> f64 {
        math::nearest_goal_error(&self.sensed_cube_quat(), &self.goals)
    }

    /// Save the whole environment state: physics (MuJoCo's integration state and the sensor
    /// values the next [`observe`](Environment::observe) reads), motor targets, noise RNG,
    /// episode counters. [`restore`](Self::restore) continues bit-identically from it, so a
    /// caller can branch an episode (e.g. to ask what another expert seed would have done).
    pub fn save(&self) -> LeapEnvState {
        let mut physics = vec![0.0; self.lm.model.state_size(STATE_SPEC)];
        self.data.read_state_into(STATE_SPEC, &mut physics);
        LeapEnvState {
            physics,
            sensors: self.data.sensordata().to_vec(),
            rng: self.rng.clone(),
            targets: self.targets,
            last_act: self.last_act,
            last_last_act: self.last_last_act,
            goal: self.goal,
            goal_dquat: self.goal_dquat,
            goals: self.goals.clone(),
            steps: self.steps,
            successes: self.successes,
            ended: self.ended,
        }
    }

    /// Return to a state taken with [`save`](Self::save) from an environment on the same
    /// model.
    pub fn restore(&mut self, s: &LeapEnvState) -> Result<()> {
        self.data
            .set_state(&s.physics, STATE_SPEC)
            .map_err(|e| Error::LeapInvalid(format!("restoring a saved state: {e:?}")))?;
        let n = self.data.sensordata().len();
        if s.sensors.len() != n {
            return Err(Error::LeapInvalid(format!(
                "restoring a saved state: {} sensor values, the model has {n}",
                s.sensors.len()
            )));
        }
        self.data.sensordata_mut().copy_from_slice(&s.sensors);
        self.rng = s.rng.clone();
        self.targets = s.targets;
        self.last_act = s.last_act;
        self.last_last_act = s.last_last_act;
        self.goal = s.goal;
        self.goal_dquat = s.goal_dquat;
        self.goals.clone_from(&s.goals);
        self.steps = s.steps;
        self.successes = s.successes;
        self.ended = s.ended;
        Ok(())
    }

    /// Place the cube (position, quaternion) at rest and recompute the sensors. For tests
    /// and demonstrations; it does not advance the step counter.
    pub fn set_cube_pose(&mut self, pos: [f64; 3], quat: Quat) {
        let (qa, da) = (self.lm.cube_qadr, self.lm.cube_dadr);
        let qpos = self.data.qpos_mut();
        qpos[qa..qa + 3].copy_from_slice(&pos);
        qpos[qa + 3..qa + 7].copy_from_slice(&quat);
        self.data.qvel_mut()[da..da + 6].fill(0.0);
        self.data.forward();
    }

    fn sensed_cube_pos(&self) -> [f64; 3] {
        let s = &self.data.sensordata()[self.lm.sens_cube_pos..self.lm.sens_cube_pos + 3];
        [s[0], s[1], s[2]]
    }

    fn sensed_cube_quat(&self) -> Quat {
        let s = &self.data.sensordata()[self.lm.sens_cube_quat..self.lm.sens_cube_quat + 4];
        [s[0], s[1], s[2], s[3]]
    }

    fn palm_pos(&self) -> [f64; 3] {
        let s = &self.data.sensordata()[self.lm.sens_palm_pos..self.lm.sens_palm_pos + 3];
        [s[0], s[1], s[2]]
    }

    fn terminated(&self) -> bool {
        let z = self.sensed_cube_pos()[2];
        z < -0.05
            || !z.is_finite()
            || self.data.qpos().iter().any(|v| v.is_nan())
            || self.data.qvel().iter().any(|v| v.is_nan())
    }

    /// Write one noisy observation into `fast`/`slow`; see the module docs for the layout.
    fn write_obs(&mut self, fast: &mut [f32], slow: &mut [f32]) {
        let n = self.cfg.noise;
        let q = self.hand_q();
        for i in 0..NU {
            let noisy = q[i] + (2.0 * self.rng.uniform() as f64 - 1.0) * n.joint_pos;
            fast[i] = noisy as f32;
            fast[NU + i] = (noisy - self.targets[i]) as f32;
        }
        let cp = self.sensed_cube_pos();
        let cq = self.sensed_cube_quat();
        let mut noisy_pos = [0.0; 3];
        for k in 0..3 {
            noisy_pos[k] = cp[k] + (2.0 * self.rng.uniform() as f64 - 1.0) * n.cube_pos;
        }
        let mut nq = [0.0; 4];
        for k in 0..4 {
            nq[k] = cq[k] + self.rng.normal() as f64 * n.cube_ori;
        }
        let norm = nq.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-12);
        nq.iter_mut().for_each(|v| *v /= norm);
        let palm = self.palm_pos();
        let cube: &mut [f32] = match self.cfg.variant {
            Variant::Playground => &mut fast[32..41],
            Variant::BlueSideUp => &mut slow[0..9],
        };
        for k in 0..3 {
            cube[k] = (palm[k] - noisy_pos[k]) as f32;
        }
        let rows = match self.cfg.variant {
            Variant::Playground => math::rot_rows_23(&math::mul_inv(&nq, &self.goal)),
            Variant::BlueSideUp => math::rot_rows_23(&nq),
        };
        for k in 0..6 {
            cube[3 + k] = rows[k] as f32;
        }
        if self.cfg.variant == Variant::Playground {
            fast[41..57].copy_from_slice(&self.last_last_act);
        }
    }

    fn reward(&self, action: &[f32; NU], err: f64, terminated: bool, success: bool) -> f64 {
        let cube = self.sensed_cube_pos();
        let palm = self.palm_pos();
        let dist = (0..3)
            .map(|k| (palm[k] - cube[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        let q = self.hand_q();
        let hand_pose: f64 = (0..NU).map(|i| (q[i] - self.lm.home[i]).powi(2)).sum();
        let mut rate = 0.0;
        for i in 0..NU {
            let (a, l, ll) = (
                action[i] as f64,
                self.last_act[i] as f64,
                self.last_last_act[i] as f64,
            );
            rate += (a - l).powi(2) + (a - 2.0 * l + ll).powi(2);
        }
        let qvel = self.data.qvel();
        let nu = NU.min(self.data.model().ffi().nu as usize);
        // SAFETY: `actuator_force` is an array of `nu` doubles owned by `self.data`, which
        // lives (and is not mutated) for the duration of this borrow.
        let force = unsafe { std::slice::from_raw_parts(self.data.ffi().actuator_force, nu) };
        let energy: f64 = (0..nu)
            .map(|i| qvel[self.lm.hand_dadr[i]].abs() * force[i].abs())
            .sum();
        let shaped = reward::ORIENTATION * tolerance_linear(err, 0.2, std::f64::consts::PI)
            + reward::POSITION * tolerance_linear(dist, 0.02, 0.05)
            + reward::TERMINATION * f64::from(u8::from(terminated))
            + reward::HAND_POSE * hand_pose
            + reward::ACTION_RATE * rate
            + reward::ENERGY * energy;
        shaped * self.cfg.ctrl_dt + if success { reward::SUCCESS } else { 0.0 }
    }
}

impl Environment for LeapCubeEnv {
    fn spec(&self) -> EnvSpec {
        let (fast_dim, slow_dim) = self.cfg.obs_dims();
        EnvSpec {
            fast_dim,
            slow_dim,
            action_dim: NU,
            control_period: (self.cfg.ctrl_dt * 1e9).round() as u64,
            max_steps: self.cfg.max_steps,
        }
    }

    /// Reset (the playground's distribution): hand = clip(home + 0.1·N(0,1), ctrlrange) at
    /// rest with motor targets equal to it; cube at (0.1, 0, 0.05) + U(±0.01) m with a
    /// uniformly random orientation; playground goal uniformly random. Draw order: goal
    /// (playground only), hand, cube position, cube orientation; then observation noise.
    fn reset(&mut self, seed: u64) {
        self.rng = Rng::new(seed);
        self.data.reset();
        self.goal = match self.cfg.variant {
            Variant::Playground => math::uniform_quat(&mut self.rng),
            Variant::BlueSideUp => math::blue_side_up_goals()[0],
        };
        self.goals = match self.cfg.variant {
            Variant::Playground => vec![self.goal],
            Variant::BlueSideUp => math::blue_side_up_goals().to_vec(),
        };
        let lm = &self.lm;
        let mut q = [0.0; NU];
        for i in 0..NU {
            q[i] = (lm.home[i] + 0.1 * self.rng.normal() as f64).clamp(lm.lo[i], lm.hi[i]);
        }
        let mut pos = [0.1, 0.0, 0.05];
        for p in &mut pos {
            *p += (2.0 * self.rng.uniform() as f64 - 1.0) * 0.01;
        }
        let quat = math::uniform_quat(&mut self.rng);
        let (hq, ca) = (lm.hand_qadr, lm.cube_qadr);
        let qpos = self.data.qpos_mut();
        for i in 0..NU {
            qpos[hq[i]] = q[i];
        }
        qpos[ca..ca + 3].copy_from_slice(&pos);
        qpos[ca + 3..ca + 7].copy_from_slice(&quat);
        self.data.qvel_mut().fill(0.0);
        self.data.ctrl_mut().copy_from_slice(&q);
        self.data.mocap_pos_mut()[0] = self.lm.home_mpos;
        self.data.mocap_quat_mut()[0] = self.goal;
        self.data.forward();
        self.targets = q;
        self.last_act = [0.0; NU];
        self.last_last_act = [0.0; NU];
        self.goal_dquat = [0.0; 3];
        self.steps = 0;
        self.successes = 0;
        self.ended = None;
    }

    /// Current noisy observation (see the module docs). Panics if a buffer has the wrong
    /// length (a wiring error, not a runtime condition).
    fn observe(&mut self, fast: &mut [f32], slow: &mut [f32]) {
        let (f, s) = self.cfg.obs_dims();
        assert_eq!(fast.len(), f, "LeapCubeEnv::observe: fast buffer length");
        assert_eq!(slow.len(), s, "LeapCubeEnv::observe: slow buffer length");
        self.write_obs(fast, slow);
    }

    /// One control step. Reward = `ctrl_dt · (5·tol(err; 0.2, π) + 0.5·tol(‖palm − cube‖;
    /// 0.02, 0.05) − 100·dropped − 0.5·Σ(q − home)² − 0.001·action rate − 0.001·energy) +
    /// 100·success` (the playground's terms; `err` is to the nearest goal in the paper
    /// variant). `success` in the returned [`EnvStep`]: paper — the episode ended within the
    /// threshold; playground — the goal was reached at least once. Stepping after `done`
    /// returns the final outcome again without simulating.
    fn step(&mut self, action: &[f32]) -> EnvStep {
        assert_eq!(action.len(), NU, "LeapCubeEnv::step: action length");
        if let Some(end) = self.ended {
            return end;
        }
        let mut a = [0.0f32; NU];
        for i in 0..NU {
            a[i] = if action[i].is_nan() {
                0.0
            } else {
                action[i].clamp(-1.0, 1.0)
            };
            self.targets[i] = (self.targets[i] + self.cfg.action_scale * a[i] as f64)
                .clamp(self.lm.lo[i], self.lm.hi[i]);
        }
        self.data.ctrl_mut().copy_from_slice(&self.targets);
        for _ in 0..self.n_sub {
            self.data.step();
        }
        self.steps += 1;
        let err = self.orientation_error();
        let hit = err < self.cfg.success_threshold;
        let terminated = self.terminated();
        let reward = self.reward(&a, err, terminated, hit) as f32;
        let timeout = self.steps >= self.cfg.max_steps;
        let out = match self.cfg.variant {
            Variant::Playground => {
                if hit {
                    self.successes += 1;
                    for d in &mut self.goal_dquat {
                        *d = 3.0 + (2.0 * self.rng.uniform() as f64 - 1.0) * 2.0;
                    }
                } else {
                    self.goal_dquat.iter_mut().for_each(|d| *d *= 0.8);
                }
                self.goal =
                    math::quat_integrate(&self.goal, &self.goal_dquat, 2.0 * self.cfg.ctrl_dt);
                self.goals[0] = self.goal;
                self.data.mocap_quat_mut()[0] = self.goal;
                EnvStep {
                    done: terminated || timeout,
                    success: self.successes > 0,
                    reward,
                }
            }
            Variant::BlueSideUp => {
                let success = hit && !terminated;
                EnvStep {
                    done: success || terminated || timeout,
                    success,
                    reward,
                }
            }
        };
        self.last_last_act = self.last_act;
        self.last_act = a;
        if out.done {
            self.ended = Some(out);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::tolerance_linear;

    #[test]
    fn tolerance_is_dm_control_linear_with_value_0_1_at_margin() {
        assert_eq!(tolerance_linear(0.0, 0.2, 1.0), 1.0);
        assert_eq!(tolerance_linear(0.2, 0.2, 1.0), 1.0);
        assert!((tolerance_linear(1.2, 0.2, 1.0) - 0.1).abs() < 1e-12);
        assert!((tolerance_linear(0.7, 0.2, 1.0) - 0.55).abs() < 1e-12);
        assert_eq!(tolerance_linear(5.0, 0.2, 1.0), 0.0);
    }
}
