//! The paper's Leap-cube task as PPO sees it: the actor's (noisy) and the critic's
//! (privileged) observations, the reward decomposed into the playground's terms, and
//! episode bookkeeping (auto-reset, drop vs. time-limit).
//!
//! Actor observation ([`actor_dim`]): the paper's 41 values exactly as
//! [`LeapCubeEnv::observe`] writes them (`fast` 32, then `slow` 9), optionally followed by
//! the previous control step's action (16, clamped to `[−1, 1]`).
//!
//! Critic observation ([`CRITIC_DIM`] = actor observation + [`PRIVILEGED_DIM`]), all
//! noise-free, in this order:
//! * hand joint angles (16), hand joint velocities (16), joint angles − motor targets (16),
//! * grasp site − cube position (3), the cube's full rotation matrix, row-major (9),
//! * rows 2–3 of the rotation matrix of `q_cube ⊗ q_goal⁻¹` for the nearest goal (6), and
//!   the orientation error to it (rad, 1),
//! * cube linear and angular velocity (sensors `cube_linvel`, `cube_angvel`, 6),
//! * the four fingertip positions in the grasp-site frame (12),
//! * the previous action (16) and the elapsed fraction of the episode (1).
//!
//! Reward ([`RewardTerms`]): MuJoCo Playground's LeapCubeReorient shaping with the
//! orientation error taken to the nearest of the four blue-side-up goals — exactly what
//! [`LeapCubeEnv::step`] returns; this module recomputes the terms for logging and tests.

use mujoco_rs::prelude::*;
use nalgebra::UnitQuaternion;
use pir2_runtime::Environment;

use crate::error::Error;
use crate::leap::math::{self, Quat};
use crate::leap::{LeapConfig, LeapCubeEnv, LeapModel, NU};

use crate::error::Result;

/// The paper's observation width (fast 32 + slow 9).
pub const BASE_OBS_DIM: usize = 41;
/// Privileged values appended to the actor observation for the critic.
pub const PRIVILEGED_DIM: usize = 16 * 3 + 3 + 9 + 6 + 1 + 6 + 12 + NU + 1;

/// Actor observation width.
pub fn actor_dim(prev_action: bool) -> usize {
    BASE_OBS_DIM + if prev_action { NU } else { 0 }
}

/// Critic observation width.
pub fn critic_dim(prev_action: bool) -> usize {
    actor_dim(prev_action) + PRIVILEGED_DIM
}

/// The playground's reward scales (`reward_config.scales`) and success bonus.
pub mod scales {
    /// Orientation tolerance term.
    pub const ORIENTATION: f64 = 5.0;
    /// Position tolerance term.
    pub const POSITION: f64 = 0.5;
    /// Cube dropped (episode terminated).
    pub const TERMINATION: f64 = -100.0;
    /// Squared distance of the hand from its home pose.
    pub const HAND_POSE: f64 = -0.5;
    /// Action rate (first and second differences).
    pub const ACTION_RATE: f64 = -0.001;
    /// Mechanical power `Σ|q̇|·|τ|`.
    pub const ENERGY: f64 = -1e-3;
    /// Bonus on the step that reaches a goal (not multiplied by `ctrl_dt`).
    pub const SUCCESS: f64 = 100.0;
}

/// The unscaled reward terms of one step (see [`scales`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RewardTerms {
    /// `tol(err; 0.2, π)` with `err` to the nearest goal, in `[0, 1]`.
    pub orientation: f64,
    /// `tol(‖palm − cube‖; 0.02, 0.05)`, in `[0, 1]`.
    pub position: f64,
    /// 1 if the cube dropped (or the state became non-finite).
    pub termination: f64,
    /// `Σ (q − q_home)²`.
    pub hand_pose: f64,
    /// `Σ (a − a₋₁)² + (a − 2a₋₁ + a₋₂)²`.
    pub action_rate: f64,
    /// `Σ |q̇|·|τ_actuator|`.
    pub energy: f64,
    /// 1 on the step that succeeds.
    pub success: f64,
}

