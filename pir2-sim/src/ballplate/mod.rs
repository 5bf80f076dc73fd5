//! Ball on a tilting plate: the small reactive task on which πR²'s advantage was measured
//! (its parameters are documented field by field on [`BallPlateConfig`]).
//!
//! # Dynamics
//!
//! Two decoupled axes `i ∈ {x, y}`. Per axis the state is the ball position `p` (m) and
//! velocity `v` (m/s) on the plate and the plate tilt `θ` (rad) and tilt rate `ω` (rad/s).
//! The plate is a position servo (unit inertia) tracking the tilt target `r` (the action):
//!
//! ```text
//!   v̇ = (5/7)·g·sin θ − c·v                 rolling ball (solid sphere), viscous friction c = 0.1
//!   ω̇ = Kp·(r − θ) − Kd·ω + β·p              servo torque + the ball's load moment
//!   τ  = Kp·(r − θ) − Kd·ω                   joint torque (sensed; quasi-statically −β·p)
//! ```
//!
//! with `g = 9.81`, `Kp = 625` (ω_n = 25 rad/s), `Kd = 40` (ζ = 0.8), `β = 40`. A positive
//! tilt accelerates the ball towards `+p`, and a ball at `+p` pulls the plate further
//! towards `+θ` (the open loop is unstable).
//!
//! Integration: control at 50 Hz, each control period split into 10 semi-implicit
//! (symplectic) Euler substeps of `dt = 2 ms`: accelerations from the current state, then
//! `v += dt·v̇`, `ω += dt·ω̇`, then `p += dt·v`, `θ += dt·ω` with the *new* velocities.
//! The target `r` is held over the control period (zero-order hold).
//!
//! # Episode
//!
//! - Reset: `p ~ U(±4 cm)`, `v ~ U(±5 cm/s)` per axis, plate level and at rest, last target 0.
//! - Pushes: a Poisson process of rate 0.6/s on `t ∈ [0.5, 8) s`; each push adds a velocity
//!   impulse of magnitude `U(0.20, 0.35)` m/s in a uniformly random direction to the ball,
//!   applied at the first substep whose time is `≥` the push time.
//! - Action: absolute tilt target per axis; the environment clamps it to `[−0.15, 0.15]` rad.
//! - Length 10 s = 500 control steps. Failure (episode ends at once): the ball leaves the
//!   square `|p|∞ ≤ 0.15 m` at any substep. Success: the ball never left and, after the last
//!   step, lies within 5 cm of the centre (Euclidean distance).
//! - Reward (informational): `−‖p‖₂` after the step.
//!
//! # Observations
//!
//! Fast channel (6-d, order `[θx, θy, θx − rx, θy − ry, τx, τy]`): plate tilt (σ 1 mrad),
//! tilt minus the last commanded target (σ 1 mrad), joint torque (σ 0.02). Slow channel
//! (4-d, `[px, py, vx, vy]`): the camera tracker's ball position (σ 0.2 mm per frame) and its
//! finite-difference velocity `(p̂_k − p̂_{k−1})/T` over the last two camera frames, *not*
//! delayed here (the runtime and the trainer apply `d_vis`). Noise is Gaussian. One camera
//! frame is taken at reset and after every control step (stream 4), so a frame's noise does
//! not depend on how often it is observed.
//!
//! The velocity entry matters: the expert's gain on the ball velocity is large (≈ 4.2 rad per
//! m/s), and a policy that sees positions only — one camera frame plus the 2-frame fast
//! history — cannot recover it well enough. A linear least-squares policy fitted on 200
//! expert demonstrations succeeds in 0/50 episodes without the camera velocity and in
//! 47/50 with it (zero delay).
//!
//! # Randomness
//!
//! Everything derives from the episode seed with [`pir2_schedule::Rng`]: stream 0 draws the
//! initial state and the pushes at reset, stream 1 the sensor noise, stream 4 the camera noise. Observing does not
//! change the physics, and the same seed with the same actions gives bit-identical
//! trajectories and observations.

// Per-axis physics reads best with explicit axis indices.
#![allow(clippy::needless_range_loop)]

