//! A safety layer that wraps any [`Robot`].
//!
//! One file on purpose: the limits ([`SafetyConfig`]), the checks that apply them in the
//! order below and the counters that record every intervention ([`SafetyStats`]) are one
//! safety argument, reviewed together; apart, a limit would sit away from the only code that
//! enforces it.
//!
//! Per target sent ([`Robot::send_targets`]), in this order:
//! 1. **Non-finite rejection**: a target with a NaN or ±inf is dropped whole; the last safe
//!    target is sent again (hold).
//! 2. **Torque hold**: while the newest state has a torque above
//!    [`SafetyConfig::torque_limit`], targets are not advanced (the last safe target is held);
//!    after [`SafetyConfig::torque_stop_reads`] consecutive over-limit reads the robot stops.
//! 3. **Joint limits**: each joint is clamped to `[lower, upper]`.
//! 4. **Velocity and acceleration limits**, in rad/s and rad/s², converted by the time since
//!    the last target (`dt`, capped at the nominal [`SafetyConfig::period`]; the first target
//!    uses the period): each joint moves at most `max_velocity · dt` from the last safe target
//!    (from the measured position for the first target), and its velocity changes by at most
//!    `max_accel · dt` per target. Targets sent faster than the nominal rate move less per
//!    target; a target after a pause moves one period's worth, never a catch-up jump.
//!
//! Per state read ([`Robot::read_state`]): a state with a non-finite value is rejected; a
//! state older than [`SafetyConfig::state_timeout`] stops the robot; a fault the driver
//! reports ([`Robot::fault`]: an XHand finger error word, an arm controller error) stops the
//! robot; a tracking error `|last target − measured|` above [`SafetyConfig::tracking_error`]
//! for [`SafetyConfig::tracking_stop_reads`] consecutive reads stops the robot; and
//! [`SafetyConfig::error_stop`] consecutive driver errors (reads or sends) stop the robot.
//!
//! **Watchdog** ([`SafetyLayer::check_watchdog`], run by a thread from
//! [`SafetyLayer::spawn_watchdog`]): stops the robot when no target arrived for
//! [`SafetyConfig::command_timeout`] (the policy stopped sending) or no fresh state for
//! [`SafetyConfig::state_timeout`] (after the first of each).
//!
//! **Stop**: the layer calls the robot's `stop()` once (streaming halts; each driver documents
//! what its stop sends), latches, and fails every later read and send with
//! [`Error::SafetyStop`] naming the reason, until [`SafetyLayer::reset`]. Every intervention is
//! counted in [`SafetyStats`].

use std::f32::consts::{PI, TAU};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::thread::JoinHandle;
use std::time::Duration;

use pir2_runtime::{Clock, Nanos};

use crate::error::{Error, Result};
use crate::robot::{Robot, StateLayout, ARM_DOF, ARM_HAND_ACTION_DIM, HAND_DOF};

/// Limits of a [`SafetyLayer`]. Vectors have one entry per action dimension.
#[derive(Debug, Clone, PartialEq)]
pub struct SafetyConfig {
    /// Lower joint limits.
    pub lower: Vec<f32>,
    /// Upper joint limits.
    pub upper: Vec<f32>,
    /// Largest joint speed, rad/s.
    pub max_velocity: Vec<f32>,
    /// Largest change of joint speed, rad/s² (`f32::INFINITY`: no limit).
    pub max_accel: Vec<f32>,
    /// Nominal control period: the `dt` of the first target, and the cap on `dt` after a
    /// pause or an overrun.
    pub period: Duration,
    /// Largest `|last target − measured position|` per joint, rad (`f32::INFINITY`: none).
    pub tracking_error: Vec<f32>,
    /// Consecutive reads over [`tracking_error`](Self::tracking_error) before a stop.
    pub tracking_stop_reads: u32,
    /// Consecutive errors of the wrapped robot (reads or sends) before a stop (0: never).
    pub error_stop: u32,
    /// Largest allowed |torque| in the state's torque entries.
    pub torque_limit: f32,
    /// Consecutive over-limit reads before a stop (0 = hold only, never stop for torque).
    pub torque_stop_reads: u32,
    /// A state older than this (or none for this long) stops the robot.
    pub state_timeout: Duration,
    /// No target for this long (after the first) stops the robot.
    pub command_timeout: Duration,
}