impl RewardTerms {
    /// `ctrl_dt · Σ scale·term + 100·success`.
    pub fn total(&self, ctrl_dt: f64) -> f64 {
        let shaped = scales::ORIENTATION * self.orientation
            + scales::POSITION * self.position
            + scales::TERMINATION * self.termination
            + scales::HAND_POSE * self.hand_pose
            + scales::ACTION_RATE * self.action_rate
            + scales::ENERGY * self.energy;
        shaped * ctrl_dt + scales::SUCCESS * self.success
    }

    /// Add `other` term by term (for episode sums).
    pub fn add(&mut self, other: &Self) {
        self.orientation += other.orientation;
        self.position += other.position;
        self.termination += other.termination;
        self.hand_pose += other.hand_pose;
        self.action_rate += other.action_rate;
        self.energy += other.energy;
        self.success += other.success;
    }
}

/// dm_control's `tolerance(x, (0, hi), margin, sigmoid="linear")` (0.1 at the margin).
pub fn tolerance_linear(x: f64, hi: f64, margin: f64) -> f64 {
    if x <= hi {
        1.0
    } else {
        (1.0 - 0.9 * (x - hi) / margin).max(0.0)
    }
}

/// Sensor addresses the critic reads beyond what [`LeapModel`] keeps.
#[derive(Debug, Clone, Copy)]
struct ExtraSensors {
    linvel: usize,
    angvel: usize,
    tips: [usize; 4],
}

impl ExtraSensors {
    fn find(model: &LeapModel) -> Result<Self> {
        let m: &MjModel = model.mj_model();
        let adr = |name: &str| -> Result<usize> {
            let id = m
                .name_to_id(MjtObjBase::mjOBJ_SENSOR, name)
                .ok_or_else(|| Error::MissingElement {
                    kind: "sensor",
                    name: name.to_string(),
                })?;
            Ok(m.sensor_adr()[id] as usize)
        };
        Ok(Self {
            linvel: adr("cube_linvel")?,
            angvel: adr("cube_angvel")?,
            tips: [
                adr("th_tip_position")?,
                adr("if_tip_position")?,
                adr("mf_tip_position")?,
                adr("rf_tip_position")?,
            ],
        })
    }
}

/// How a step ended the episode, if it did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ending {
    /// The episode goes on.
    Running,
    /// A goal was reached (terminal: no value after it).
    Success,
    /// The cube dropped or the state became non-finite (terminal).
    Dropped,
    /// The step limit was hit (not terminal: bootstrap with the value of the final state).
    TimeLimit,
}

/// Outcome of [`PpoEnv::step`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepOutcome {
    /// The environment's reward.
    pub reward: f32,
    /// The terms it is made of.
    pub terms: RewardTerms,
    /// Whether and how the episode ended.
    pub ending: Ending,
    /// Steps in the episode so far (including this one).
    pub steps: usize,
}

/// A [`LeapCubeEnv`] in the paper configuration plus the state PPO needs.
#[derive(Debug)]
pub struct PpoEnv {
    env: LeapCubeEnv,
    sens: ExtraSensors,
    prev_action: bool,
    last_act: [f32; NU],
    last_last_act: [f32; NU],
    fast: [f32; 32],
    slow: [f32; 9],
}

impl PpoEnv {
    /// A new environment (reset with seed 0) on `model` in configuration `cfg` (the paper's
    /// observation layout is required).
    pub fn new(model: &LeapModel, cfg: LeapConfig, prev_action: bool) -> Result<Self> {
        if cfg.obs_dims() != (32, 9) {
            return Err(Error::PpoInvalid(format!(
                "PPO needs the paper's 32 + 9 observation, got {:?}",
                cfg.obs_dims()
            )));
        }
        let mut out = Self {
            env: LeapCubeEnv::new(model, cfg)?,
            sens: ExtraSensors::find(model)?,
            prev_action,
            last_act: [0.0; NU],
            last_last_act: [0.0; NU],
            fast: [0.0; 32],
            slow: [0.0; 9],
        };
        out.reset(0);
        Ok(out)
    }

