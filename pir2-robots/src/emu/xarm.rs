//! Loopback xArm6 emulator: a TCP server speaking the protocol of [`crate::xarm::proto`]
//! byte for byte as current firmware does (see that module's reference), on a command port
//! and the three report ports, with simple joint dynamics and fault injection.
//!
//! One file on purpose: the register table, the command handlers and the motion model are one
//! state machine, read against the protocol module line by line.
//!
//! Ports: the standard ones (502, 30001 normal, 30002 rich, 30003 real) with
//! [`XArmPorts::standard`], or ephemeral ones (port 0, chosen by the OS) with
//! [`XArmPorts::ephemeral`]; [`XArmEmulator::cmd_addr`] and [`XArmEmulator::report_addr`] tell
//! where it listens.
//!
//! What it says about itself: the version string [`XARM_EMU_VERSION`]
//! (`6,6,XI1304,AC1303,v2.6.0`: 6 axes, type 6, firmware 2.6.0, so clients switch to
//! protocol id 3 and send the two-byte `SET_MODE`); every reply echoes the request's
//! protocol id. Reports: 135-byte real frames at 100 Hz, 145-byte normal and 587-byte rich
//! frames at 5 Hz ([`XArmEmuOptions::legacy_reports`] switches to the 87 / 133 / 233-byte
//! frames of old firmware). The rich frames carry type 6, axis 6, the SDK's default motion
//! limits, sensitivities 3, gravity `[0, 0, -1]`, the simulation flag cleared.
//!
//! Behaviour: the arm starts stopped (state 4), mode 0, motors disabled. `MOTION_EN [8, 1]`,
//! `SET_MODE [1, 0]` (or `[1]`) and `SET_STATE [0]` make it ready (state 2); servo-j is then
//! applied (state 1) and each joint moves toward its target at up to [`ARM_MAX_SPEED`] rad/s
//! (joint 7 of the request is ignored: a 6-axis arm). The not-ready status bit is set while
//! the motors are disabled, the state is 4 or 5 or an error is latched, and on servo-j
//! outside servo mode; such a servo-j is ignored. An injected error code stops the arm and
//! sets the error bit in every reply until `CLEAN_ERR`; after that the arm needs
//! `MOTION_EN`/`SET_STATE 0` again. The SDK's heartbeat frame (protocol id 1) gets no answer.
//! Unknown registers answer with the invalid bit.
//!
//! Client loss: when the command connection whose servo-j last moved the arm closes while
//! the arm is moving (state 1), the arm stops (state 4) and [`ArmSim::client_loss_stops`]
//! counts it. A process that dies without stopping the arm closes its sockets, so a killed
//! `pir2 gr00t run` leaves the emulated arm stopped, not in motion. (A real controller holds its
//! last servo target instead; see [`crate::xarm`], "When this process dies".)

use std::collections::VecDeque;
use std::io::{ErrorKind, Write};
use std::net::{IpAddr, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use pir2_runtime::{Clock, Nanos, SystemClock};

use crate::error::{Error, Result};
use crate::xarm::proto::{
    self, reg, state, status, Command, FrameBuf, Reply, Report, ReportKind, RichInfo,
};

/// Joint speed limit of the emulated arm, rad/s.
pub const ARM_MAX_SPEED: f32 = 3.0;
/// Version string the emulator reports (format of current firmware).
/// (Real controllers put the 6-character serial-number prefixes here, which keeps the string
/// well under the 40-byte reply: the SDK cuts it at the first NUL.)
pub const XARM_EMU_VERSION: &str = "6,6,XI1304,AC1303,v2.6.0";
/// Robot serial number the emulator reports.
pub const XARM_EMU_SN: &str = "XI130400000001";
/// Joint angles the emulated arm starts at, rad.
pub const ARM_HOME: [f32; 7] = [0.0, -0.3, -0.5, 0.0, 0.8, 0.0, 0.0];
/// Collision and teach sensitivity the emulator reports.
pub const EMU_SENSITIVITY: u8 = 3;
/// Motion limits of the rich report: the SDK's defaults (TCP jerk, TCP min/max acc, TCP
/// min/max speed, joint jerk, joint min/max acc, joint min/max speed, rotation jerk, rotation
/// max acc).
pub const EMU_LIMITS: [f32; 12] = [
    1000.0, 1.0, 50000.0, 0.1, 1000.0, 20.0, 0.01, 20.0, 0.0001, 4.0, 2.3, 2.7,
];

/// Which ports to listen on; `None` leaves a report stream out, `Some(0)` picks a free port.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct XArmPorts {
    /// Command port.
    pub cmd: u16,
    /// "Normal" report port.
    pub report_normal: Option<u16>,
    /// "Rich" report port.
    pub report_rich: Option<u16>,
    /// "Real" report port.
    pub report_real: Option<u16>,
}

