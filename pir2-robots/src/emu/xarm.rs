//! Loopback xArm emulator: a TCP server speaking the frames of [`crate::xarm::proto`] on a
//! command port and up to three report ports, with simple joint dynamics and fault injection.
//!
//! Ports: the standard ones (502, 30001 normal, 30002 rich, 30003 real) with
//! [`XArmPorts::standard`], or ephemeral ones (port 0, chosen by the OS) with
//! [`XArmPorts::ephemeral`]; [`XArmEmulator::cmd_addr`] and [`XArmEmulator::report_addr`] tell
//! where it listens. The rich stream sends the normal layout padded with zeros to 233 bytes
//! (`TCP_REPORT_RICH_BUF_SIZE` in the SDK's `x_config.py`); fields past the normal layout are
//! not emulated.
//!
//! Behaviour: the arm starts stopped (state 4), mode 0, motors disabled. `MOTION_EN [8, 1]`,
//! `SET_MODE [1]` and `SET_STATE [0]` make it ready (state 2); servo-j is then applied
//! (state 1) and each joint moves toward its target at up to [`ARM_MAX_SPEED`] rad/s. Servo-j
//! in any other condition answers with the not-ready bit and is ignored. An injected error code
//! stops the arm and sets the error bit in every reply until `CLEAN_ERR`. Unknown registers
//! answer with the invalid bit.

use std::collections::VecDeque;
use std::io::{ErrorKind, Read, Write};
use std::net::{IpAddr, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use pir2_runtime::{Clock, Nanos, SystemClock};

use crate::error::{Error, Result};
use crate::xarm::proto::{self, reg, state, status, Command, FrameBuf, Reply, Report, ReportKind};

/// Joint speed limit of the emulated arm, rad/s.
pub const ARM_MAX_SPEED: f32 = 3.0;
/// Version string the emulator reports.
pub const XARM_EMU_VERSION: &str = "xArm-emu 2.0.0";
/// Joint angles the emulated arm starts at, rad.
pub const ARM_HOME: [f32; 7] = [0.0, -0.3, -0.5, 0.0, 0.8, 0.0, 0.0];

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
    /// Answer with protocol id 3 instead of 2.
    WrongProtocol,
    /// Set the controller error code (sticky until CLEAN_ERR; the arm stops).
    ErrorCode(u8),
    /// Stop the arm from the controller side (state 4, no error), like an emergency stop.
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
    /// Requests answered.
    pub requests: u64,
    t: Option<Nanos>,
}