use pir2_runtime::{EnvStep, Environment, Nanos};
use pir2_schedule::Rng;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Fast observation dimension.
pub const FAST_DIM: usize = 6;
/// Slow observation dimension.
pub const SLOW_DIM: usize = 4;
/// Action dimension.
pub const ACTION_DIM: usize = 2;
/// Rolling factor of a solid sphere: `ẍ = (5/7)·g·sin θ`.
pub const ROLLING_FACTOR: f64 = 5.0 / 7.0;

/// Names of the fast observation entries (in order), as written to datasets.
pub const FAST_NAMES: [&str; FAST_DIM] = [
    "tilt_x",
    "tilt_y",
    "tilt_minus_target_x",
    "tilt_minus_target_y",
    "torque_x",
    "torque_y",
];
/// Names of the slow observation entries.
pub const SLOW_NAMES: [&str; SLOW_DIM] = ["ball_x", "ball_y", "ball_vx", "ball_vy"];
/// Names of the action entries.
pub const ACTION_NAMES: [&str; ACTION_DIM] = ["tilt_target_x", "tilt_target_y"];

/// Parameters of the ball-on-plate task; the defaults are the measured task of the findings.
/// Loadable from TOML (every field optional).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BallPlateConfig {
    /// Control rate in Hz.
    pub control_hz: f64,
    /// Semi-implicit Euler substeps per control period.
    pub substeps: usize,
    /// Episode length in seconds.
    pub episode_s: f64,
    /// Gravity (m/s²).
    pub gravity: f64,
    /// Viscous rolling friction `c` of the ball (1/s).
    pub ball_friction: f64,
    /// Servo stiffness `Kp` (1/s², unit inertia).
    pub servo_kp: f64,
    /// Servo damping `Kd` (1/s).
    pub servo_kd: f64,
    /// Load coupling `β` of the ball position into the plate (1/(m·s²)).
    pub load_coupling: f64,
    /// The environment clamps tilt targets to `±max_target` (rad).
    pub max_target: f64,
    /// Poisson rate of pushes (1/s); 0 disables pushes.
    pub push_rate: f64,
    /// Pushes happen in `[push_start, push_end)` seconds.
    pub push_start: f64,
    /// End of the push window (s).
    pub push_end: f64,
    /// Minimum push speed (m/s).
    pub push_min: f64,
    /// Maximum push speed (m/s).
    pub push_max: f64,
    /// Initial ball position drawn from `U(±init_pos)` per axis (m).
    pub init_pos: f64,
    /// Initial ball velocity drawn from `U(±init_vel)` per axis (m/s).
    pub init_vel: f64,
    /// The ball must stay in `|p|∞ ≤ bound` (m).
    pub bound: f64,
    /// Success radius at the end of the episode (m, Euclidean).
    pub success_radius: f64,
    /// Noise σ of the sensed tilt (rad).
    pub noise_tilt: f64,
    /// Noise σ of the sensed tilt − last target (rad).
    pub noise_tilt_error: f64,
    /// Noise σ of the sensed joint torque.
    pub noise_torque: f64,
    /// Noise σ of the camera ball position (m).
    pub noise_camera: f64,
}

impl Default for BallPlateConfig {
    fn default() -> Self {
        Self {
            control_hz: 50.0,
            substeps: 10,
            episode_s: 10.0,
            gravity: 9.81,
            ball_friction: 0.1,
            servo_kp: 625.0,
            servo_kd: 40.0,
            load_coupling: 40.0,
            max_target: 0.15,
            push_rate: 0.6,
            push_start: 0.5,
            push_end: 8.0,
            push_min: 0.20,
            push_max: 0.35,
            init_pos: 0.04,
            init_vel: 0.05,
            bound: 0.15,
            success_radius: 0.05,
            noise_tilt: 1e-3,
            noise_tilt_error: 1e-3,
            noise_torque: 0.02,
            noise_camera: 2e-4,
        }
    }
}

/// Longest episode a configuration may ask for, in control steps.
const MAX_STEPS: usize = 10_000_000;
/// Most physics substeps per control step.
const MAX_SUBSTEPS: usize = 100_000;
/// Largest mean number of pushes per episode (`push_rate × (push_end − push_start)`).
const MAX_MEAN_PUSHES: f64 = 10_000.0;