impl XArmPorts {
    /// 502, 30001, 30002, 30003.
    pub fn standard() -> Self {
        Self {
            cmd: proto::PORT_CMD,
            report_normal: Some(proto::PORT_REPORT_NORMAL),
            report_rich: Some(proto::PORT_REPORT_RICH),
            report_real: Some(proto::PORT_REPORT_REAL),
        }
    }
    /// All four on OS-chosen free ports (for tests).
    pub fn ephemeral() -> Self {
        Self {
            cmd: 0,
            report_normal: Some(0),
            report_rich: Some(0),
            report_real: Some(0),
        }
    }
}

/// What the emulated controller looks like.
#[derive(Debug, Clone, PartialEq)]
pub struct XArmEmuOptions {
    /// GET_VERSION answer.
    pub version: String,
    /// Send the frame sizes of old firmware (87 real, 133 normal, 233 rich) instead of the
    /// current ones (135, 145, 587).
    pub legacy_reports: bool,
}

impl Default for XArmEmuOptions {
    fn default() -> Self {
        Self {
            version: XARM_EMU_VERSION.into(),
            legacy_reports: false,
        }
    }
}

impl XArmEmuOptions {
    /// The frame size of the stream `kind`.
    pub fn report_len(&self, kind: ReportKind) -> usize {
        if self.legacy_reports {
            kind.min_len()
        } else {
            kind.current_len()
        }
    }
}

/// A fault for the emulator to act out. Command faults apply to the next request on any
/// command connection; report faults to the next report frame on any report connection.
#[derive(Debug, Clone, PartialEq)]
pub enum XArmFault {
    /// Close the command connection instead of answering.
    DropConnection,
    /// Wait this long before answering.
    Stall(Duration),
    /// Send the first half of the reply, then close.
    Truncated,
    /// Send these bytes instead of the reply.
    Garbage(Vec<u8>),
    /// Send a reply with another transaction id first, then the right one (a late reply).
    WrongTid,
    /// Answer with another protocol id than the request's.
    WrongProtocol,
    /// Latch a controller error code (until CLEAN_ERR; the arm stops), e.g. a collision (31)
    /// or an emergency stop (1, 2).
    ErrorCode(u8),
    /// Stop the arm from the controller side (state 4, no error).
    EmergencyStop,
    /// Pause the report stream this long.
    ReportStall(Duration),
    /// Close the report connection.
    ReportDisconnect,
    /// Send a report frame with a different size header.
    ReportGarbage,
}