/// xArm6 lower joint limits, rad: the xArm6 URDF ranges of UFACTORY's ROS description
/// (J2 [-2.059, 2.0944], J3 [-3.927, 0.19198], J5 [-1.69297, π], J1/J4/J6 ±2π), the
/// fractional ones rounded inward.
pub const XARM6_LOWER: [f32; 6] = [-TAU, -2.059, -3.927, -TAU, -1.692, -TAU];
/// xArm6 upper joint limits, rad.
pub const XARM6_UPPER: [f32; 6] = [TAU, 2.094, 0.191, TAU, PI, TAU];
/// Conservative default XHand joint envelope, rad (not vendor limits: set the hand's own in
/// the embodiment's `[safety]` table).
pub const XHAND_LOWER: f32 = -0.5;
/// Conservative default XHand joint envelope, rad.
pub const XHAND_UPPER: f32 = 2.0;
/// Default arm joint speed limit, rad/s.
pub const ARM_MAX_VELOCITY: f32 = 1.25;
/// Default arm joint acceleration limit, rad/s².
pub const ARM_MAX_ACCEL: f32 = 20.0;
/// Hardware ceiling of an xArm joint's speed, rad/s: the largest joint speed UFACTORY's
/// controller accepts (xarm-python-sdk 1.18.4, `xarm/x3/base.py`: joint speed limit
/// `[0.0001, 4.0]` rad/s).
pub const ARM_HW_MAX_VELOCITY: f32 = 4.0;
/// Hardware ceiling of an xArm joint's acceleration, rad/s² (the same file: `[0.01, 20.0]`).
pub const ARM_HW_MAX_ACCEL: f32 = 20.0;
/// Default hand joint speed limit, rad/s.
pub const HAND_MAX_VELOCITY: f32 = 5.0;
/// Default hand joint acceleration limit, rad/s².
pub const HAND_MAX_ACCEL: f32 = 100.0;
/// Default arm tracking-error bound, rad.
pub const ARM_TRACKING_ERROR: f32 = 0.5;
/// Default hand tracking-error bound, rad.
pub const HAND_TRACKING_ERROR: f32 = 1.0;

impl SafetyConfig {
    /// The same limits on every one of `dim` joints at a 25 Hz nominal rate, no acceleration
    /// or tracking bound, no torque limit, stop after 3 driver errors in a row.
    pub fn uniform(dim: usize, lower: f32, upper: f32, max_velocity: f32) -> Self {
        Self {
            lower: vec![lower; dim],
            upper: vec![upper; dim],
            max_velocity: vec![max_velocity; dim],
            max_accel: vec![f32::INFINITY; dim],
            period: Duration::from_millis(40),
            tracking_error: vec![f32::INFINITY; dim],
            tracking_stop_reads: 1,
            error_stop: 3,
            torque_limit: f32::INFINITY,
            torque_stop_reads: 0,
            state_timeout: Duration::from_millis(200),
            command_timeout: Duration::from_millis(200),
        }
    }

    /// Defaults for the xArm6 + XHand composite at `control_hz`: xArm6 joint limits, arm
    /// 1.25 rad/s and 20 rad/s², the conservative hand envelope with 5 rad/s and 100 rad/s²,
    /// tracking errors of 0.5 rad (arm) and 1 rad (hand) for 0.5 s, hand torque limit 300
    /// (the paper's) for 1 s, state and command timeouts of 200 ms.
    pub fn xarm6_xhand_at(control_hz: f64) -> Self {
        let mut c = Self::uniform(
            ARM_HAND_ACTION_DIM,
            XHAND_LOWER,
            XHAND_UPPER,
            HAND_MAX_VELOCITY,
        );
        c.lower[..ARM_DOF].copy_from_slice(&XARM6_LOWER);
        c.upper[..ARM_DOF].copy_from_slice(&XARM6_UPPER);
        c.max_velocity[..ARM_DOF].fill(ARM_MAX_VELOCITY);
        c.max_accel[..ARM_DOF].fill(ARM_MAX_ACCEL);
        c.max_accel[ARM_DOF..].fill(HAND_MAX_ACCEL);
        c.tracking_error[..ARM_DOF].fill(ARM_TRACKING_ERROR);
        c.tracking_error[ARM_DOF..].fill(HAND_TRACKING_ERROR);
        debug_assert_eq!(c.lower.len(), ARM_DOF + HAND_DOF);
        let hz = if control_hz.is_finite() && control_hz > 0.0 {
            control_hz
        } else {
            25.0
        };
        c.period = Duration::from_secs_f64(1.0 / hz);
        let reads = |secs: f64| ((secs * hz).round() as u32).max(1);
        c.tracking_stop_reads = reads(0.5);
        c.torque_limit = 300.0;
        c.torque_stop_reads = reads(1.0);
        c
    }

