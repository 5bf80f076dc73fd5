//! Ball on a tilting plate: the small reactive task on which πR²'s advantage was measured
//! (facts in `shared/reference/embedded_task_findings.md`).
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
        if self.max_steps() == 0 {
            return bad("episode_s", "must last at least one control period");
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
        loop {
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
mod tests {
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
}
