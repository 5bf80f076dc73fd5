//! XHand over RS-485: protocol ([`proto`]), protocol choices ([`consts`]), serial line
//! ([`tty`], unix) and the [`XHand`] robot.
//!
//! The transport is injected: anything `Read + Write + Send` (a [`tty::TtyPort`] on a real
//! adapter or a PTY, or the in-memory [`crate::emu::duplex()`] port). A read that returns
//! `Ok(0)`, `WouldBlock` or `TimedOut` means "nothing yet"; the driver keeps its own deadline
//! on the injected clock. `BrokenPipe`/`UnexpectedEof`/`ConnectionReset` mean the line is gone.
//!
//! Every request gets exactly one reply. `send_targets` sends the 12 finger commands (position
//! mode, kp/ki/kd and torque limit from [`XHandConfig`]) and caches the state that answers
//! it; `read_state` returns that cache while it is younger than
//! [`XHandConfig::refresh_after`], and otherwise asks again (re-sending the last command, or
//! [`consts::CMD_READ_STATE`] before the first command).
//!
//! # Behaviour on stop and faults
//!
//! [`Robot::stop`] sends one last command that holds every joint at its last measured
//! position (or, with [`XHandConfig::release_on_stop`], puts every joint in powerless mode),
//! then refuses further targets. The command is always finite: a joint whose measured
//! position is not finite holds its last commanded target, and a joint with neither is made
//! powerless. A finger state with a non-zero error word is reported by [`Robot::fault`]
//! (the safety layer stops on it). A CRC error, a reply from the wrong id or a timeout fails
//! the request with an error naming it; the driver stays usable (the next request resyncs on
//! `55 AA`), so the safety layer decides whether to stop.

pub mod consts;
pub mod proto;
#[cfg(unix)]
pub mod tty;

use std::io::{ErrorKind, Read, Write};
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::{Clock, Nanos};

use crate::error::{Error, Result};
use crate::robot::{Robot, StateLayout};
use proto::{FingerCommand, Frame, FrameParser, HandState};

const CH: &str = "XHand serial";
const DEVICE: &str = "XHand";

/// A byte transport for the hand (serial port, PTY, in-memory pipe).
pub trait Transport: Read + Write + Send {}
impl<T: Read + Write + Send> Transport for T {}

/// Settings of an [`XHand`].
#[derive(Debug, Clone)]
pub struct XHandConfig {
    /// The hand's bus id.
    pub hand_id: u8,
    /// Position gain (paper: 100).
    pub kp: i16,
    /// Integral gain.
    pub ki: i16,
    /// Derivative gain.
    pub kd: i16,
    /// Torque limit per joint (paper: 300).
    pub torque_limit: u16,
    /// Longest wait for a reply.
    pub timeout: Duration,
    /// `read_state` re-queries when the cached state is older than this.
    pub refresh_after: Duration,
    /// On `stop()`: `false` holds the measured position, `true` makes all joints powerless.
    pub release_on_stop: bool,
}

impl Default for XHandConfig {
    fn default() -> Self {
        Self {
            hand_id: consts::DEFAULT_HAND_ID,
            kp: consts::DEFAULT_KP,
            ki: consts::DEFAULT_KI,
            kd: consts::DEFAULT_KD,
            torque_limit: consts::DEFAULT_TORQUE_LIMIT,
            timeout: Duration::from_millis(100),
            refresh_after: Duration::from_millis(5),
            release_on_stop: false,
        }
    }
}

/// Counters of a hand driver's life.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct XHandStats {
    /// Requests sent.
    pub requests: u64,
    /// Frames ignored because they came from another id or went to another id.
    pub foreign_frames: u64,
    /// Bytes skipped while hunting for `55 AA`.
    pub dropped_bytes: u64,
    /// Replies whose finger states carried a non-zero error word.
    pub finger_errors: u64,
}

/// The XHand as a [`Robot`]: state = 12 positions, 12 torques, 15 fingertip forces (39);
/// action = 12 joint targets (rad).
#[derive(Debug)]
pub struct XHand<T> {
    port: T,
    cfg: XHandConfig,
    clock: Arc<dyn Clock>,
    parser: FrameParser,
    state: Option<(HandState, Nanos)>,
    last_cmd: Option<[f32; consts::JOINTS]>,
    fault: Option<String>,
    stopped: bool,
    stats: XHandStats,
    tx: Vec<u8>,
    rx: Vec<u8>,
    cmd_buf: Vec<u8>,
}