impl ArmSim {
    fn new() -> Self {
        Self {
            q: ARM_HOME,
            target: ARM_HOME,
            tau: [0.0; 7],
            mode: 0,
            state: state::STOP,
            enabled: false,
            error: 0,
            warning: 0,
            servoj: 0,
            requests: 0,
            t: None,
        }
    }
    fn ready(&self) -> bool {
        self.enabled
            && self.error == 0
            && self.mode == proto::MODE_SERVO
            && matches!(self.state, state::MOVING | state::SLEEPING)
    }
    fn advance(&mut self, now: Nanos) {
        let dt = self.t.map_or(0.0, |t| now.saturating_sub(t) as f32 * 1e-9);
        self.t = Some(now);
        let moving = self.ready();
        for i in 0..7 {
            if moving {
                let step = ARM_MAX_SPEED * dt;
                self.q[i] += (self.target[i] - self.q[i]).clamp(-step, step);
            }
            // A stiff servo plus a gravity-like load on the shoulder and elbow.
            let load = if i == 1 || i == 2 {
                2.0 * self.q[i].sin()
            } else {
                0.0
            };
            self.tau[i] = 5.0 * (self.target[i] - self.q[i]) + load;
        }
    }
    fn status(&self) -> u8 {
        let mut s = 0;
        if self.error != 0 {
            s |= status::ERROR;
        }
        if self.warning != 0 {
            s |= status::WARNING;
        }
        if !self.ready() {
            s |= status::NOT_READY;
        }
        s
    }
    fn report(&self) -> Report {
        Report {
            state: self.state,
            mode: self.mode,
            cmd_num: 0,
            angles: self.q,
            pose: [200.0, 0.0, 300.0, std::f32::consts::PI, 0.0, 0.0],
            torques: self.tau,
            error: self.error,
            warning: self.warning,
        }
    }
    /// Answer one request: `(status, data)`.
    fn handle(&mut self, c: &Command) -> (u8, Vec<u8>) {
        self.requests += 1;
        let mut data = Vec::new();
        let mut invalid = false;
        match c.register {
            reg::GET_VERSION => {
                data = XARM_EMU_VERSION.as_bytes().to_vec();
                data.resize(proto::VERSION_LEN, 0);
            }
            reg::MOTION_EN => match c.params.as_slice() {
                [_axis, on] => {
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
            reg::GET_ERROR => data = vec![self.error, self.warning],
            reg::CLEAN_ERR => {
                self.error = 0;
                self.warning = 0;
            }
            reg::SET_MODE => match c.params.as_slice() {
                [m] => {
                    self.mode = *m;
                    // The real controller needs SET_STATE 0 after a mode change.
                    self.state = state::STOP;
                }
                _ => invalid = true,
            },
            reg::MOVE_SERVOJ => {
                if c.params.len() != 40 {
                    invalid = true;
                } else if self.ready() {
                    let mut v = [0f32; 10];
                    let _ = proto::read_fp32s_le(&c.params, &mut v);
                    if v.iter().all(|x| x.is_finite()) {
                        self.target.copy_from_slice(&v[..7]);
                        self.state = state::MOVING;
                        self.servoj += 1;
                    } else {
                        invalid = true;
                    }
                }
            }
            reg::GET_JOINT_POS => {
                data = proto::fp32s_le(&self.q);
                if c.params.first() == Some(&3) {
                    data.extend(proto::fp32s_le(&[0.0; 7]));
                    data.extend(proto::fp32s_le(&self.tau));
                }
            }
            reg::GET_JOINT_TAU => data = proto::fp32s_le(&self.tau),
            _ => invalid = true,
        }
        let st = self.status() | if invalid { status::INVALID } else { 0 };
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
    reports: Vec<(ReportKind, usize, SocketAddr)>,
    threads: Vec<JoinHandle<()>>,
}

impl XArmEmulator {
    /// Listen on `host` (use 127.0.0.1) at `ports`, until [`XArmEmulator::shutdown`] or drop.
    pub fn spawn(host: IpAddr, ports: XArmPorts) -> Result<Self> {
        Self::spawn_with_stop(host, ports, Arc::new(AtomicBool::new(false)))
    }

    /// Like [`XArmEmulator::spawn`], also ending when `stop` is set.
    pub fn spawn_with_stop(host: IpAddr, ports: XArmPorts, stop: Arc<AtomicBool>) -> Result<Self> {
        let handle = XArmEmuHandle {
            sim: Arc::new(Mutex::new(ArmSim::new())),
            faults: Arc::new(Mutex::new(Faults::default())),
            stop,
            clock: Arc::new(SystemClock::new()),
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
        for (port, kind, size, period) in [
            (
                ports.report_real,
                ReportKind::Real,
                proto::REPORT_REAL_LEN,
                Duration::from_millis(10),
            ),
            (
                ports.report_normal,
                ReportKind::Normal,
                proto::REPORT_NORMAL_LEN,
                Duration::from_millis(200),
            ),
            (
                ports.report_rich,
                ReportKind::Normal,
                proto::REPORT_RICH_LEN,
                Duration::from_millis(200),
            ),
        ] {
            let Some(port) = port else { continue };
            let l = bind(port)?;
            let addr = l.local_addr().map_err(|e| Error::io("xArm emulator", e))?;
            reports.push((kind, size, addr));
            let h = handle.clone();
            threads.push(spawn_named("xarm-emu-report", move || {
                accept_loop(l, h, Role::Report { kind, size, period })
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
    /// Where a report stream listens: `(Real, _)` → 30003, `(Normal, 133)` → 30001,
    /// `(Normal, 233)` → 30002.
    pub fn report_addr(&self, kind: ReportKind, size: usize) -> Option<SocketAddr> {
        self.reports
            .iter()
            .find(|(k, s, _)| *k == kind && *s == size)
            .map(|r| r.2)
    }
    /// The real-time (30003) report address, if served.
    pub fn real_report_addr(&self) -> Option<SocketAddr> {
        self.report_addr(ReportKind::Real, proto::REPORT_REAL_LEN)
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
    Report {
        kind: ReportKind,
        size: usize,
        period: Duration,
    },
}

fn accept_loop(l: TcpListener, h: XArmEmuHandle, role: Role) {
    let mut conns: Vec<JoinHandle<()>> = Vec::new();
    while !h.stop.load(Ordering::SeqCst) {
        match l.accept() {
            Ok((s, _)) => {
                let h2 = h.clone();
                let _ = s.set_nonblocking(false);
                let _ = s.set_nodelay(true);
                let r = match role {
                    Role::Cmd => spawn_named("xarm-emu-conn", move || serve_cmd(s, h2)),
                    Role::Report { kind, size, period } => {
                        spawn_named("xarm-emu-stream", move || {
                            serve_report(s, h2, kind, size, period)
                        })
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

fn serve_cmd(mut s: TcpStream, h: XArmEmuHandle) {
    let _ = s.set_read_timeout(Some(Duration::from_millis(20)));
    let mut fb = FrameBuf::new();
    let mut buf = [0u8; 1024];
    while !h.stop.load(Ordering::SeqCst) {
        match s.read(&mut buf) {
            Ok(0) => return,
            Ok(n) => fb.push(&buf[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                ) =>
            {
                continue
            }
            Err(_) => return,
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
            let (st, data) = {
                let mut sim = lock(&h.sim);
                sim.advance(h.clock.now());
                sim.handle(&cmd)
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
                Some(XArmFault::WrongProtocol) => reply.proto = 3,
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

fn serve_report(
    mut s: TcpStream,
    h: XArmEmuHandle,
    kind: ReportKind,
    size: usize,
    period: Duration,
) {
    while !h.stop.load(Ordering::SeqCst) {
        let rep = {
            let mut sim = lock(&h.sim);
            sim.advance(h.clock.now());
            sim.report()
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
        std::thread::sleep(period);
    }
}