    /// The wrapped environment.
    pub fn env(&self) -> &LeapCubeEnv {
        &self.env
    }

    /// Reset the episode with `seed` and take the first observation.
    pub fn reset(&mut self, seed: u64) {
        self.env.reset(seed);
        self.last_act = [0.0; NU];
        self.last_last_act = [0.0; NU];
        self.env.observe(&mut self.fast, &mut self.slow);
    }

    /// The current noisy observation, `fast` (32) and `slow` (9), as the environment gave it.
    pub fn observation(&self) -> (&[f32; 32], &[f32; 9]) {
        (&self.fast, &self.slow)
    }

    /// Write the actor observation ([`actor_dim`] values).
    pub fn actor_obs(&self, out: &mut [f32]) {
        out[..32].copy_from_slice(&self.fast);
        out[32..41].copy_from_slice(&self.slow);
        if self.prev_action {
            out[41..41 + NU].copy_from_slice(&self.last_act);
        }
    }

    /// Write the critic observation ([`critic_dim`] values; layout in the module docs).
    pub fn critic_obs(&self, out: &mut [f32]) {
        let a = actor_dim(self.prev_action);
        self.actor_obs(&mut out[..a]);
        let env = &self.env;
        let lm = env.model();
        let data = env.data();
        let sd = data.sensordata();
        let qvel = data.qvel();
        let q = env.hand_q();
        let targets = env.motor_targets();
        let mut o = a;
        let mut put = |v: f64| {
            out[o] = v as f32;
            o += 1;
        };
        for i in 0..NU {
            put(q[i]);
        }
        for i in 0..NU {
            put(qvel[lm.hand_dadr[i]]);
        }
        for i in 0..NU {
            put(q[i] - targets[i]);
        }
        let cube = &sd[lm.sens_cube_pos..lm.sens_cube_pos + 3];
        let palm = &sd[lm.sens_palm_pos..lm.sens_palm_pos + 3];
        for k in 0..3 {
            put(palm[k] - cube[k]);
        }
        let cq = &sd[lm.sens_cube_quat..lm.sens_cube_quat + 4];
        let cq: Quat = [cq[0], cq[1], cq[2], cq[3]];
        let r = UnitQuaternion::from_quaternion(math::to_na(&cq)).to_rotation_matrix();
        for i in 0..3 {
            for j in 0..3 {
                put(r.matrix()[(i, j)]);
            }
        }
        let (goal, err) = nearest_goal(&cq, env.goals());
        for v in math::rot_rows_23(&math::mul_inv(&cq, &goal)) {
            put(v);
        }
        put(err);
        for k in 0..3 {
            put(sd[self.sens.linvel + k]);
        }
        for k in 0..3 {
            put(sd[self.sens.angvel + k]);
        }
        for t in self.sens.tips {
            for k in 0..3 {
                put(sd[t + k]);
            }
        }
        for i in 0..NU {
            put(f64::from(self.last_act[i]));
        }
        put(env.steps() as f64 / env.config().max_steps as f64);
        debug_assert_eq!(o, a + PRIVILEGED_DIM);
    }

    /// Mutable access to the wrapped environment (tests and demonstrations: place the cube).
    pub fn env_mut(&mut self) -> &mut LeapCubeEnv {
        &mut self.env
    }

    /// The reward terms of the current state as if the step that led to it applied
    /// `action` (already clamped) after the two previous actions; success = the error to
    /// the nearest goal is within the threshold.
    pub fn reward_terms(&self, action: &[f32; NU]) -> RewardTerms {
        let hit = self.env.orientation_error() < self.env.config().success_threshold;
        self.terms(action, hit)
    }

