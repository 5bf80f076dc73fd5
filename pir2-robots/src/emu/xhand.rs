//! XHand emulator: answers the RS-485 protocol of [`crate::xhand::proto`] on any transport
//! (an in-memory [`super::duplex()`] port or a PTY), with simple joint dynamics and fault
//! injection.
//!
//! Dynamics: each joint in position mode moves toward its target as a first-order lag
//! (time constant [`HAND_TAU_S`]); its torque is `kp · error / 100`, clamped to the command's
//! torque limit; each fingertip's normal force grows with its finger's flexion.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use pir2_runtime::{Clock, Nanos, SystemClock};

use crate::error::{Error, Result};
use crate::xhand::consts;
use crate::xhand::proto::{self, FingerCommand, Frame, FrameParser, HandState};
use crate::xhand::Transport;

/// Time constant of the emulated finger joints.
pub const HAND_TAU_S: f32 = 0.03;
/// Version string the emulator reports.
pub const XHAND_EMU_VERSION: &str = "xhand-emu 1.0";

/// A one-shot fault applied to the next request (except `Disconnect`, which ends the line).
#[derive(Debug, Clone, PartialEq)]
pub enum XHandFault {
    /// Ignore the next request.
    NoReply,
    /// Wait this long before answering.
    Stall(Duration),
    /// Send only the first half of the reply.
    Truncated,
    /// Send these bytes instead of the reply.
    Garbage(Vec<u8>),
    /// Send the reply with a corrupted CRC.
    BadCrc,
    /// Answer from another hand id.
    WrongId,
    /// Close the line (the emulator stops).
    Disconnect,
    /// Set this error word on joint 0 of every following state (0 clears it).
    FingerError(u16),
    /// Report joint 0's position as NaN in every following state (`false` clears it).
    NonFinitePosition(bool),
}

#[derive(Debug)]
struct Sim {
    q: [f32; consts::JOINTS],
    cmd: [FingerCommand; consts::JOINTS],
    t: Option<Nanos>,
    finger_error: u16,
    nan_position: bool,
    commands: u64,
    requests: u64,
}

impl Sim {
    fn new() -> Self {
        let cmd = [FingerCommand {
            id: 0,
            kp: 0,
            ki: 0,
            kd: 0,
            position: 0.0,
            tor_max: 0,
            mode: consts::MODE_POWERLESS,
        }; consts::JOINTS];
        Self {
            q: [0.0; consts::JOINTS],
            cmd,
            t: None,
            finger_error: 0,
            nan_position: false,
            commands: 0,
            requests: 0,
        }
    }
    fn advance(&mut self, now: Nanos) {
        let dt = self.t.map_or(0.0, |t| now.saturating_sub(t) as f32 * 1e-9);
        self.t = Some(now);
        let a = 1.0 - (-dt / HAND_TAU_S).exp();
        for i in 0..consts::JOINTS {
            if self.cmd[i].mode == consts::MODE_POSITION {
                self.q[i] += a * (self.cmd[i].position - self.q[i]);
            }
        }
    }
    fn state(&self) -> HandState {
        let mut s = HandState::default();
        for i in 0..consts::JOINTS {
            let c = &self.cmd[i];
            let torque = if c.mode == consts::MODE_POSITION {
                let lim = c.tor_max as f32;
                (c.kp as f32 * (c.position - self.q[i]) / 100.0).clamp(-lim, lim)
            } else {
                0.0
            };
            s.fingers[i] = proto::FingerState {
                id: i as u16,
                sensor_id: (i / 3) as u16,
                position: if i == 0 && self.nan_position {
                    f32::NAN
                } else {
                    self.q[i]
                },
                torque,
                raw_position: (self.q[i] * 10_000.0) as i32,
                temperature: 30,
                errors: [if i == 0 { self.finger_error } else { 0 }, 0, 0],
            };
        }
        for k in 0..consts::TIPS {
            let flex = self.q[(k * consts::JOINTS / consts::TIPS).min(consts::JOINTS - 1)];
            s.tip_force[k] = [0, 0, (flex.max(0.0) * 100.0).min(255.0) as i16];
        }
        s
    }
}

/// A shared view of a running XHand emulator.
#[derive(Debug, Clone)]
pub struct XHandEmuHandle {
    sim: Arc<Mutex<Sim>>,
    faults: Arc<Mutex<VecDeque<XHandFault>>>,
    stop: Arc<AtomicBool>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl XHandEmuHandle {
    /// Queue a fault for the next request.
    pub fn inject(&self, f: XHandFault) {
        lock(&self.faults).push_back(f);
    }
    /// Current emulated joint positions.
    pub fn positions(&self) -> [f32; consts::JOINTS] {
        lock(&self.sim).q
    }
    /// Position targets of the last command.
    pub fn targets(&self) -> [f32; consts::JOINTS] {
        let s = lock(&self.sim);
        let mut t = [0f32; consts::JOINTS];
        for (o, c) in t.iter_mut().zip(s.cmd.iter()) {
            *o = c.position;
        }
        t
    }
    /// The last finger commands received.
    pub fn last_commands(&self) -> [FingerCommand; consts::JOINTS] {
        lock(&self.sim).cmd
    }
    /// Number of 0x02 commands answered.
    pub fn commands(&self) -> u64 {
        lock(&self.sim).commands
    }
    /// Number of well-formed requests received for this hand.
    pub fn requests(&self) -> u64 {
        lock(&self.sim).requests
    }
    /// Ask the emulator thread to end.
    pub fn shutdown(&self) {
        self.stop.store(true, Ordering::SeqCst);
    }
}

/// A running emulator thread.
#[derive(Debug)]
pub struct XHandEmulator {
    handle: XHandEmuHandle,
    thread: Option<JoinHandle<()>>,
}

impl XHandEmulator {
    /// Serve hand `hand_id` on `port` until shut down, the line closes, or `stop` is set.
    pub fn spawn<T: Transport + 'static>(
        port: T,
        hand_id: u8,
        stop: Arc<AtomicBool>,
    ) -> Result<Self> {
        let handle = XHandEmuHandle {
            sim: Arc::new(Mutex::new(Sim::new())),
            faults: Arc::new(Mutex::new(VecDeque::new())),
            stop,
        };
        let h = handle.clone();
        let thread = std::thread::Builder::new()
            .name("xhand-emu".into())
            .spawn(move || serve(port, hand_id, h, Arc::new(SystemClock::new())))
            .map_err(|e| Error::io("XHand emulator thread", e))?;
        Ok(Self {
            handle,
            thread: Some(thread),
        })
    }