/// Emulated arm state.
#[derive(Debug, Clone)]
pub struct ArmSim {
    /// Joint angles, rad.
    pub q: [f32; 7],
    /// Joint velocities, rad/s.
    pub dq: [f32; 7],
    /// Servo targets, rad.
    pub target: [f32; 7],
    /// Joint torques.
    pub tau: [f32; 7],
    /// Control mode.
    pub mode: u8,
    /// Motion state.
    pub state: u8,
    /// Motors enabled.
    pub enabled: bool,
    /// Error code.
    pub error: u8,
    /// Warning code.
    pub warning: u8,
    /// Servo-j frames applied.
    pub servoj: u64,
    /// Stops because the connection that moved the arm closed (see the module docs).
    pub client_loss_stops: u64,
    /// The command connection whose servo-j last moved the arm.
    owner: Option<u64>,
    /// Requests answered.
    pub requests: u64,
    /// CLEAN_ERR requests received.
    pub clean_err: u64,
    /// Parameters of the last SET_MODE request.
    pub set_mode_params: Vec<u8>,
    /// Protocol id of the last request.
    pub last_proto: u16,
    counter: u32,
    t: Option<Nanos>,
}

impl ArmSim {
    fn new() -> Self {
        Self {
            q: ARM_HOME,
            dq: [0.0; 7],
            target: ARM_HOME,
            tau: [0.0; 7],
            mode: 0,
            state: state::STOP,
            enabled: false,
            error: 0,
            warning: 0,
            servoj: 0,
            client_loss_stops: 0,
            owner: None,
            requests: 0,
            clean_err: 0,
            set_mode_params: Vec::new(),
            last_proto: 0,
            counter: 0,
            t: None,
        }
    }
    /// Enabled, no error, not stopped: motion commands are taken.
    fn ready(&self) -> bool {
        self.enabled && self.error == 0 && !matches!(self.state, state::STOP | state::NOT_READY)
    }
    fn servo_ready(&self) -> bool {
        self.ready() && self.mode == proto::MODE_SERVO
    }
    fn advance(&mut self, now: Nanos) {
        let dt = self.t.map_or(0.0, |t| now.saturating_sub(t) as f32 * 1e-9);
        self.t = Some(now);
        let moving = self.servo_ready();
        for i in 0..7 {
            let before = self.q[i];
            if moving {
                let step = ARM_MAX_SPEED * dt;
                self.q[i] += (self.target[i] - self.q[i]).clamp(-step, step);
            }
            self.dq[i] = if dt > 0.0 {
                (self.q[i] - before) / dt
            } else {
                0.0
            };
            // A stiff servo plus a gravity-like load on the shoulder and elbow.
            let load = if i == 1 || i == 2 {
                2.0 * self.q[i].sin()
            } else {
                0.0
            };
            self.tau[i] = if i < 6 {
                5.0 * (self.target[i] - self.q[i]) + load
            } else {
                0.0
            };
        }
    }
    fn status(&self, servo: bool) -> u8 {
        let mut s = 0;
        if self.error != 0 {
            s |= status::ERROR;
        }
        if self.warning != 0 {
            s |= status::WARNING;
        }
        let ready = if servo {
            self.servo_ready()
        } else {
            self.ready()
        };
        if !ready {
            s |= status::NOT_READY;
        }
        s
    }
    fn report(&mut self, kind: ReportKind, version: &str) -> Report {
        let bits = if self.enabled { 0x3f } else { 0 };
        let mut r = Report {
            state: self.state,
            mode: self.mode,
            cmd_num: 0,
            angles: self.q,
            pose: [200.0, 0.0, 300.0, std::f32::consts::PI, 0.0, 0.0],
            torques: self.tau,
            ft: Some(([0.0; 6], [0.0; 6])),
            brake_bits: bits,
            enable_bits: bits,
            error: self.error,
            warning: self.warning,
            collision_sens: EMU_SENSITIVITY,
            teach_sens: EMU_SENSITIVITY,
            gravity: Some([0.0, 0.0, -1.0]),
            ..Report::default()
        };
        if kind == ReportKind::Rich {
            self.counter = self.counter.wrapping_add(1);
            // The version field holds the version number part of the string.
            let mut text = [0u8; 30];
            let v = version.rsplit(',').next().unwrap_or("").as_bytes();
            let n = v.len().min(30);
            text[..n].copy_from_slice(&v[..n]);
            r.rich = Some(RichInfo {
                arm_type: 6,
                axis: 6,
                version: text,
                limits: EMU_LIMITS,
                servo_codes: [0; 16],
                temperatures: Some([30; 7]),
                counter: Some(self.counter),
                simulation: Some(false),
                collision_detection: Some(true),
            });
        }
        r
    }
    /// Command connection `conn` closed: if its servo-j moved the arm and the arm is still
    /// moving, stop it.
    fn client_gone(&mut self, conn: u64) {
        if self.owner == Some(conn) {
            self.owner = None;
            if self.state == state::MOVING {
                self.state = state::STOP;
                self.client_loss_stops += 1;
            }
        }
    }
    /// Answer one request of command connection `conn`: `(status, data)`.
    fn handle(&mut self, c: &Command, version: &str, conn: u64) -> (u8, Vec<u8>) {
        self.requests += 1;
        self.last_proto = c.proto;
        let mut data = Vec::new();
        let mut invalid = false;
        let mut servo = false;
        let ascii40 = |s: &str| {
            let mut d = s.as_bytes().to_vec();
            d.resize(proto::VERSION_LEN, 0);
            d
        };
        match c.register {
            reg::GET_VERSION => data = ascii40(version),
            reg::GET_ROBOT_SN => data = ascii40(XARM_EMU_SN),
            reg::MOTION_EN => match c.params.as_slice() {
                [axis, on] if *axis == proto::AXIS_ALL || (1..=6).contains(axis) => {
                    self.enabled = *on != 0;
                    if !self.enabled {
                        self.state = state::STOP;
                    }
                }
                _ => invalid = true,
            },
            reg::SET_STATE => match c.params.as_slice() {
                [s] if *s == state::GO => {
                    if self.enabled && self.error == 0 {
                        self.state = state::SLEEPING;
                        self.target = self.q;
                    }
                }
                [s] if *s == state::PAUSE || *s == state::STOP => self.state = *s,
                _ => invalid = true,
            },
            reg::GET_STATE => data = vec![self.state],
            reg::GET_CMDNUM => data = vec![0, 0],
            reg::GET_ERROR => data = vec![self.error, self.warning],
            reg::CLEAN_ERR => {
                self.clean_err += 1;
                if self.error != 0 {
                    // Clearing does not re-arm: enable and SET_STATE 0 again.
                    self.error = 0;
                    self.enabled = false;
                    self.state = state::STOP;
                }
            }
            reg::CLEAN_WAR => self.warning = 0,
            reg::SET_MODE => match c.params.as_slice() {
                [m] | [m, _] if *m <= 7 => {
                    self.mode = *m;
                    self.set_mode_params = c.params.clone();
                    // The controller needs SET_STATE 0 after a mode change.
                    self.state = state::STOP;
                }
                _ => invalid = true,
            },
            reg::MOVE_SERVOJ => {
                servo = true;
                if c.params.len() != 40 {
                    invalid = true;
                } else if self.servo_ready() {
                    let mut v = [0f32; 10];
                    let _ = proto::read_fp32s_le(&c.params, &mut v);
                    if v[..7].iter().all(|x| x.is_finite()) {
                        self.target[..6].copy_from_slice(&v[..6]);
                        self.state = state::MOVING;
                        self.servoj += 1;
                        self.owner = Some(conn);
                    } else {
                        invalid = true;
                    }
                }
            }
            reg::GET_TCP_POSE => {
                data = proto::fp32s_le(&[200.0, 0.0, 300.0, std::f32::consts::PI, 0.0, 0.0])
            }
            reg::GET_JOINT_POS => match c.params.as_slice() {
                [] => data = proto::fp32s_le(&self.q),
                [n] if (1..=3).contains(&(n & 0x0f)) => {
                    let blocks = [self.q, self.dq, self.tau];
                    for b in &blocks[..(n & 0x0f) as usize] {
                        data.extend(proto::fp32s_le(b));
                    }
                }
                _ => invalid = true,
            },
            reg::GET_JOINT_TAU => data = proto::fp32s_le(&self.tau),
            _ => invalid = true,
        }
        let st = self.status(servo) | if invalid { status::INVALID } else { 0 };
        (st, data)
    }
}

