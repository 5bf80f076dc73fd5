//! UFACTORY xArm6 over TCP: protocol ([`proto`], the reference for the wire format),
//! client ([`client`]) and the [`XArm6`] robot.
//!
//! # Connecting
//!
//! [`XArm6::connect`] reads the version string and refuses anything but a 6-axis arm on V1
//! firmware, then speaks what that firmware expects (protocol id 3 from 1.8.6 on, the
//! two-byte `SET_MODE` from 1.10.0 on). It reads the error and warning codes **before**
//! touching anything: a latched controller error (a collision, an emergency stop, a servo
//! fault) ends the connect with an error naming the code, and is cleared (`CLEAN_ERR`, and
//! `CLEAN_WAR` for a warning) only when [`XArm6Config::clear_errors`] is set — the CLI's
//! `--clear-errors`. Then it enables the motors, enters servo mode, sends `SET_STATE 0` and
//! checks that the controller left state 4/5 (a pressed emergency stop keeps it there).
//!
//! # Streaming
//!
//! In servo mode (mode 1) the controller executes only the newest servo-j target, at full
//! speed. A 25 Hz policy sending its targets directly would make the arm jump every 40 ms, so
//! [`XArm6`] runs a streaming thread: each policy target starts a linear ramp from the point
//! currently being streamed to the new target over one policy period
//! ([`XArm6Config::action_period`]), and the thread sends the ramp's value at
//! [`XArm6Config::stream_hz`] (100–250 Hz). A second thread reads the 30003 report stream and
//! keeps the newest joint angles and torques with the clock time they arrived.
//!
//! # Behaviour on stop and faults
//!
//! [`Robot::stop`] halts the streaming thread first (so no further servo-j leaves), then sends
//! `SET_STATE 4` (stop) and reads the state back (`GET_STATE`) until the controller confirms
//! it (state 4, or 5: not ready, which cannot move either). A request that fails (a timeout,
//! a broken connection: the command port is reopened) is retried every
//! [`STOP_RETRY_EVERY`] for up to [`STOP_WAIT`]; if the controller never confirms, `stop`
//! returns [`Error::Stopped`] naming the attempts and the last answer, so the caller knows the
//! arm may still hold servo mode, and dropping the driver tries once more. The driver refuses
//! new targets from the first call on; reconnect to move again.
//!
//! # When this process dies
//!
//! In servo mode the controller holds the last servo-j target it received; the protocol has
//! no dead-man input (the SDK's protocol id 3 only adds a keep-alive: its client sends
//! `GET_STATE` after 30 s without traffic and gives up after 90 s). A process killed without
//! [`Robot::stop`] therefore leaves a real arm standing at its last target in state 1:
//! `pir2 robot check` reports that state as not healthy, and the arm's emergency stop remains
//! the operator's last line. The emulator ([`crate::emu::xarm`]) stops the arm (state 4)
//! when the connection that moved it closes, which is what a dead process does to its
//! sockets.
//! A fault in the streaming thread (I/O error, timeout, framing error, controller error bit in
//! a reply, 10 consecutive replies with the not-ready bit) ends the thread — servo mode holds
//! the last target it received — and the fault is returned by the next
//! `send_targets`/`read_state`. A report with state 4 or 5 (a stop from the controller side,
//! e.g. an emergency stop) or a broken report stream is a fault too and also ends streaming.
//! A silent report stream leaves the state timestamp old, which the safety layer's watchdog
//! turns into a stop.
//!
//! Hardware tests live in `tests/hardware.rs` and are `#[ignore]`d.

pub mod client;
pub mod proto;

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use pir2_runtime::{Clock, Nanos};

use crate::error::{Error, Result};
use crate::robot::{Robot, StateLayout};
pub use client::{ClientStats, ReportReader, XArmClient};
use proto::{status, FirmwareVersion, ReportKind};