impl<T: Transport> XHand<T> {
    /// A driver on `port`. No traffic until the first call.
    pub fn new(port: T, cfg: XHandConfig, clock: Arc<dyn Clock>) -> Self {
        Self {
            port,
            cfg,
            clock,
            parser: FrameParser::new(),
            state: None,
            last_cmd: None,
            fault: None,
            stopped: false,
            stats: XHandStats::default(),
            tx: Vec::with_capacity(
                consts::HEADER_LEN + consts::COMMAND_PAYLOAD_LEN + consts::CRC_LEN,
            ),
            rx: vec![0; 4096],
            cmd_buf: Vec::with_capacity(consts::COMMAND_PAYLOAD_LEN),
        }
    }

    /// Counters so far.
    pub fn stats(&self) -> XHandStats {
        XHandStats {
            dropped_bytes: self.parser.dropped(),
            ..self.stats
        }
    }

    /// The configuration.
    pub fn config(&self) -> &XHandConfig {
        &self.cfg
    }

    /// The newest decoded state and when it arrived.
    pub fn last_state(&self) -> Option<&(HandState, Nanos)> {
        self.state.as_ref()
    }

    /// Send one frame and wait for the reply to `cmd` from our hand.
    pub fn transact(&mut self, cmd: u8, payload: &[u8]) -> Result<Frame> {
        // Anything still buffered answers an older request: drop it.
        self.parser.clear();
        self.tx.clear();
        proto::encode_frame(
            consts::HOST_ID,
            self.cfg.hand_id,
            cmd,
            payload,
            &mut self.tx,
        )?;
        self.stats.requests += 1;
        self.port.write_all(&self.tx).map_err(io_err)?;
        self.port.flush().map_err(io_err)?;
        let start = self.clock.now();
        let timeout = self.cfg.timeout.as_nanos() as Nanos;
        loop {
            while let Some(res) = self.parser.next_frame() {
                let f = res?;
                if f.src != self.cfg.hand_id || f.dst != consts::HOST_ID {
                    self.stats.foreign_frames += 1;
                    continue;
                }
                if f.cmd != cmd {
                    return Err(Error::XHandReply {
                        reason: format!("answer to command 0x{:02x}, expected 0x{cmd:02x}", f.cmd),
                    });
                }
                return Ok(f);
            }
            let waited = self.clock.now().saturating_sub(start);
            if waited >= timeout {
                return Err(Error::Timeout {
                    channel: CH,
                    what: format!("reply to command 0x{cmd:02x}"),
                    waited_ms: waited / 1_000_000,
                });
            }
            match self.port.read(&mut self.rx) {
                Ok(0) => {}
                Ok(n) => self.parser.push(&self.rx[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(io_err(e)),
            }
        }
    }

    /// Firmware version string.
    pub fn version(&mut self) -> Result<String> {
        let f = self.transact(consts::CMD_VERSION, &[])?;
        let end = f
            .payload
            .iter()
            .position(|&b| b == 0)
            .unwrap_or(f.payload.len());
        Ok(String::from_utf8_lossy(&f.payload[..end])
            .trim()
            .to_string())
    }

    fn accept_state(&mut self, f: Frame) -> Result<&HandState> {
        let s = HandState::decode(&f.payload)?;
        self.fault = s
            .fingers
            .iter()
            .enumerate()
            .find(|(_, f)| f.errors.iter().any(|&e| e != 0))
            .map(|(j, f)| {
                format!(
                    "joint {j} error words {:04x} {:04x} {:04x}",
                    f.errors[0], f.errors[1], f.errors[2]
                )
            });
        if self.fault.is_some() {
            self.stats.finger_errors += 1;
        }
        let t = self.clock.now();
        Ok(&self.state.insert((s, t)).0)
    }

    /// Ask for the state without commanding.
    pub fn query_state(&mut self) -> Result<&HandState> {
        let f = self.transact(consts::CMD_READ_STATE, &[])?;
        self.accept_state(f)
    }

    /// Send raw finger commands; returns the state that answers them.
    pub fn send_fingers(
        &mut self,
        fingers: &[FingerCommand; consts::JOINTS],
    ) -> Result<&HandState> {
        let mut payload = std::mem::take(&mut self.cmd_buf);
        proto::encode_hand_command_into(fingers, &mut payload);
        let r = self.transact(consts::CMD_SET_COMMAND, &payload);
        self.cmd_buf = payload;
        self.accept_state(r?)
    }

    fn position_commands(
        &self,
        q: &[f32; consts::JOINTS],
        mode: u16,
    ) -> [FingerCommand; consts::JOINTS] {
        let mut out = [FingerCommand {
            id: 0,
            kp: 0,
            ki: 0,
            kd: 0,
            position: 0.0,
            tor_max: 0,
            mode: 0,
        }; consts::JOINTS];
        for (i, c) in out.iter_mut().enumerate() {
            *c = FingerCommand {
                id: i as u16,
                kp: self.cfg.kp,
                ki: self.cfg.ki,
                kd: self.cfg.kd,
                position: q[i],
                tor_max: self.cfg.torque_limit,
                mode,
            };
        }
        out
    }

    /// Command 12 joint positions in position mode; returns the answering state.
    pub fn command_positions(&mut self, q: &[f32; consts::JOINTS]) -> Result<&HandState> {
        let cmds = self.position_commands(q, consts::MODE_POSITION);
        self.last_cmd = Some(*q);
        self.send_fingers(&cmds)
    }
}

fn io_err(e: std::io::Error) -> Error {
    match e.kind() {
        ErrorKind::BrokenPipe | ErrorKind::UnexpectedEof | ErrorKind::ConnectionReset => {
            Error::Disconnected { channel: CH }
        }
        _ => Error::io(CH, e),
    }
}

impl<T: Transport> Robot for XHand<T> {
    fn name(&self) -> &'static str {
        DEVICE
    }
    fn state_dim(&self) -> usize {
        2 * consts::JOINTS + 3 * consts::TIPS
    }
    fn action_dim(&self) -> usize {
        consts::JOINTS
    }
    fn layout(&self) -> StateLayout {
        StateLayout {
            positions: 0..consts::JOINTS,
            torques: Some(consts::JOINTS..2 * consts::JOINTS),
        }
    }
    fn read_state(&mut self, out: &mut [f32]) -> Result<Nanos> {
        Error::check_dim("XHand state", self.state_dim(), out.len())?;
        let now = self.clock.now();
        let fresh = matches!(&self.state, Some((_, t)) if now.saturating_sub(*t) < self.cfg.refresh_after.as_nanos() as Nanos);
        if !fresh && !self.stopped {
            match self.last_cmd {
                Some(q) => {
                    self.command_positions(&q)?;
                }
                None => {
                    self.query_state()?;
                }
            }
        }
        match &self.state {
            Some((s, t)) => {
                s.write_vector(out);
                Ok(*t)
            }
            None => Err(Error::Stopped {
                device: DEVICE,
                reason: "stopped before any state was read".into(),
            }),
        }
    }
    fn send_targets(&mut self, targets: &[f32]) -> Result<()> {
        Error::check_dim("XHand targets", consts::JOINTS, targets.len())?;
        if self.stopped {
            return Err(Error::Stopped {
                device: DEVICE,
                reason: "stop() was called".into(),
            });
        }
        let mut q = [0f32; consts::JOINTS];
        q.copy_from_slice(targets);
        self.command_positions(&q).map(|_| ())
    }
    fn stop(&mut self) -> Result<()> {
        if self.stopped {
            return Ok(());
        }
        self.stopped = true;
        // Per joint: the measured position, else the last commanded target, else powerless
        // (no finite value to hold).
        let measured = self.state.as_ref().map(|(s, _)| s);
        if measured.is_none() && self.last_cmd.is_none() {
            // Never commanded and never read: the hand is in whatever mode it booted in.
            return Ok(());
        }
        let mut q = [0f32; consts::JOINTS];
        let mut hold = [false; consts::JOINTS];
        for j in 0..consts::JOINTS {
            let m = measured.map(|s| s.fingers[j].position);
            let c = self.last_cmd.map(|c| c[j]);
            if let Some(x) = [m, c].into_iter().flatten().find(|x| x.is_finite()) {
                q[j] = x;
                hold[j] = true;
            }
        }
        let mode = if self.cfg.release_on_stop {
            consts::MODE_POWERLESS
        } else {
            consts::MODE_POSITION
        };
        let mut cmds = self.position_commands(&q, mode);
        for (c, h) in cmds.iter_mut().zip(hold) {
            if !h {
                c.mode = consts::MODE_POWERLESS;
            }
        }
        self.send_fingers(&cmds).map(|_| ())
    }
    fn fault(&self) -> Option<String> {
        self.fault.clone()
    }
}