    /// The ceiling no configuration may widen for the xArm6 + XHand composite at
    /// `control_hz` ([`widening`](Self::widening)): the xArm6 joint ranges and the controller's
    /// largest accepted joint speed and acceleration ([`ARM_HW_MAX_VELOCITY`],
    /// [`ARM_HW_MAX_ACCEL`]); for the hand, whose vendor publishes no speed or acceleration
    /// bound this project could cite, the conservative envelope of
    /// [`xarm6_xhand_at`](Self::xarm6_xhand_at); the tracking-error bounds of the defaults.
    pub fn xarm6_xhand_ceiling_at(control_hz: f64) -> Self {
        let mut c = Self::xarm6_xhand_at(control_hz);
        c.max_velocity[..ARM_DOF].fill(ARM_HW_MAX_VELOCITY);
        c.max_accel[..ARM_DOF].fill(ARM_HW_MAX_ACCEL);
        c
    }

    /// The first limit of `self` that is looser than `ceiling`'s (a joint range reaching
    /// outside, a larger speed, acceleration or tracking-error bound), or `None` when `self`
    /// only tightens: a checkpoint or a flag may narrow the robot's envelope, never widen it.
    /// Both must have the same length (checked by [`validate`](Self::validate)).
    pub fn widening(&self, ceiling: &SafetyConfig) -> Option<Widening> {
        let n = self.lower.len().min(ceiling.lower.len());
        for joint in 0..n {
            let checks = [
                (
                    "lower",
                    self.lower[joint],
                    ceiling.lower[joint],
                    self.lower[joint] < ceiling.lower[joint],
                ),
                (
                    "upper",
                    self.upper[joint],
                    ceiling.upper[joint],
                    self.upper[joint] > ceiling.upper[joint],
                ),
                (
                    "max_velocity",
                    self.max_velocity[joint],
                    ceiling.max_velocity[joint],
                    self.max_velocity[joint] > ceiling.max_velocity[joint],
                ),
                (
                    "max_accel",
                    self.max_accel[joint],
                    ceiling.max_accel[joint],
                    self.max_accel[joint] > ceiling.max_accel[joint],
                ),
                (
                    "tracking_error",
                    self.tracking_error[joint],
                    ceiling.tracking_error[joint],
                    self.tracking_error[joint] > ceiling.tracking_error[joint],
                ),
            ];
            for (field, value, limit, wider) in checks {
                // NaN compares false everywhere: refuse it here too.
                if wider || value.is_nan() {
                    return Some(Widening {
                        joint,
                        field,
                        value,
                        limit,
                    });
                }
            }
        }
        None
    }

    /// [`xarm6_xhand_at`](Self::xarm6_xhand_at) 25 Hz, the paper's rate.
    pub fn xarm6_xhand() -> Self {
        Self::xarm6_xhand_at(25.0)
    }