const DEVICE: &str = "xArm6";
/// Consecutive servo-j replies with the not-ready bit before the stream gives up.
const NOT_READY_LIMIT: u32 = 10;
/// How long [`Robot::stop`] keeps trying to get `SET_STATE 4` confirmed.
pub const STOP_WAIT: Duration = Duration::from_secs(1);
/// Pause between two attempts of [`Robot::stop`].
pub const STOP_RETRY_EVERY: Duration = Duration::from_millis(50);

/// Settings of an [`XArm6`].
#[derive(Debug, Clone)]
pub struct XArm6Config {
    /// Command port address (normally `<ip>:502`).
    pub cmd_addr: SocketAddr,
    /// Real-time report address (normally `<ip>:30003`). `None`: poll joint positions and
    /// torques on the command port from the streaming thread instead.
    pub report_addr: Option<SocketAddr>,
    /// Servo-j streaming rate, 100..=250 Hz.
    pub stream_hz: f64,
    /// Duration of the ramp to each new policy target (the policy period, 40 ms at 25 Hz).
    pub action_period: Duration,
    /// Connect and request timeout.
    pub timeout: Duration,
    /// Clear a latched controller error or warning at connect (`CLEAN_ERR` / `CLEAN_WAR`)
    /// instead of refusing to connect. Off by default: clearing a collision or emergency-stop
    /// error is the operator's decision.
    pub clear_errors: bool,
}

impl XArm6Config {
    /// Defaults for an arm at `ip`: ports 502 and 30003, 200 Hz streaming, 25 Hz policy.
    pub fn new(ip: std::net::IpAddr) -> Self {
        Self {
            cmd_addr: SocketAddr::new(ip, proto::PORT_CMD),
            report_addr: Some(SocketAddr::new(ip, proto::PORT_REPORT_REAL)),
            stream_hz: 200.0,
            action_period: Duration::from_millis(40),
            timeout: Duration::from_millis(500),
            clear_errors: false,
        }
    }
    /// Check ranges.
    pub fn validate(&self) -> Result<()> {
        if !(100.0..=250.0).contains(&self.stream_hz) {
            return Err(Error::Config(format!(
                "xArm stream_hz = {} must be in 100..=250",
                self.stream_hz
            )));
        }
        if self.action_period.is_zero() || self.action_period > Duration::from_secs(1) {
            return Err(Error::Config(format!(
                "xArm action_period = {:?} must be in (0, 1 s]",
                self.action_period
            )));
        }
        if self.timeout.is_zero() {
            return Err(Error::Config("xArm timeout must be > 0".into()));
        }
        Ok(())
    }
}

/// Linear ramp from the point being streamed to the newest policy target.
#[derive(Debug, Clone, PartialEq)]
pub struct Interpolator {
    from: [f32; 6],
    to: [f32; 6],
    t0: Nanos,
    duration: Nanos,
}

impl Interpolator {
    /// Hold `q` from the start.
    pub fn hold(q: [f32; 6], duration: Nanos) -> Self {
        Self {
            from: q,
            to: q,
            t0: 0,
            duration: duration.max(1),
        }
    }
    /// The streamed point at `t`.
    pub fn sample(&self, t: Nanos) -> [f32; 6] {
        let a = (t.saturating_sub(self.t0) as f64 / self.duration as f64).min(1.0) as f32;
        std::array::from_fn(|i| self.from[i] + a * (self.to[i] - self.from[i]))
    }
    /// Start a new ramp at `t` from the current point to `target`.
    pub fn retarget(&mut self, t: Nanos, target: [f32; 6]) {
        self.from = self.sample(t);
        self.to = target;
        self.t0 = t;
    }
    /// The final target of the current ramp.
    pub fn target(&self) -> [f32; 6] {
        self.to
    }
}

#[derive(Debug)]
struct Shared {
    interp: Interpolator,
    /// Newest state: joint angles (6), torques (6), and when it arrived.
    q: [f32; 6],
    tau: [f32; 6],
    t_state: Nanos,
    fault: Option<String>,
    sent: u64,
}