    fn terms(&self, action: &[f32; NU], success: bool) -> RewardTerms {
        let env = &self.env;
        let lm = env.model();
        let data = env.data();
        let sd = data.sensordata();
        let cube = &sd[lm.sens_cube_pos..lm.sens_cube_pos + 3];
        let palm = &sd[lm.sens_palm_pos..lm.sens_palm_pos + 3];
        let dist = (0..3)
            .map(|k| (palm[k] - cube[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        let q = env.hand_q();
        let home = lm.home();
        let hand_pose = (0..NU).map(|i| (q[i] - home[i]).powi(2)).sum();
        let mut rate = 0.0;
        for i in 0..NU {
            let (a, l, ll) = (
                f64::from(action[i]),
                f64::from(self.last_act[i]),
                f64::from(self.last_last_act[i]),
            );
            rate += (a - l).powi(2) + (a - 2.0 * l + ll).powi(2);
        }
        let qvel = data.qvel();
        // SAFETY: `actuator_force` is an array of `nu` (= NU, checked when the model was
        // loaded) doubles owned by `data`, which is borrowed immutably for this scope.
        let force = unsafe { std::slice::from_raw_parts(data.ffi().actuator_force, NU) };
        let energy = (0..NU)
            .map(|i| qvel[lm.hand_dadr[i]].abs() * force[i].abs())
            .sum();
        RewardTerms {
            orientation: tolerance_linear(env.orientation_error(), 0.2, std::f64::consts::PI),
            position: tolerance_linear(dist, 0.02, 0.05),
            termination: f64::from(u8::from(self.dropped())),
            hand_pose,
            action_rate: rate,
            energy,
            success: f64::from(u8::from(success)),
        }
    }

    /// The cube fell below the drop height, or the state is not finite.
    pub fn dropped(&self) -> bool {
        let data = self.env.data();
        let lm = self.env.model();
        let z = data.sensordata()[lm.sens_cube_pos + 2];
        z < -0.05
            || !z.is_finite()
            || data.qpos().iter().any(|v| v.is_nan())
            || data.qvel().iter().any(|v| v.is_nan())
    }

    /// One control step with `action` (clamped to `[−1, 1]`, NaN → 0 as the environment
    /// does). If the episode goes on, the next observation is taken; if it ended, the state
    /// is left as is (read [`critic_obs`](Self::critic_obs) for a time-limit bootstrap, then
    /// [`reset`](Self::reset)).
    pub fn step(&mut self, action: &[f32]) -> StepOutcome {
        let mut a = [0.0f32; NU];
        for i in 0..NU {
            a[i] = if action[i].is_nan() {
                0.0
            } else {
                action[i].clamp(-1.0, 1.0)
            };
        }
        let st = self.env.step(&a);
        // The bonus is paid whenever the error is within the threshold (as the environment
        // does), even on the rare step that also drops the cube.
        let hit = self.env.orientation_error() < self.env.config().success_threshold;
        let terms = self.terms(&a, hit);
        let ending = if !st.done {
            Ending::Running
        } else if st.success {
            Ending::Success
        } else if self.dropped() {
            Ending::Dropped
        } else {
            Ending::TimeLimit
        };
        self.last_last_act = self.last_act;
        self.last_act = a;
        if ending == Ending::Running {
            self.env.observe(&mut self.fast, &mut self.slow);
        }
        StepOutcome {
            reward: st.reward,
            terms,
            ending,
            steps: self.env.steps(),
        }
    }
}

/// The goal nearest to `q` and the orientation error to it.
pub fn nearest_goal(q: &Quat, goals: &[Quat]) -> (Quat, f64) {
    let mut best = (goals[0], f64::INFINITY);
    for g in goals {
        let e = math::orientation_error(q, g);
        if e < best.1 {
            best = (*g, e);
        }
    }
    best
}