    /// Check sizes and ranges against an action dimension.
    pub fn validate(&self, dim: usize) -> Result<()> {
        Error::check_dim("safety lower limits", dim, self.lower.len())?;
        Error::check_dim("safety upper limits", dim, self.upper.len())?;
        Error::check_dim("safety max_velocity", dim, self.max_velocity.len())?;
        Error::check_dim("safety max_accel", dim, self.max_accel.len())?;
        Error::check_dim("safety tracking_error", dim, self.tracking_error.len())?;
        if self.period.is_zero() {
            return Err(Error::Config("safety period must be > 0".into()));
        }
        if self.tracking_stop_reads == 0 {
            return Err(Error::Config(
                "safety tracking_stop_reads must be >= 1".into(),
            ));
        }
        for i in 0..dim {
            if self.lower[i].is_nan() || self.upper[i].is_nan() || self.lower[i] > self.upper[i] {
                return Err(Error::Config(format!(
                    "safety joint {i}: lower {} > upper {}",
                    self.lower[i], self.upper[i]
                )));
            }
            if !self.lower[i].is_finite() || !self.upper[i].is_finite() {
                return Err(Error::Config(format!(
                    "safety joint {i}: limits [{}, {}] must be finite",
                    self.lower[i], self.upper[i]
                )));
            }
            if !self.max_velocity[i].is_finite() || self.max_velocity[i] < 0.0 {
                return Err(Error::Config(format!(
                    "safety joint {i}: max_velocity {} rad/s must be finite and >= 0",
                    self.max_velocity[i]
                )));
            }
            for (what, v) in [
                ("max_accel", self.max_accel[i]),
                ("tracking_error", self.tracking_error[i]),
            ] {
                if v.is_nan() || v <= 0.0 {
                    return Err(Error::Config(format!(
                        "safety joint {i}: {what} {v} must be > 0"
                    )));
                }
            }
        }
        if self.torque_limit.is_nan() || self.torque_limit <= 0.0 {
            return Err(Error::Config(format!(
                "safety torque_limit {} must be > 0",
                self.torque_limit
            )));
        }
        if self.state_timeout.is_zero() || self.command_timeout.is_zero() {
            return Err(Error::Config("safety timeouts must be > 0".into()));
        }
        Ok(())
    }
}

/// A limit looser than the robot's ceiling ([`SafetyConfig::widening`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Widening {
    /// The action dimension.
    pub joint: usize,
    /// `lower`, `upper`, `max_velocity`, `max_accel` or `tracking_error`.
    pub field: &'static str,
    /// The configured value.
    pub value: f32,
    /// The ceiling's value.
    pub limit: f32,
}

/// Every intervention of the safety layer, counted.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SafetyStats {
    /// Targets received.
    pub targets: u64,
    /// States read.
    pub reads: u64,
    /// Targets with at least one joint clamped to its limits.
    pub limit_clamps: u64,
    /// Targets with at least one joint rate-limited.
    pub rate_clamps: u64,
    /// Targets rejected for a NaN/inf (last safe target held).
    pub non_finite_targets: u64,
    /// States rejected for a NaN/inf.
    pub non_finite_states: u64,
    /// Reads with a torque over the limit.
    pub torque_over: u64,
    /// Targets held because of a torque over the limit.
    pub torque_holds: u64,
    /// Stale states (too old when read, or none for too long).
    pub stale_states: u64,
    /// Watchdog firings because no target arrived in time.
    pub command_timeouts: u64,
    /// Errors returned by the wrapped robot.
    pub robot_errors: u64,
    /// Reads with a tracking error over the bound.
    pub tracking_over: u64,
    /// Faults reported by the wrapped robot (finger error words, controller errors).
    pub faults: u64,
    /// Stops issued by the layer (including explicit `stop()` calls).
    pub stops: u64,
}

impl SafetyStats {
    /// Number of interventions (everything except plain counts of targets, reads and errors).
    pub fn interventions(&self) -> u64 {
        self.limit_clamps
            + self.rate_clamps
            + self.non_finite_targets
            + self.non_finite_states
            + self.torque_holds
            + self.stale_states
            + self.command_timeouts
            + self.tracking_over
            + self.faults
            + self.stops
    }
}

impl std::fmt::Display for SafetyStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "targets {} reads {} | limit clamps {} rate clamps {} non-finite targets {} non-finite states {} \
             torque over {} torque holds {} stale states {} command timeouts {} robot errors {} \
             tracking over {} faults {} stops {}",
            self.targets,
            self.reads,
            self.limit_clamps,
            self.rate_clamps,
            self.non_finite_targets,
            self.non_finite_states,
            self.torque_over,
            self.torque_holds,
            self.stale_states,
            self.command_timeouts,
            self.robot_errors,
            self.tracking_over,
            self.faults,
            self.stops
        )
    }
}

#[derive(Debug)]
struct Inner<R> {
    robot: R,
    cfg: SafetyConfig,
    layout: StateLayout,
    clock: Arc<dyn Clock>,
    last_target: Option<Vec<f32>>,
    last_pos: Option<Vec<f32>>,
    state_buf: Vec<f32>,
    target_buf: Vec<f32>,
    ref_buf: Vec<f32>,
    last_vel: Vec<f32>,
    t_send: Option<Nanos>,
    t_state: Option<Nanos>,
    torque_run: u32,
    tracking_run: u32,
    error_run: u32,
    stopped: Option<String>,
    stats: SafetyStats,
}