#[derive(Debug, Default)]
struct Faults {
    cmd: VecDeque<XArmFault>,
    report: VecDeque<XArmFault>,
}

/// A shared view of a running emulator.
#[derive(Debug, Clone)]
pub struct XArmEmuHandle {
    sim: Arc<Mutex<ArmSim>>,
    faults: Arc<Mutex<Faults>>,
    stop: Arc<AtomicBool>,
    clock: Arc<dyn Clock>,
    opts: Arc<XArmEmuOptions>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl XArmEmuHandle {
    /// Queue a fault.
    pub fn inject(&self, f: XArmFault) {
        let mut q = lock(&self.faults);
        match f {
            XArmFault::ReportStall(_) | XArmFault::ReportDisconnect | XArmFault::ReportGarbage => {
                q.report.push_back(f)
            }
            XArmFault::EmergencyStop => {
                drop(q);
                lock(&self.sim).state = state::STOP;
            }
            XArmFault::ErrorCode(code) => {
                drop(q);
                let mut s = lock(&self.sim);
                s.error = code;
                s.state = state::STOP;
            }
            _ => q.cmd.push_back(f),
        }
    }
    /// Latch a warning code (cleared by CLEAN_WAR).
    pub fn set_warning(&self, code: u8) {
        lock(&self.sim).warning = code;
    }
    /// A snapshot of the emulated arm (advanced to now).
    pub fn sim(&self) -> ArmSim {
        let mut s = lock(&self.sim);
        s.advance(self.clock.now());
        s.clone()
    }
    /// Ask every emulator thread to end.
    pub fn shutdown(&self) {
        self.stop.store(true, Ordering::SeqCst);
    }
}

/// A running emulator.
#[derive(Debug)]
pub struct XArmEmulator {
    handle: XArmEmuHandle,
    cmd_addr: SocketAddr,
    reports: Vec<(ReportKind, SocketAddr)>,
    threads: Vec<JoinHandle<()>>,
}

impl XArmEmulator {
    /// Listen on `host` (use 127.0.0.1) at `ports`, until [`XArmEmulator::shutdown`] or drop.
    pub fn spawn(host: IpAddr, ports: XArmPorts) -> Result<Self> {
        Self::spawn_with_stop(host, ports, Arc::new(AtomicBool::new(false)))
    }