impl BallPlateConfig {
    /// Parse a (partial) TOML table; missing fields keep their defaults.
    pub fn from_toml_str(s: &str) -> Result<Self> {
        let cfg: Self = toml::from_str(s)?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Check ranges (NaN is rejected everywhere).
    pub fn validate(&self) -> Result<()> {
        let bad = |field, reason: &str| {
            Err(Error::ConfigValue {
                field,
                reason: reason.to_string(),
            })
        };
        let positive = |v: f64| v.is_finite() && v > 0.0;
        let non_negative = |v: f64| v.is_finite() && v >= 0.0;
        if !positive(self.control_hz) {
            return bad("control_hz", "must be > 0");
        }
        if self.substeps == 0 {
            return bad("substeps", "must be ≥ 1");
        }
        if !positive(self.episode_s) || self.max_steps() == 0 {
            return bad("episode_s", "must last at least one control period");
        }
        if self.episode_s * self.control_hz > MAX_STEPS as f64 {
            return bad(
                "episode_s",
                "episode_s × control_hz must be at most 10^7 steps",
            );
        }
        if self.substeps > MAX_SUBSTEPS {
            return bad("substeps", "must be at most 100000");
        }
        if !non_negative(self.push_start)
            || !non_negative(self.push_end)
            || self.push_start > self.push_end
        {
            return bad("push_start", "must be ≥ 0 and ≤ push_end (both finite)");
        }
        if self.push_rate * (self.push_end - self.push_start) > MAX_MEAN_PUSHES {
            return bad(
                "push_rate",
                "push_rate × (push_end − push_start) must be at most 10000 pushes per episode",
            );
        }
        if !non_negative(self.push_rate) {
            return bad("push_rate", "must be ≥ 0");
        }
        if !non_negative(self.push_min)
            || !non_negative(self.push_max)
            || self.push_min > self.push_max
        {
            return bad("push_min", "must be ≥ 0 and ≤ push_max");
        }
        for (field, v) in [
            ("max_target", self.max_target),
            ("bound", self.bound),
            ("success_radius", self.success_radius),
        ] {
            if !positive(v) {
                return bad(field, "must be > 0");
            }
        }
        for (field, v) in [
            ("noise_tilt", self.noise_tilt),
            ("noise_tilt_error", self.noise_tilt_error),
            ("noise_torque", self.noise_torque),
            ("noise_camera", self.noise_camera),
            ("init_pos", self.init_pos),
            ("init_vel", self.init_vel),
        ] {
            if !non_negative(v) {
                return bad(field, "must be ≥ 0");
            }
        }
        Ok(())
    }

    /// Control period in seconds.
    pub fn control_period_s(&self) -> f64 {
        1.0 / self.control_hz
    }

    /// Substep length in seconds.
    pub fn dt(&self) -> f64 {
        self.control_period_s() / self.substeps as f64
    }

    /// Episode length in control steps.
    pub fn max_steps(&self) -> usize {
        (self.episode_s * self.control_hz).round() as usize
    }
}

/// The full (privileged) state of the task, per axis `[x, y]`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BallPlateState {
    /// Ball position on the plate (m).
    pub pos: [f64; 2],
    /// Ball velocity (m/s).
    pub vel: [f64; 2],
    /// Plate tilt (rad).
    pub tilt: [f64; 2],
    /// Plate tilt rate (rad/s).
    pub tilt_rate: [f64; 2],
    /// The tilt target currently held by the servo (rad, clamped).
    pub target: [f64; 2],
}

impl BallPlateState {
    /// The per-axis LQR state `(p, v, θ, ω)` of axis `i`.
    pub fn axis(&self, i: usize) -> [f64; 4] {
        [self.pos[i], self.vel[i], self.tilt[i], self.tilt_rate[i]]
    }
}

/// One scheduled push: time (s) and velocity impulse (m/s).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Push {
    /// Time of the push since the episode start (s).
    pub t: f64,
    /// Velocity impulse added to the ball (m/s).
    pub dv: [f64; 2],
}

/// Test hook: hold parts of the system still (energy/momentum and servo checks).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) enum Freeze {
    #[default]
    None,
    /// The plate keeps its tilt and rate 0 (only the ball moves).
    Plate,
    /// The ball keeps its position and velocity (only the plate moves).
    Ball,
}