impl<R: Robot> Inner<R> {
    fn halt(&mut self, reason: String) -> Error {
        if self.stopped.is_none() {
            self.stats.stops += 1;
            if self.robot.stop().is_err() {
                self.stats.robot_errors += 1;
            }
            self.stopped = Some(reason.clone());
        }
        Error::SafetyStop(self.stopped.clone().unwrap_or(reason))
    }

    fn check_stopped(&self) -> Result<()> {
        match &self.stopped {
            Some(r) => Err(Error::SafetyStop(r.clone())),
            None => Ok(()),
        }
    }

    fn watchdog(&mut self) -> Result<()> {
        self.check_stopped()?;
        let now = self.clock.now();
        let cmd_to = self.cfg.command_timeout.as_nanos() as Nanos;
        let st_to = self.cfg.state_timeout.as_nanos() as Nanos;
        if let Some(t) = self.t_send {
            let age = now.saturating_sub(t);
            if age > cmd_to {
                self.stats.command_timeouts += 1;
                return Err(self.halt(format!("watchdog: no target for {} ms", age / 1_000_000)));
            }
        }
        if let Some(t) = self.t_state {
            let age = now.saturating_sub(t);
            if age > st_to {
                self.stats.stale_states += 1;
                return Err(self.halt(format!(
                    "watchdog: no fresh state for {} ms",
                    age / 1_000_000
                )));
            }
        }
        Ok(())
    }

    /// Count a driver error; a fault the driver reports with it, or enough errors in a row,
    /// stop the robot.
    fn robot_error(&mut self, e: Error) -> Error {
        self.stats.robot_errors += 1;
        self.error_run += 1;
        if let Some(fault) = self.robot.fault() {
            self.stats.faults += 1;
            return self.halt(format!(
                "{} reports a fault: {fault} (driver error: {e})",
                self.robot.name()
            ));
        }
        if self.cfg.error_stop > 0 && self.error_run >= self.cfg.error_stop {
            let n = self.error_run;
            return self.halt(format!("{n} driver errors in a row, the last: {e}"));
        }
        e
    }

    fn read(&mut self, out: &mut [f32]) -> Result<Nanos> {
        self.check_stopped()?;
        Error::check_dim("safety state", self.robot.state_dim(), out.len())?;
        let t = match self.robot.read_state(out) {
            Ok(t) => t,
            Err(e) => return Err(self.robot_error(e)),
        };
        self.error_run = 0;
        self.stats.reads += 1;
        if let Some(fault) = self.robot.fault() {
            self.stats.faults += 1;
            return Err(self.halt(format!("{} reports a fault: {fault}", self.robot.name())));
        }
        if let Some(i) = out.iter().position(|x| !x.is_finite()) {
            self.stats.non_finite_states += 1;
            return Err(Error::Stopped {
                device: "safety",
                reason: format!("state value {i} is not finite; state rejected"),
            });
        }
        let now = self.clock.now();
        let age = now.saturating_sub(t);
        if age > self.cfg.state_timeout.as_nanos() as Nanos {
            self.stats.stale_states += 1;
            return Err(self.halt(format!("state is {} ms old", age / 1_000_000)));
        }
        self.t_state = Some(self.t_state.map_or(t, |old| old.max(t)));
        if let Some(r) = self.layout.torques.clone() {
            if out[r].iter().any(|x| x.abs() > self.cfg.torque_limit) {
                self.stats.torque_over += 1;
                self.torque_run += 1;
                if self.cfg.torque_stop_reads > 0 && self.torque_run >= self.cfg.torque_stop_reads {
                    let n = self.torque_run;
                    return Err(self.halt(format!(
                        "torque over {} for {n} consecutive reads",
                        self.cfg.torque_limit
                    )));
                }
            } else {
                self.torque_run = 0;
            }
        }
        let pos = &out[self.layout.positions.clone()];
        if let Some(target) = &self.last_target {
            let over =
                (0..pos.len()).find(|&i| (target[i] - pos[i]).abs() > self.cfg.tracking_error[i]);
            match over {
                Some(i) => {
                    self.stats.tracking_over += 1;
                    self.tracking_run += 1;
                    if self.tracking_run >= self.cfg.tracking_stop_reads {
                        let (n, err) = (self.tracking_run, (target[i] - pos[i]).abs());
                        return Err(self.halt(format!(
                            "joint {i} is {err:.3} rad from its target (bound {}) for {n} \
                             consecutive reads",
                            self.cfg.tracking_error[i]
                        )));
                    }
                }
                None => self.tracking_run = 0,
            }
        }
        match &mut self.last_pos {
            Some(p) => p.copy_from_slice(pos),
            None => self.last_pos = Some(pos.to_vec()),
        }
        Ok(t)
    }