    /// Like [`XArmEmulator::spawn`], also ending when `stop` is set.
    pub fn spawn_with_stop(host: IpAddr, ports: XArmPorts, stop: Arc<AtomicBool>) -> Result<Self> {
        Self::spawn_with(host, ports, stop, XArmEmuOptions::default())
    }

    /// Like [`XArmEmulator::spawn_with_stop`], looking like `opts` says.
    pub fn spawn_with(
        host: IpAddr,
        ports: XArmPorts,
        stop: Arc<AtomicBool>,
        opts: XArmEmuOptions,
    ) -> Result<Self> {
        let handle = XArmEmuHandle {
            sim: Arc::new(Mutex::new(ArmSim::new())),
            faults: Arc::new(Mutex::new(Faults::default())),
            stop,
            clock: Arc::new(SystemClock::new()),
            opts: Arc::new(opts),
        };
        let bind = |port: u16| -> Result<TcpListener> {
            let addr = SocketAddr::new(host, port);
            let l = TcpListener::bind(addr).map_err(|source| Error::Connect {
                channel: "xArm emulator bind",
                addr,
                source,
            })?;
            l.set_nonblocking(true)
                .map_err(|e| Error::io("xArm emulator", e))?;
            Ok(l)
        };
        let cmd = bind(ports.cmd)?;
        let cmd_addr = cmd
            .local_addr()
            .map_err(|e| Error::io("xArm emulator", e))?;
        let mut threads = Vec::new();
        let h = handle.clone();
        threads.push(spawn_named("xarm-emu-cmd", move || {
            accept_loop(cmd, h, Role::Cmd)
        })?);
        let mut reports = Vec::new();
        for (port, kind, period) in [
            (
                ports.report_real,
                ReportKind::Real,
                Duration::from_millis(10),
            ),
            (
                ports.report_normal,
                ReportKind::Normal,
                Duration::from_millis(200),
            ),
            (
                ports.report_rich,
                ReportKind::Rich,
                Duration::from_millis(200),
            ),
        ] {
            let Some(port) = port else { continue };
            let l = bind(port)?;
            let addr = l.local_addr().map_err(|e| Error::io("xArm emulator", e))?;
            reports.push((kind, addr));
            let h = handle.clone();
            threads.push(spawn_named("xarm-emu-report", move || {
                accept_loop(l, h, Role::Report { kind, period })
            })?);
        }
        Ok(Self {
            handle,
            cmd_addr,
            reports,
            threads,
        })
    }