/// The xArm6 as a [`Robot`]: state = 6 joint angles + 6 joint torques, action = 6 joint
/// targets (rad).
#[derive(Debug)]
pub struct XArm6 {
    cfg: XArm6Config,
    clock: Arc<dyn Clock>,
    client: Arc<Mutex<XArmClient>>,
    shared: Arc<Mutex<Shared>>,
    halt: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
    version: String,
    firmware: FirmwareVersion,
    cleared: Option<(u8, u8)>,
    /// `stop()` was called: new targets are refused.
    stop_requested: bool,
    /// The controller confirmed the stop (state 4 or 5 read back).
    stopped: bool,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl XArm6 {
    /// Connect (see the module docs, "Connecting"), enable motors, enter servo mode, start
    /// streaming (holding the current position) and, if configured, reading the report
    /// stream.
    pub fn connect(cfg: XArm6Config, clock: Arc<dyn Clock>) -> Result<Self> {
        cfg.validate()?;
        let mut client = XArmClient::connect(cfg.cmd_addr, cfg.timeout, clock.clone())?;
        let firmware = client.identify()?;
        if let Some(axis) = firmware.axis.filter(|&a| a != 6) {
            return Err(Error::Config(format!(
                "the controller at {} reports {axis} axes (version {:?}); this driver drives an \
                 xArm6",
                cfg.cmd_addr, firmware.text
            )));
        }
        let version = firmware.text.clone();
        let (err, warn) = client.error_codes()?;
        let mut cleared = None;
        if err != 0 || warn != 0 {
            if !cfg.clear_errors && err != 0 {
                return Err(Error::Stopped {
                    device: DEVICE,
                    reason: format!(
                        "the controller has a latched error code {err} (warning code {warn}); \
                         it was not cleared. Check the arm (collision, emergency stop, servo \
                         fault), then connect with clear_errors (`--clear-errors`)"
                    ),
                });
            }
            if cfg.clear_errors {
                client.clean_error()?;
                client.clean_warning()?;
                let (e2, w2) = client.error_codes()?;
                if e2 != 0 {
                    return Err(Error::Stopped {
                        device: DEVICE,
                        reason: format!(
                            "controller error code {err} did not clear (now {e2}, warning {w2})"
                        ),
                    });
                }
                cleared = Some((err, warn));
            }
        }
        let st = client.motion_enable(true)?;
        fail_on_error_bit(&mut client, st, "MOTION_EN")?;
        let st = client.set_mode(proto::MODE_SERVO)?;
        fail_on_error_bit(&mut client, st, "SET_MODE 1")?;
        let st = client.set_state(proto::state::GO)?;
        fail_on_error_bit(&mut client, st, "SET_STATE 0")?;
        wait_ready(&mut client, clock.as_ref(), cfg.timeout)?;
        let (q7, t7) = read_joints(&mut client, &firmware)?;
        let mut q = [0f32; 6];
        q.copy_from_slice(&q7[..6]);
        let mut tau = [0f32; 6];
        tau.copy_from_slice(&t7[..6]);
        let period = cfg.action_period.as_nanos() as Nanos;
        let shared = Arc::new(Mutex::new(Shared {
            interp: Interpolator::hold(q, period),
            q,
            tau,
            t_state: clock.now(),
            fault: None,
            sent: 0,
        }));
        let client = Arc::new(Mutex::new(client));
        let halt = Arc::new(AtomicBool::new(false));
        let mut threads = Vec::new();
        if let Some(addr) = cfg.report_addr {
            let reader = ReportReader::connect(addr, ReportKind::Real, cfg.timeout)?;
            let (client, shared, halt, clock) =
                (client.clone(), shared.clone(), halt.clone(), clock.clone());
            threads.push(
                std::thread::Builder::new()
                    .name("xarm-report".into())
                    .spawn(move || report_loop(reader, client, shared, halt, clock))
                    .map_err(|e| Error::io("xArm report thread", e))?,
            );
        }
        {
            let (client, shared, halt, clock) =
                (client.clone(), shared.clone(), halt.clone(), clock.clone());
            let period_ns = (1e9 / cfg.stream_hz) as Nanos;
            let poll_state = cfg.report_addr.is_none().then(|| firmware.clone());
            threads.push(
                std::thread::Builder::new()
                    .name("xarm-servo".into())
                    .spawn(move || stream_loop(client, shared, halt, clock, period_ns, poll_state))
                    .map_err(|e| Error::io("xArm streaming thread", e))?,
            );
        }
        Ok(Self {
            cfg,
            clock,
            client,
            shared,
            halt,
            threads,
            version,
            firmware,
            cleared,
            stop_requested: false,
            stopped: false,
        })
    }

    /// The parsed firmware version.
    pub fn firmware(&self) -> &FirmwareVersion {
        &self.firmware
    }
    /// `(error, warning)` codes cleared at connect (only with
    /// [`XArm6Config::clear_errors`]).
    pub fn cleared_at_connect(&self) -> Option<(u8, u8)> {
        self.cleared
    }

    /// Firmware version read at connect.
    pub fn version(&self) -> &str {
        &self.version
    }
    /// Number of servo-j frames streamed so far.
    pub fn streamed(&self) -> u64 {
        lock(&self.shared).sent
    }
    /// The configuration.
    pub fn config(&self) -> &XArm6Config {
        &self.cfg
    }
    /// Client counters (requests, skipped stale replies).
    pub fn client_stats(&self) -> ClientStats {
        lock(&self.client).stats()
    }

    fn check_fault(&self) -> Result<()> {
        if self.stop_requested {
            return Err(Error::Stopped {
                device: DEVICE,
                reason: "stop() was called".into(),
            });
        }
        if let Some(f) = &lock(&self.shared).fault {
            return Err(Error::Stopped {
                device: DEVICE,
                reason: f.clone(),
            });
        }
        Ok(())
    }

    /// One attempt at a confirmed stop: reopen the command port if it is closed, send
    /// `SET_STATE 4`, read the state back.
    fn stop_once(&self) -> Result<u8> {
        let mut c = lock(&self.client);
        if !c.is_open() {
            let mut fresh =
                XArmClient::connect(self.cfg.cmd_addr, self.cfg.timeout, self.clock.clone())?;
            fresh.identify()?;
            *c = fresh;
        }
        c.set_state(proto::state::STOP)?;
        c.state()
    }

    fn halt_threads(&mut self) {
        self.halt.store(true, Ordering::SeqCst);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// After a command whose reply has the error bit: fail with the controller's codes.
fn fail_on_error_bit(client: &mut XArmClient, st: u8, what: &str) -> Result<()> {
    if st & status::ERROR == 0 {
        return Ok(());
    }
    let (error, warning) = client.error_codes()?;
    Err(Error::Stopped {
        device: DEVICE,
        reason: format!("controller error code {error} (warning {warning}) after {what}"),
    })
}

/// Wait (up to `timeout`) for the controller to leave states 4/5 after `SET_STATE 0`.
fn wait_ready(client: &mut XArmClient, clock: &dyn Clock, timeout: Duration) -> Result<()> {
    let t0 = clock.now();
    loop {
        let st = client.state()?;
        if st != proto::state::STOP && st != proto::state::NOT_READY {
            return Ok(());
        }
        if clock.now().saturating_sub(t0) >= timeout.as_nanos() as Nanos {
            let (error, warning) = client.error_codes()?;
            return Err(Error::Stopped {
                device: DEVICE,
                reason: format!(
                    "the controller stays in state {st} after enable, servo mode and SET_STATE \
                     0 (error code {error}, warning {warning}): emergency stop pressed?"
                ),
            });
        }
        clock.sleep_until(clock.now() + 10_000_000);
    }
}

/// Measured joint positions and torques: one `GET_JOINT_POS [3]` where the firmware has it,
/// else `GET_JOINT_POS` + `GET_JOINT_TAU`.
fn read_joints(client: &mut XArmClient, fw: &FirmwareVersion) -> Result<([f32; 7], [f32; 7])> {
    if fw.has_joint_states() {
        client.joint_states()
    } else {
        Ok((client.joint_positions()?, client.joint_torques()?))
    }
}

fn report_loop(
    mut reader: ReportReader,
    client: Arc<Mutex<XArmClient>>,
    shared: Arc<Mutex<Shared>>,
    halt: Arc<AtomicBool>,
    clock: Arc<dyn Clock>,
) {
    while !halt.load(Ordering::SeqCst) {
        match reader.poll() {
            Ok(Some(r)) => {
                let t = clock.now();
                let stopped = {
                    let mut s = lock(&shared);
                    s.q.copy_from_slice(&r.angles[..6]);
                    s.tau.copy_from_slice(&r.torques[..6]);
                    s.t_state = t;
                    // States 4 (stop) and 5 are "not ready" (SDK report handler): an
                    // emergency stop or a controller-side stop. Servo-j is ignored from then on.
                    s.fault.is_none() && (r.state == proto::state::STOP || r.state == 5)
                };
                if stopped {
                    // The real-time report carries no error code: ask the command port once,
                    // so the one error names the controller's code when it has one (the
                    // `shared` lock is not held here: the servo thread takes the client first).
                    let codes = lock(&client).error_codes();
                    let reason = match codes {
                        Ok((error, warning)) if error != 0 => format!(
                            "controller error code {error} (warning {warning}); controller \
                             reports state {} (stopped)",
                            r.state
                        ),
                        _ => format!("controller reports state {} (stopped)", r.state),
                    };
                    lock(&shared).fault.get_or_insert(reason);
                }
            }
            Ok(None) => {}
            Err(e) => {
                // Keep the old timestamp: the state goes stale and the watchdog stops the arm.
                let mut s = lock(&shared);
                s.fault.get_or_insert_with(|| format!("report stream: {e}"));
                return;
            }
        }
    }
}

fn stream_loop(
    client: Arc<Mutex<XArmClient>>,
    shared: Arc<Mutex<Shared>>,
    halt: Arc<AtomicBool>,
    clock: Arc<dyn Clock>,
    period: Nanos,
    poll_state: Option<FirmwareVersion>,
) {
    let mut next = clock.now();
    let mut not_ready = 0u32;
    while !halt.load(Ordering::SeqCst) {
        let t = clock.now();
        let q = {
            let s = lock(&shared);
            if s.fault.is_some() {
                return;
            }
            s.interp.sample(t)
        };
        let res = {
            let mut c = lock(&client);
            c.servo_j(&q).and_then(|st| {
                if st & status::ERROR != 0 {
                    let (error, warning) = c.error_codes().unwrap_or((0, 0));
                    return Err(Error::XArmController { error, warning });
                }
                if st & status::NOT_READY != 0 {
                    not_ready += 1;
                    if not_ready >= NOT_READY_LIMIT {
                        return Err(Error::Stopped {
                            device: DEVICE,
                            reason: format!(
                                "controller not ready for {not_ready} servo-j frames in a row"
                            ),
                        });
                    }
                } else {
                    not_ready = 0;
                }
                if let Some(fw) = &poll_state {
                    let (qp, tp) = read_joints(&mut c, fw)?;
                    let now = clock.now();
                    let mut s = lock(&shared);
                    s.q.copy_from_slice(&qp[..6]);
                    s.tau.copy_from_slice(&tp[..6]);
                    s.t_state = now;
                }
                Ok(())
            })
        };
        match res {
            Ok(()) => lock(&shared).sent += 1,
            Err(e) => {
                lock(&shared)
                    .fault
                    .get_or_insert_with(|| format!("streaming: {e}"));
                return;
            }
        }
        next += period;
        let now = clock.now();
        if next < now {
            // Overran (e.g. a blocking reply): restart the schedule instead of bursting.
            next = now;
        }
        clock.sleep_until(next);
    }
}

impl Robot for XArm6 {
    fn name(&self) -> &'static str {
        DEVICE
    }
    fn state_dim(&self) -> usize {
        12
    }
    fn action_dim(&self) -> usize {
        6
    }
    fn layout(&self) -> StateLayout {
        StateLayout {
            positions: 0..6,
            torques: Some(6..12),
        }
    }
    fn read_state(&mut self, out: &mut [f32]) -> Result<Nanos> {
        Error::check_dim("xArm6 state", 12, out.len())?;
        self.check_fault()?;
        let s = lock(&self.shared);
        out[..6].copy_from_slice(&s.q);
        out[6..].copy_from_slice(&s.tau);
        Ok(s.t_state)
    }
    fn send_targets(&mut self, targets: &[f32]) -> Result<()> {
        Error::check_dim("xArm6 targets", 6, targets.len())?;
        self.check_fault()?;
        let mut q = [0f32; 6];
        q.copy_from_slice(targets);
        let t = self.clock.now();
        lock(&self.shared).interp.retarget(t, q);
        Ok(())
    }
    fn stop(&mut self) -> Result<()> {
        self.halt_threads();
        self.stop_requested = true;
        if self.stopped {
            return Ok(());
        }
        let t0 = std::time::Instant::now();
        let mut attempts = 0u32;
        let last = loop {
            attempts += 1;
            let answer = match self.stop_once() {
                Ok(proto::state::STOP | proto::state::NOT_READY) => {
                    self.stopped = true;
                    return Ok(());
                }
                Ok(st) => format!("the controller still reports state {st}"),
                Err(e) => e.to_string(),
            };
            if t0.elapsed() + STOP_RETRY_EVERY > STOP_WAIT {
                break answer;
            }
            std::thread::sleep(STOP_RETRY_EVERY);
        };
        Err(Error::Stopped {
            device: DEVICE,
            reason: format!(
                "streaming halted, but SET_STATE 4 was not confirmed after {attempts} attempts \
                 in {} ms (last: {last}); the arm may hold its last target in servo mode: use \
                 its emergency stop",
                t0.elapsed().as_millis()
            ),
        })
    }
    /// The fault that ended streaming (a controller error code, a stop from the controller
    /// side, a broken connection), if any: the safety layer stops the whole robot on it at
    /// once instead of counting driver errors.
    fn fault(&self) -> Option<String> {
        lock(&self.shared).fault.clone()
    }
}

impl Drop for XArm6 {
    fn drop(&mut self) {
        if !self.stopped {
            let _ = self.stop();
        }
        self.halt_threads();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolator_ramps_over_one_period_then_holds() {
        let mut it = Interpolator::hold([0.0; 6], 40);
        it.retarget(100, [1.0, 2.0, 0.0, 0.0, 0.0, -4.0]);
        assert_eq!(it.sample(100), [0.0; 6]);
        assert_eq!(it.sample(120), [0.5, 1.0, 0.0, 0.0, 0.0, -2.0]);
        assert_eq!(it.sample(140), [1.0, 2.0, 0.0, 0.0, 0.0, -4.0]);
        assert_eq!(it.sample(1000), [1.0, 2.0, 0.0, 0.0, 0.0, -4.0]);
    }

    #[test]
    fn interpolator_retarget_mid_ramp_starts_from_the_streamed_point() {
        let mut it = Interpolator::hold([0.0; 6], 40);
        it.retarget(0, [1.0; 6]);
        it.retarget(20, [0.0; 6]);
        assert_eq!(it.sample(20), [0.5; 6]);
        assert_eq!(it.sample(40), [0.25; 6]);
        assert_eq!(it.target(), [0.0; 6]);
    }

    #[test]
    fn config_rejects_stream_rates_outside_100_to_250_hz() {
        let mut c = XArm6Config::new([127, 0, 0, 1].into());
        assert!(c.validate().is_ok());
        c.stream_hz = 50.0;
        assert!(matches!(c.validate(), Err(Error::Config(m)) if m.contains("stream_hz")));
        c.stream_hz = 300.0;
        assert!(c.validate().is_err());
    }
}