    fn send(&mut self, action: &[f32]) -> Result<()> {
        self.check_stopped()?;
        let dim = self.robot.action_dim();
        Error::check_dim("safety targets", dim, action.len())?;
        self.stats.targets += 1;
        let now = self.clock.now();
        let period = self.cfg.period.as_secs_f64();
        // Seconds since the last target, capped at the nominal period (first: the period).
        let dt = self
            .t_send
            .map_or(period, |t| (now.saturating_sub(t) as f64 / 1e9).min(period))
            as f32;
        self.t_send = Some(now);
        if self.last_target.is_none() && self.last_pos.is_none() {
            let mut buf = std::mem::take(&mut self.state_buf);
            let r = self.read(&mut buf);
            self.state_buf = buf;
            r?;
        }
        let mut reference = std::mem::take(&mut self.ref_buf);
        reference.clear();
        match self.last_target.as_ref().or(self.last_pos.as_ref()) {
            Some(r) => reference.extend_from_slice(r),
            None => {
                self.ref_buf = reference;
                return Err(Error::Stopped {
                    device: "safety",
                    reason: "no measured position to start from".into(),
                });
            }
        }
        let mut target = std::mem::take(&mut self.target_buf);
        target.clear();
        if action.iter().any(|x| !x.is_finite()) {
            self.stats.non_finite_targets += 1;
            target.extend_from_slice(&reference);
            self.last_vel.fill(0.0);
        } else if self.torque_run > 0 {
            self.stats.torque_holds += 1;
            target.extend_from_slice(&reference);
            self.last_vel.fill(0.0);
        } else {
            let (mut lim, mut rate) = (false, false);
            for i in 0..dim {
                let (lo, hi) = (self.cfg.lower[i], self.cfg.upper[i]);
                let x = action[i].clamp(lo, hi);
                lim |= x != action[i];
                // Speed window: the speed limit, narrowed by the acceleration limit around
                // the last speed but always containing 0 (braking is never limited), so the
                // target moves from the reference toward `x` and never past it. The reference
                // may sit outside the joint limits (first target from a measured position).
                let r = reference[i];
                let y = if dt > 0.0 {
                    let vmax = self.cfg.max_velocity[i];
                    let dv = self.cfg.max_accel[i] * dt;
                    let v_prev = self.last_vel[i];
                    let v_lo = (v_prev - dv).min(0.0).max(-vmax);
                    let v_hi = (v_prev + dv).max(0.0).min(vmax);
                    let want = (x - r) / dt;
                    let v = want.clamp(v_lo, v_hi);
                    self.last_vel[i] = v;
                    if v == want {
                        x
                    } else {
                        r + v * dt
                    }
                } else {
                    self.last_vel[i] = 0.0;
                    r
                };
                rate |= y != x;
                target.push(y);
            }
            self.stats.limit_clamps += lim as u64;
            self.stats.rate_clamps += rate as u64;
        }
        let res = self.robot.send_targets(&target);
        match &mut self.last_target {
            Some(t) => t.copy_from_slice(&target),
            None => self.last_target = Some(target.clone()),
        }
        self.target_buf = target;
        self.ref_buf = reference;
        match res {
            Ok(()) => {
                self.error_run = 0;
                if let Some(fault) = self.robot.fault() {
                    self.stats.faults += 1;
                    return Err(
                        self.halt(format!("{} reports a fault: {fault}", self.robot.name()))
                    );
                }
                Ok(())
            }
            Err(e) => Err(self.robot_error(e)),
        }
    }
}