    /// Where the command port listens.
    pub fn cmd_addr(&self) -> SocketAddr {
        self.cmd_addr
    }
    /// Where the report stream `kind` listens, if served.
    pub fn report_addr(&self, kind: ReportKind) -> Option<SocketAddr> {
        self.reports.iter().find(|(k, _)| *k == kind).map(|r| r.1)
    }
    /// The real-time (30003) report address, if served.
    pub fn real_report_addr(&self) -> Option<SocketAddr> {
        self.report_addr(ReportKind::Real)
    }
    /// The shared view.
    pub fn handle(&self) -> &XArmEmuHandle {
        &self.handle
    }
    /// Stop all threads and wait for them.
    pub fn shutdown(mut self) {
        self.stop_and_join();
    }
    fn stop_and_join(&mut self) {
        self.handle.shutdown();
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl Drop for XArmEmulator {
    fn drop(&mut self) {
        self.stop_and_join();
    }
}

/// Run an xArm emulator on `host` at `ports` until `stop` is set (blocking). Use
/// [`XArmPorts::standard`] to stand in for a real arm at `host`.
pub fn run_xarm_emulator(host: IpAddr, ports: XArmPorts, stop: Arc<AtomicBool>) -> Result<()> {
    let emu = XArmEmulator::spawn_with_stop(host, ports, stop.clone())?;
    while !stop.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(20));
    }
    emu.shutdown();
    Ok(())
}

fn spawn_named(name: &str, f: impl FnOnce() + Send + 'static) -> Result<JoinHandle<()>> {
    std::thread::Builder::new()
        .name(name.into())
        .spawn(f)
        .map_err(|e| Error::io("xArm emulator thread", e))
}

#[derive(Debug, Clone, Copy)]
enum Role {
    Cmd,
    Report { kind: ReportKind, period: Duration },
}

fn accept_loop(l: TcpListener, h: XArmEmuHandle, role: Role) {
    let mut conns: Vec<JoinHandle<()>> = Vec::new();
    let mut next_conn = 0u64;
    while !h.stop.load(Ordering::SeqCst) {
        match l.accept() {
            Ok((s, _)) => {
                let h2 = h.clone();
                let _ = s.set_nonblocking(false);
                let _ = s.set_nodelay(true);
                next_conn += 1;
                let conn = next_conn;
                let r = match role {
                    Role::Cmd => spawn_named("xarm-emu-conn", move || {
                        serve_cmd(s, &h2, conn);
                        // However the session ended (the client closed, a fault, garbage).
                        lock(&h2.sim).client_gone(conn);
                    }),
                    Role::Report { kind, period } => {
                        spawn_named("xarm-emu-stream", move || serve_report(s, h2, kind, period))
                    }
                };
                if let Ok(j) = r {
                    conns.push(j);
                }
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(5))
            }
            Err(_) => std::thread::sleep(Duration::from_millis(5)),
        }
        conns.retain(|j| !j.is_finished());
    }
    for j in conns {
        let _ = j.join();
    }
}