/// The ball-on-plate environment. Implements [`Environment`].
#[derive(Debug, Clone)]
pub struct BallPlate {
    cfg: BallPlateConfig,
    state: BallPlateState,
    step: usize,
    pushes: Vec<Push>,
    next_push: usize,
    sensor_rng: Rng,
    camera_rng: Rng,
    /// Camera frames `[previous, latest]` of the ball position (noisy).
    camera: [[f64; 2]; 2],
    done: bool,
    success: bool,
    left_bound: bool,
    pub(crate) freeze: Freeze,
}

impl BallPlate {
    /// A new environment, reset with seed 0.
    pub fn new(cfg: BallPlateConfig) -> Result<Self> {
        cfg.validate()?;
        let mut env = Self {
            cfg,
            state: BallPlateState::default(),
            step: 0,
            pushes: Vec::new(),
            next_push: 0,
            sensor_rng: Rng::new(0),
            camera_rng: Rng::new(0),
            camera: [[0.0; 2]; 2],
            done: false,
            success: false,
            left_bound: false,
            freeze: Freeze::None,
        };
        env.reset(0);
        Ok(env)
    }

    /// The configuration.
    pub fn config(&self) -> &BallPlateConfig {
        &self.cfg
    }

    /// The privileged state (for experts and tests).
    pub fn state(&self) -> &BallPlateState {
        &self.state
    }

    /// Replace the state (for tests and studies); keeps the step counter and pushes.
    pub fn set_state(&mut self, state: BallPlateState) {
        self.state = state;
    }

    /// Control steps taken in this episode.
    pub fn step_count(&self) -> usize {
        self.step
    }

    /// Time since the episode start (s).
    pub fn time(&self) -> f64 {
        self.step as f64 * self.cfg.control_period_s()
    }

    /// The pushes scheduled for this episode.
    pub fn pushes(&self) -> &[Push] {
        &self.pushes
    }

    /// Whether the episode has ended.
    pub fn is_done(&self) -> bool {
        self.done
    }

    /// Whether the ball has left the plate's square (a failure).
    pub fn left_bound(&self) -> bool {
        self.left_bound
    }

    /// Joint torque of axis `i` without noise: `Kp·(r − θ) − Kd·ω`.
    pub fn torque(&self, i: usize) -> f64 {
        let s = &self.state;
        self.cfg.servo_kp * (s.target[i] - s.tilt[i]) - self.cfg.servo_kd * s.tilt_rate[i]
    }

    /// Take a camera frame of the current ball position into `camera[1]`.
    fn capture(&mut self) {
        for i in 0..2 {
            self.camera[1][i] =
                self.state.pos[i] + self.cfg.noise_camera * self.camera_rng.normal() as f64;
        }
    }

    /// Set the clamped target for the next control period (used by [`Environment::step`]).
    fn set_target(&mut self, action: &[f32]) {
        let m = self.cfg.max_target;
        for i in 0..2 {
            let a = action[i] as f64;
            // A NaN action holds the plate level rather than poisoning the state.
            self.state.target[i] = if a.is_nan() { 0.0 } else { a.clamp(-m, m) };
        }
    }

    /// One semi-implicit Euler substep of length `dt`.
    fn substep(&mut self, dt: f64) {
        let c = &self.cfg;
        let s = &mut self.state;
        for i in 0..2 {
            let acc_ball =
                ROLLING_FACTOR * c.gravity * s.tilt[i].sin() - c.ball_friction * s.vel[i];
            let acc_plate = c.servo_kp * (s.target[i] - s.tilt[i]) - c.servo_kd * s.tilt_rate[i]
                + c.load_coupling * s.pos[i];
            if self.freeze != Freeze::Ball {
                s.vel[i] += dt * acc_ball;
                s.pos[i] += dt * s.vel[i];
            }
            if self.freeze != Freeze::Plate {
                s.tilt_rate[i] += dt * acc_plate;
                s.tilt[i] += dt * s.tilt_rate[i];
            }
        }
    }

    fn draw_pushes(cfg: &BallPlateConfig, rng: &mut Rng, out: &mut Vec<Push>) {
        out.clear();
        if cfg.push_rate <= 0.0 {
            return;
        }
        let mut t = cfg.push_start;
        // Validation bounds the mean count (≤ 10^4); the cap is a backstop, never reached.
        while out.len() < 10 * MAX_MEAN_PUSHES as usize {
            // Exponential inter-arrival times: a Poisson process of rate `push_rate`.
            let u = 1.0 - rng.uniform_f64(); // (0, 1]
            t += -u.ln() / cfg.push_rate;
            if t >= cfg.push_end {
                break;
            }
            let speed = cfg.push_min + (cfg.push_max - cfg.push_min) * rng.uniform_f64();
            let phi = std::f64::consts::TAU * rng.uniform_f64();
            out.push(Push {
                t,
                dv: [speed * phi.cos(), speed * phi.sin()],
            });
        }
    }
}