/// A [`Robot`] wrapped with limits, rate limits, torque holds, NaN rejection and a watchdog.
#[derive(Debug)]
pub struct SafetyLayer<R> {
    inner: Arc<Mutex<Inner<R>>>,
    watchdog: Option<(Arc<AtomicBool>, JoinHandle<()>)>,
    dims: (usize, usize),
    layout: StateLayout,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl<R: Robot + 'static> SafetyLayer<R> {
    /// Wrap `robot` (no watchdog thread yet; see [`SafetyLayer::spawn_watchdog`]).
    pub fn new(robot: R, cfg: SafetyConfig, clock: Arc<dyn Clock>) -> Result<Self> {
        let dim = robot.action_dim();
        cfg.validate(dim)?;
        let layout = robot.layout();
        Error::check_dim("safety: robot position range", dim, layout.positions.len())?;
        let dims = (robot.state_dim(), dim);
        let inner = Inner {
            state_buf: vec![0.0; robot.state_dim()],
            target_buf: Vec::with_capacity(dim),
            ref_buf: Vec::with_capacity(dim),
            robot,
            cfg,
            layout: layout.clone(),
            clock,
            last_target: None,
            last_pos: None,
            last_vel: vec![0.0; dim],
            t_send: None,
            t_state: None,
            torque_run: 0,
            tracking_run: 0,
            error_run: 0,
            stopped: None,
            stats: SafetyStats::default(),
        };
        Ok(Self {
            inner: Arc::new(Mutex::new(inner)),
            watchdog: None,
            dims,
            layout,
        })
    }

    /// Run [`SafetyLayer::check_watchdog`] every `poll` on a thread until the layer drops.
    pub fn spawn_watchdog(&mut self, poll: Duration) -> Result<()> {
        if self.watchdog.is_some() {
            return Ok(());
        }
        let halt = Arc::new(AtomicBool::new(false));
        let weak: Weak<Mutex<Inner<R>>> = Arc::downgrade(&self.inner);
        let h = halt.clone();
        let j = std::thread::Builder::new()
            .name("safety-watchdog".into())
            .spawn(move || {
                while !h.load(Ordering::SeqCst) {
                    std::thread::sleep(poll);
                    let Some(inner) = weak.upgrade() else { return };
                    let _ = lock(&inner).watchdog();
                }
            })
            .map_err(|e| Error::io("safety watchdog thread", e))?;
        self.watchdog = Some((halt, j));
        Ok(())
    }

    /// Check the command and state deadlines now; stops the robot and returns the stop error
    /// if one passed. Also returns the latched stop error if already stopped.
    pub fn check_watchdog(&self) -> Result<()> {
        lock(&self.inner).watchdog()
    }

    /// Counters so far.
    pub fn stats(&self) -> SafetyStats {
        lock(&self.inner).stats
    }

    /// Why the layer stopped the robot, if it did.
    pub fn stop_reason(&self) -> Option<String> {
        lock(&self.inner).stopped.clone()
    }

    /// Clear a latched stop. The next target is rate-limited from the measured position
    /// again. The wrapped driver may itself need a reconnect (see its docs).
    pub fn reset(&self) {
        let mut i = lock(&self.inner);
        i.stopped = None;
        i.last_target = None;
        i.t_send = None;
        i.t_state = None;
        i.torque_run = 0;
        i.tracking_run = 0;
        i.error_run = 0;
        i.last_vel.fill(0.0);
    }

    /// Run `f` on the wrapped robot.
    pub fn with_robot<T>(&self, f: impl FnOnce(&mut R) -> T) -> T {
        f(&mut lock(&self.inner).robot)
    }
}

impl<R> Drop for SafetyLayer<R> {
    fn drop(&mut self) {
        if let Some((halt, j)) = self.watchdog.take() {
            halt.store(true, Ordering::SeqCst);
            let _ = j.join();
        }
    }
}

impl<R: Robot + 'static> Robot for SafetyLayer<R> {
    fn name(&self) -> &'static str {
        "safety"
    }
    fn state_dim(&self) -> usize {
        self.dims.0
    }
    fn action_dim(&self) -> usize {
        self.dims.1
    }
    fn layout(&self) -> StateLayout {
        self.layout.clone()
    }
    fn read_state(&mut self, out: &mut [f32]) -> Result<Nanos> {
        lock(&self.inner).read(out)
    }
    fn send_targets(&mut self, targets: &[f32]) -> Result<()> {
        lock(&self.inner).send(targets)
    }
    fn stop(&mut self) -> Result<()> {
        let mut i = lock(&self.inner);
        if i.stopped.is_none() {
            i.stats.stops += 1;
            i.stopped = Some("stop() was called".into());
        }
        i.robot.stop()
    }
}