fn serve_cmd(mut s: TcpStream, h: &XArmEmuHandle, conn: u64) {
    let _ = s.set_read_timeout(Some(Duration::from_millis(20)));
    let mut fb = FrameBuf::new();
    let mut buf = [0u8; 1024];
    while !h.stop.load(Ordering::SeqCst) {
        match super::read_some(&mut s, &mut buf) {
            super::Got::Bytes(n) => fb.push(&buf[..n]),
            super::Got::Idle => continue,
            super::Got::Empty | super::Got::Failed => return,
        }
        loop {
            let frame = match fb.next_frame() {
                Ok(Some(f)) => f,
                Ok(None) => break,
                Err(_) => return, // garbage from the client: drop it like a controller would
            };
            let Ok(cmd) = Command::decode(&frame) else {
                return;
            };
            if cmd.proto == proto::PROTO_HEARTBEAT {
                continue; // the SDK's keep-alive: nothing to answer
            }
            let (st, data) = {
                let mut sim = lock(&h.sim);
                sim.advance(h.clock.now());
                sim.handle(&cmd, &h.opts.version, conn)
            };
            let fault = lock(&h.faults).cmd.pop_front();
            let mut reply = Reply {
                tid: cmd.tid,
                proto: cmd.proto,
                register: cmd.register,
                status: st,
                data,
            };
            let mut pre: Option<Vec<u8>> = None;
            match &fault {
                Some(XArmFault::DropConnection) => {
                    let _ = s.shutdown(std::net::Shutdown::Both);
                    return;
                }
                Some(XArmFault::Stall(d)) => std::thread::sleep(*d),
                Some(XArmFault::WrongTid) => {
                    let stale = Reply {
                        tid: cmd.tid ^ 0x8000,
                        ..reply.clone()
                    };
                    pre = stale.encode().ok();
                }
                Some(XArmFault::WrongProtocol) => reply.proto = cmd.proto ^ 1,
                _ => {}
            }
            let Ok(mut out) = reply.encode() else { return };
            if let Some(p) = pre {
                out.splice(0..0, p);
            }
            match fault {
                Some(XArmFault::Truncated) => {
                    let _ = s.write_all(&out[..out.len() / 2]);
                    let _ = s.shutdown(std::net::Shutdown::Both);
                    return;
                }
                Some(XArmFault::Garbage(g)) => out = g,
                _ => {}
            }
            if s.write_all(&out).is_err() {
                return;
            }
        }
    }
}

fn serve_report(mut s: TcpStream, h: XArmEmuHandle, kind: ReportKind, period: Duration) {
    let size = h.opts.report_len(kind);
    let clock = h.clock.clone();
    let period_ns = period.as_nanos() as Nanos;
    let mut next = clock.now();
    while !h.stop.load(Ordering::SeqCst) {
        let rep = {
            let mut sim = lock(&h.sim);
            sim.advance(clock.now());
            sim.report(kind, &h.opts.version)
        };
        let Ok(mut frame) = rep.encode(kind, size) else {
            return;
        };
        match lock(&h.faults).report.pop_front() {
            Some(XArmFault::ReportStall(d)) => std::thread::sleep(d),
            Some(XArmFault::ReportDisconnect) => {
                let _ = s.shutdown(std::net::Shutdown::Both);
                return;
            }
            Some(XArmFault::ReportGarbage) => {
                frame[..4].copy_from_slice(&(size as u32 + 7).to_be_bytes());
            }
            _ => {}
        }
        if s.write_all(&frame).is_err() {
            return;
        }
        next += period_ns;
        let now = clock.now();
        if next < now {
            next = now;
        }
        clock.sleep_until(next);
    }
}