impl Environment for BallPlate {
    fn spec(&self) -> pir2_runtime::io::EnvSpec {
        pir2_runtime::io::EnvSpec {
            fast_dim: FAST_DIM,
            slow_dim: SLOW_DIM,
            action_dim: ACTION_DIM,
            control_period: (1e9 / self.cfg.control_hz).round() as Nanos,
            max_steps: self.cfg.max_steps(),
        }
    }

    fn reset(&mut self, seed: u64) {
        let mut rng = Rng::derive(seed, 0);
        let (p, v) = (self.cfg.init_pos, self.cfg.init_vel);
        let mut s = BallPlateState::default();
        for i in 0..2 {
            s.pos[i] = p * (2.0 * rng.uniform_f64() - 1.0);
            s.vel[i] = v * (2.0 * rng.uniform_f64() - 1.0);
        }
        self.state = s;
        Self::draw_pushes(&self.cfg, &mut rng, &mut self.pushes);
        self.sensor_rng = Rng::derive(seed, 1);
        self.camera_rng = Rng::derive(seed, 4);
        // The tracker ran before the episode: the previous frame saw the ball one period
        // earlier (the plate was level and at rest, so the ball moved at constant speed).
        let period = self.cfg.control_period_s();
        for i in 0..2 {
            self.camera[0][i] = self.state.pos[i] - period * self.state.vel[i]
                + self.cfg.noise_camera * self.camera_rng.normal() as f64;
        }
        self.capture();
        self.step = 0;
        self.next_push = 0;
        self.done = false;
        self.success = false;
        self.left_bound = false;
    }

    fn observe(&mut self, fast: &mut [f32], slow: &mut [f32]) {
        let c = &self.cfg;
        let r = &mut self.sensor_rng;
        let s = &self.state;
        for i in 0..2 {
            let torque = c.servo_kp * (s.target[i] - s.tilt[i]) - c.servo_kd * s.tilt_rate[i];
            fast[i] = (s.tilt[i] + c.noise_tilt * r.normal() as f64) as f32;
            fast[2 + i] = (s.tilt[i] - s.target[i] + c.noise_tilt_error * r.normal() as f64) as f32;
            fast[4 + i] = (torque + c.noise_torque * r.normal() as f64) as f32;
        }
        let period = c.control_period_s();
        let [prev, now] = self.camera;
        for i in 0..2 {
            slow[i] = now[i] as f32;
            slow[2 + i] = ((now[i] - prev[i]) / period) as f32;
        }
    }

    fn step(&mut self, action: &[f32]) -> EnvStep {
        let reward = -(self.state.pos[0].hypot(self.state.pos[1])) as f32;
        if self.done {
            return EnvStep {
                done: true,
                success: self.success,
                reward,
            };
        }
        self.set_target(action);
        let dt = self.cfg.dt();
        let t0 = self.time();
        for k in 0..self.cfg.substeps {
            let t = t0 + k as f64 * dt;
            while let Some(p) = self.pushes.get(self.next_push) {
                if p.t > t + 1e-12 {
                    break;
                }
                if self.freeze != Freeze::Ball {
                    self.state.vel[0] += p.dv[0];
                    self.state.vel[1] += p.dv[1];
                }
                self.next_push += 1;
            }
            self.substep(dt);
            let b = self.cfg.bound;
            if self.state.pos[0].abs() > b || self.state.pos[1].abs() > b {
                self.left_bound = true;
            }
        }
        self.step += 1;
        self.camera[0] = self.camera[1];
        self.capture();
        let dist = self.state.pos[0].hypot(self.state.pos[1]);
        if self.left_bound {
            self.done = true;
            self.success = false;
        } else if self.step >= self.cfg.max_steps() {
            self.done = true;
            self.success = dist <= self.cfg.success_radius;
        }
        EnvStep {
            done: self.done,
            success: self.success,
            reward: -(dist as f32),
        }
    }
}

#[cfg(test)]
mod tests;