    /// The shared view.
    pub fn handle(&self) -> &XHandEmuHandle {
        &self.handle
    }

    /// Stop the thread and wait for it.
    pub fn shutdown(mut self) {
        self.handle.shutdown();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for XHandEmulator {
    fn drop(&mut self) {
        // A detached emulator (see `run_xhand_emulator_pty`) has no thread here and keeps
        // running until its stop flag is set.
        if let Some(t) = self.thread.take() {
            self.handle.shutdown();
            let _ = t.join();
        }
    }
}

/// Spawn an XHand emulator (hand id [`consts::DEFAULT_HAND_ID`]) on a new pseudo-terminal and
/// return the device path a driver opens (e.g. `/dev/pts/4`). It runs until `stop` is set.
#[cfg(unix)]
pub fn run_xhand_emulator_pty(stop: Arc<AtomicBool>) -> Result<PathBuf> {
    let (emu, path) = spawn_pty(consts::DEFAULT_HAND_ID, stop)?;
    // The thread owns everything it needs; detach it (it ends when `stop` is set).
    let mut emu = emu;
    emu.thread.take();
    Ok(path)
}

/// Spawn an XHand emulator on a new pseudo-terminal; returns the emulator and the device path.
#[cfg(unix)]
pub fn spawn_pty(hand_id: u8, stop: Arc<AtomicBool>) -> Result<(XHandEmulator, PathBuf)> {
    let master = crate::xhand::tty::PtyMaster::open(Duration::from_millis(20))?;
    let path = master.slave_path().to_path_buf();
    Ok((XHandEmulator::spawn(master, hand_id, stop)?, path))
}

fn reply_state(sim: &Mutex<Sim>, clock: &dyn Clock) -> Vec<u8> {
    let mut s = lock(sim);
    s.advance(clock.now());
    s.state().encode()
}

fn serve<T: Transport>(mut port: T, hand_id: u8, h: XHandEmuHandle, clock: Arc<dyn Clock>) {
    let mut parser = FrameParser::new();
    let mut buf = vec![0u8; 4096];
    while !h.stop.load(Ordering::SeqCst) {
        match super::read_some(&mut port, &mut buf) {
            super::Got::Bytes(n) => parser.push(&buf[..n]),
            super::Got::Empty | super::Got::Idle => continue,
            super::Got::Failed => return,
        }
        while let Some(res) = parser.next_frame() {
            let Ok(req) = res else { continue }; // a real device ignores corrupted requests
            if req.src != consts::HOST_ID || (req.dst != hand_id && req.dst != consts::BROADCAST_ID)
            {
                continue;
            }
            lock(&h.sim).requests += 1;
            let fault = lock(&h.faults).pop_front();
            let mut src = hand_id;
            match &fault {
                Some(XHandFault::NoReply) => continue,
                Some(XHandFault::Stall(d)) => std::thread::sleep(*d),
                Some(XHandFault::Disconnect) => return,
                Some(XHandFault::FingerError(code)) => lock(&h.sim).finger_error = *code,
                Some(XHandFault::NonFinitePosition(on)) => lock(&h.sim).nan_position = *on,
                Some(XHandFault::WrongId) => src = hand_id.wrapping_add(1),
                _ => {}
            }
            let payload = match req.cmd {
                consts::CMD_VERSION => {
                    let mut v = XHAND_EMU_VERSION.as_bytes().to_vec();
                    v.push(0);
                    v
                }
                consts::CMD_READ_STATE => reply_state(&h.sim, clock.as_ref()),
                consts::CMD_SET_COMMAND => {
                    let Ok(cmds) = proto::decode_hand_command(&req.payload) else {
                        continue;
                    };
                    {
                        let mut s = lock(&h.sim);
                        s.advance(clock.now());
                        s.cmd = cmds;
                        s.commands += 1;
                    }
                    reply_state(&h.sim, clock.as_ref())
                }
                _ => continue,
            };
            let Ok(mut out) = (Frame {
                src,
                dst: consts::HOST_ID,
                cmd: req.cmd,
                payload,
            })
            .encode() else {
                continue;
            };
            match fault {
                Some(XHandFault::Truncated) => out.truncate(out.len() / 2),
                Some(XHandFault::Garbage(g)) => out = g,
                Some(XHandFault::BadCrc) => {
                    let n = out.len();
                    out[n - 1] ^= 0x5a;
                }
                _ => {}
            }
            if port.write_all(&out).and_then(|_| port.flush()).is_err() {
                return;
            }
        }
    }
}
