//! UFACTORY xArm wire format: command frames (port 502) and report frames (ports 30001–30003).
//!
//! # Command frame (client → controller)
//!
//! ```text
//! offset  size  field
//! 0       2     transaction id, u16 big-endian (1, 2, ..., 65535, 1, ...)
//! 2       2     protocol id, u16 BE (2 = private protocol; firmware ≥ 1.8.6 may use 3)
//! 4       2     length, u16 BE = 1 + n  (counts the register byte and the parameters)
//! 6       1     register
//! 7       n     parameters
//! ```
//!
//! # Reply frame (controller → client)
//!
//! ```text
//! 0  tid u16 BE | 2  proto u16 BE | 4  length u16 BE = 2 + n | 6  register | 7  status | 8  data[n]
//! ```
//!
//! Status bits: `0x08` invalid request, `0x10` not ready, `0x20` warning present, `0x40` error
//! present. A stream is split into frames by the length field (`6 + length` bytes), never by
//! `recv` boundaries. Integers in headers and u16 data are big-endian; **fp32 and int32 data are
//! little-endian**.
//!
//! # Registers used here
//!
//! | reg | name          | request params             | reply data                         |
//! |-----|---------------|----------------------------|------------------------------------|
//! | 1   | GET_VERSION   | –                          | 40 bytes ASCII, NUL padded         |
//! | 11  | MOTION_EN     | `[axis u8 (8 = all), on u8]` | –                                |
//! | 12  | SET_STATE     | `[state u8]` (0 go, 3 pause, 4 stop) | –                        |
//! | 13  | GET_STATE     | –                          | `[state u8]`                       |
//! | 15  | GET_ERROR     | –                          | `[error u8, warning u8]`           |
//! | 16  | CLEAN_ERR     | –                          | –                                  |
//! | 19  | SET_MODE      | `[mode u8]` (1 = servo)    | –                                  |
//! | 29  | MOVE_SERVOJ   | 10 × fp32: j1..j7 rad, speed, acc, mvtime | –                   |
//! | 42  | GET_JOINT_POS | – (or `[3]`: pos, vel, effort) | 7 × fp32 rad (21 with `[3]`)   |
//! | 55  | GET_JOINT_TAU | –                          | 7 × fp32 N·m                       |
//!
//! Source: xArm-Python-SDK `xarm/core/wrapper/uxbus_cmd.py` (register helpers such as
//! `motion_en`, `move_servoj`, `get_err_code`, `get_version`), `uxbus_cmd_tcp.py` (framing,
//! transaction id, status bits), `xarm/core/config/x_config.py` (register numbers).
//!
//! # Report frame (port 30003 "real", 30001 "normal")
//!
//! ```text
//! 0   u32 BE  total frame size in bytes (including these 4)
//! 4   u8      state (low nibble) | mode (high nibble)
//! 5   u16 BE  command count
//! 7   7×fp32  joint angles, rad
//! 35  6×fp32  TCP pose (mm, rad)
//! 59  7×fp32  joint torques
//! 87  ...     real: optional F/T data; normal: brake mask @87, enable mask @88,
//!             error code @89, warning code @90, then configuration fields
//! ```
//!
//! The size header fixes the frame length; every frame of one connection has the same size.
//! Source: SDK `xarm/core/comm/base.py` (`recv_report_proc`), `xarm/x3/base.py`
//! (`__handle_report_real`, `__handle_report_normal`).

use crate::error::{Error, Result};

/// Command port.
pub const PORT_CMD: u16 = 502;
/// "Normal" report stream (~5 Hz).
pub const PORT_REPORT_NORMAL: u16 = 30001;
/// "Rich" report stream (~5 Hz).
pub const PORT_REPORT_RICH: u16 = 30002;
/// "Real-time" report stream (~100 Hz).
pub const PORT_REPORT_REAL: u16 = 30003;

/// Private protocol identifier (SDK default).
pub const PROTO_PRIVATE: u16 = 2;

/// Register numbers (SDK `XCONF.UxbusReg`).
pub mod reg {
    /// Firmware version string.
    pub const GET_VERSION: u8 = 1;
    /// Enable/disable motors.
    pub const MOTION_EN: u8 = 11;
    /// Set the motion state.
    pub const SET_STATE: u8 = 12;
    /// Read the motion state.
    pub const GET_STATE: u8 = 13;
    /// Read the error and warning codes.
    pub const GET_ERROR: u8 = 15;
    /// Clear the error.
    pub const CLEAN_ERR: u8 = 16;
    /// Set the control mode.
    pub const SET_MODE: u8 = 19;
    /// Servo-j: joint target executed at once (servo mode only).
    pub const MOVE_SERVOJ: u8 = 29;
    /// Read joint positions.
    pub const GET_JOINT_POS: u8 = 42;
    /// Read joint torques.
    pub const GET_JOINT_TAU: u8 = 55;
}

/// Status bits of a reply.
pub mod status {
    /// The request was invalid.
    pub const INVALID: u8 = 0x08;
    /// The controller is not ready for motion.
    pub const NOT_READY: u8 = 0x10;
    /// A warning is present (read GET_ERROR).
    pub const WARNING: u8 = 0x20;
    /// An error is present (read GET_ERROR).
    pub const ERROR: u8 = 0x40;
}

/// Motion states (`SET_STATE` / `GET_STATE` / report low nibble).
pub mod state {
    /// Start / resume motion.
    pub const GO: u8 = 0;
    /// Moving.
    pub const MOVING: u8 = 1;
    /// Ready, no motion in progress.
    pub const SLEEPING: u8 = 2;
    /// Paused.
    pub const PAUSE: u8 = 3;
    /// Stopped (needs `SET_STATE 0` to move again).
    pub const STOP: u8 = 4;
}

/// Servo mode (`SET_MODE 1`): executes only the newest servo-j target.
pub const MODE_SERVO: u8 = 1;
/// Axis id meaning "all joints" for `MOTION_EN`.
pub const AXIS_ALL: u8 = 8;
/// Length of the version string reply.
pub const VERSION_LEN: usize = 40;
/// Header length of a command/reply frame before the register byte.
pub const HEADER_LEN: usize = 6;
/// Largest length field we accept (the biggest SDK request is a few hundred bytes).
pub const MAX_LENGTH_FIELD: u16 = 4096;

/// The transaction id after `tid`: 1, 2, ..., 65535, then 1 again (0 is never used).
pub fn next_tid(tid: u16) -> u16 {
    tid % u16::MAX + 1
}

/// Append one command frame to `out` (no intermediate allocation).
pub fn encode_command(
    tid: u16,
    proto: u16,
    register: u8,
    params: &[u8],
    out: &mut Vec<u8>,
) -> Result<()> {
    let len = 1 + params.len();
    if len > MAX_LENGTH_FIELD as usize {
        return Err(Error::XArmFrame {
            reason: format!("command of {len} bytes exceeds {MAX_LENGTH_FIELD}"),
        });
    }
    out.extend_from_slice(&tid.to_be_bytes());
    out.extend_from_slice(&proto.to_be_bytes());
    out.extend_from_slice(&(len as u16).to_be_bytes());
    out.push(register);
    out.extend_from_slice(params);
    Ok(())
}

/// One command frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Command {
    /// Transaction id.
    pub tid: u16,
    /// Protocol id.
    pub proto: u16,
    /// Register.
    pub register: u8,
    /// Parameter bytes.
    pub params: Vec<u8>,
}

/// One reply frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reply {
    /// Transaction id (echoes the request's).
    pub tid: u16,
    /// Protocol id.
    pub proto: u16,
    /// Register (echoes the request's).
    pub register: u8,
    /// Status bits (see [`status`]).
    pub status: u8,
    /// Data bytes.
    pub data: Vec<u8>,
}

impl Command {
    /// Append the encoded frame to `out`.
    pub fn encode_into(&self, out: &mut Vec<u8>) -> Result<()> {
        encode_command(self.tid, self.proto, self.register, &self.params, out)
    }
    /// The encoded frame.
    pub fn encode(&self) -> Result<Vec<u8>> {
        let mut v = Vec::with_capacity(HEADER_LEN + 1 + self.params.len());
        self.encode_into(&mut v)?;
        Ok(v)
    }
    /// Decode exactly one complete frame.
    pub fn decode(frame: &[u8]) -> Result<Self> {
        let (tid, proto, body) = split_frame(frame, 1)?;
        Ok(Command {
            tid,
            proto,
            register: body[0],
            params: body[1..].to_vec(),
        })
    }
}

impl Reply {
    /// The encoded frame.
    pub fn encode(&self) -> Result<Vec<u8>> {
        let len = 2 + self.data.len();
        if len > MAX_LENGTH_FIELD as usize {
            return Err(Error::XArmFrame {
                reason: format!("reply of {len} bytes exceeds {MAX_LENGTH_FIELD}"),
            });
        }
        let mut out = Vec::with_capacity(HEADER_LEN + len);
        out.extend_from_slice(&self.tid.to_be_bytes());
        out.extend_from_slice(&self.proto.to_be_bytes());
        out.extend_from_slice(&(len as u16).to_be_bytes());
        out.push(self.register);
        out.push(self.status);
        out.extend_from_slice(&self.data);
        Ok(out)
    }
    /// Decode exactly one complete frame.
    pub fn decode(frame: &[u8]) -> Result<Self> {
        let (tid, proto, body) = split_frame(frame, 2)?;
        Ok(Reply {
            tid,
            proto,
            register: body[0],
            status: body[1],
            data: body[2..].to_vec(),
        })
    }
}

/// Check the header of one complete frame and return `(tid, proto, body)`.
fn split_frame(frame: &[u8], min_len: u16) -> Result<(u16, u16, &[u8])> {
    if frame.len() < HEADER_LEN {
        return Err(Error::XArmFrame {
            reason: format!("{} bytes is shorter than the 6-byte header", frame.len()),
        });
    }
    let tid = u16::from_be_bytes([frame[0], frame[1]]);
    let proto = u16::from_be_bytes([frame[2], frame[3]]);
    let len = u16::from_be_bytes([frame[4], frame[5]]);
    if len < min_len || len > MAX_LENGTH_FIELD {
        return Err(Error::XArmFrame {
            reason: format!("length field {len} outside {min_len}..={MAX_LENGTH_FIELD}"),
        });
    }
    if frame.len() != HEADER_LEN + len as usize {
        return Err(Error::XArmFrame {
            reason: format!(
                "length field {len} implies {} bytes, frame has {}",
                HEADER_LEN + len as usize,
                frame.len()
            ),
        });
    }
    Ok((tid, proto, &frame[HEADER_LEN..]))
}

/// Splits a byte stream into command/reply frames by their length field.
#[derive(Debug, Default)]
pub struct FrameBuf {
    buf: Vec<u8>,
}

impl FrameBuf {
    /// An empty buffer.
    pub fn new() -> Self {
        Self::default()
    }
    /// Append received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }
    /// Bytes waiting for the rest of their frame.
    pub fn pending(&self) -> usize {
        self.buf.len()
    }
    /// Drop everything buffered (after a framing error the stream cannot be resynchronised).
    pub fn clear(&mut self) {
        self.buf.clear();
    }
    /// Take the next complete frame, if any. A length field outside `2..=MAX_LENGTH_FIELD`
    /// is an error (the stream is garbage); the buffer is cleared then.
    pub fn next_frame(&mut self) -> Result<Option<Vec<u8>>> {
        if self.buf.len() < HEADER_LEN {
            return Ok(None);
        }
        let len = u16::from_be_bytes([self.buf[4], self.buf[5]]);
        if !(1..=MAX_LENGTH_FIELD).contains(&len) {
            self.buf.clear();
            return Err(Error::XArmFrame {
                reason: format!("length field {len} outside 1..={MAX_LENGTH_FIELD}"),
            });
        }
        let total = HEADER_LEN + len as usize;
        if self.buf.len() < total {
            return Ok(None);
        }
        let frame: Vec<u8> = self.buf.drain(..total).collect();
        Ok(Some(frame))
    }
}

/// Encode `values` as little-endian fp32.
pub fn fp32s_le(values: &[f32]) -> Vec<u8> {
    let mut v = Vec::with_capacity(values.len() * 4);
    for x in values {
        v.extend_from_slice(&x.to_le_bytes());
    }
    v
}

/// Decode `out.len()` little-endian fp32 from the front of `bytes`.
pub fn read_fp32s_le(bytes: &[u8], out: &mut [f32]) -> Result<()> {
    if bytes.len() < out.len() * 4 {
        return Err(Error::XArmFrame {
            reason: format!("{} bytes cannot hold {} fp32", bytes.len(), out.len()),
        });
    }
    for (i, o) in out.iter_mut().enumerate() {
        let b = &bytes[4 * i..4 * i + 4];
        *o = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    }
    Ok(())
}

/// Parameters of a servo-j request: 7 joint targets (j7 = 0 on a 6-axis arm), speed, acc,
/// mvtime (all three ignored by the controller in servo mode; sent as 0).
pub fn servoj_params(joints6: &[f32; 6]) -> Vec<u8> {
    let mut v = [0f32; 10];
    v[..6].copy_from_slice(joints6);
    fp32s_le(&v)
}

// ---------------------------------------------------------------------------------------------
// Reports
// ---------------------------------------------------------------------------------------------

/// Which report stream a frame came from (the layouts differ after byte 87).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReportKind {
    /// Port 30003: 87 bytes (135 with F/T data).
    Real,
    /// Port 30001/30002: 87 common bytes, then masks, error and warning codes, configuration.
    Normal,
}

/// Size of the common part of every report.
pub const REPORT_COMMON_LEN: usize = 87;
/// Size of a "real" report without F/T data.
pub const REPORT_REAL_LEN: usize = 87;
/// Size of a "normal" report on older firmware.
pub const REPORT_NORMAL_LEN: usize = 133;
/// Size of a "rich" report (normal layout plus configuration blocks).
pub const REPORT_RICH_LEN: usize = 233;
/// Largest report size we accept.
pub const REPORT_MAX_LEN: u32 = 1024;

/// The fields of a report this crate uses.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Report {
    /// Motion state (low nibble of byte 4).
    pub state: u8,
    /// Control mode (high nibble of byte 4).
    pub mode: u8,
    /// Command count.
    pub cmd_num: u16,
    /// Joint angles, rad.
    pub angles: [f32; 7],
    /// TCP pose (x, y, z mm; roll, pitch, yaw rad).
    pub pose: [f32; 6],
    /// Joint torques.
    pub torques: [f32; 7],
    /// Error code (normal reports only; 0 in real reports).
    pub error: u8,
    /// Warning code (normal reports only; 0 in real reports).
    pub warning: u8,
}

impl Report {
    /// Parse one complete report frame (size header included).
    pub fn parse(frame: &[u8], kind: ReportKind) -> Result<Self> {
        if frame.len() < 4 {
            return Err(Error::XArmReportSize {
                expected: REPORT_COMMON_LEN as u32,
                got: frame.len() as u32,
            });
        }
        let size = u32::from_be_bytes([frame[0], frame[1], frame[2], frame[3]]);
        let min = match kind {
            ReportKind::Real => REPORT_COMMON_LEN,
            ReportKind::Normal => REPORT_COMMON_LEN + 4,
        };
        if (size as usize) < min || size as usize != frame.len() {
            return Err(Error::XArmReportSize {
                expected: frame.len().max(min) as u32,
                got: size,
            });
        }
        let mut r = Report {
            state: frame[4] & 0x0f,
            mode: frame[4] >> 4,
            ..Report::default()
        };
        r.cmd_num = u16::from_be_bytes([frame[5], frame[6]]);
        read_fp32s_le(&frame[7..], &mut r.angles)?;
        read_fp32s_le(&frame[35..], &mut r.pose)?;
        read_fp32s_le(&frame[59..], &mut r.torques)?;
        if kind == ReportKind::Normal {
            r.error = frame[89];
            r.warning = frame[90];
        }
        Ok(r)
    }

    /// Encode as a frame of `size` bytes (≥ 87; ≥ 91 for normal reports); bytes not modelled
    /// here are zero.
    pub fn encode(&self, kind: ReportKind, size: usize) -> Result<Vec<u8>> {
        let min = match kind {
            ReportKind::Real => REPORT_COMMON_LEN,
            ReportKind::Normal => REPORT_COMMON_LEN + 4,
        };
        if size < min || size > REPORT_MAX_LEN as usize {
            return Err(Error::XArmReportSize {
                expected: min as u32,
                got: size as u32,
            });
        }
        let mut f = vec![0u8; size];
        f[..4].copy_from_slice(&(size as u32).to_be_bytes());
        f[4] = (self.state & 0x0f) | (self.mode << 4);
        f[5..7].copy_from_slice(&self.cmd_num.to_be_bytes());
        f[7..35].copy_from_slice(&fp32s_le(&self.angles));
        f[35..59].copy_from_slice(&fp32s_le(&self.pose));
        f[59..87].copy_from_slice(&fp32s_le(&self.torques));
        if kind == ReportKind::Normal {
            f[89] = self.error;
            f[90] = self.warning;
        }
        Ok(f)
    }
}

/// Splits a report stream into frames by the size header. The first frame fixes the size;
/// a later header that differs is an error (the SDK closes the stream then, so do we).
#[derive(Debug)]
pub struct ReportBuf {
    kind: ReportKind,
    size: Option<u32>,
    buf: Vec<u8>,
}

impl ReportBuf {
    /// An empty buffer for a stream of `kind`.
    pub fn new(kind: ReportKind) -> Self {
        Self {
            kind,
            size: None,
            buf: Vec::new(),
        }
    }
    /// Append received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }
    /// The frame size locked on the first frame.
    pub fn size(&self) -> Option<u32> {
        self.size
    }
    /// Parse the next complete report, if any.
    pub fn next_report(&mut self) -> Result<Option<Report>> {
        if self.buf.len() < 4 {
            return Ok(None);
        }
        let size = u32::from_be_bytes([self.buf[0], self.buf[1], self.buf[2], self.buf[3]]);
        let min = REPORT_COMMON_LEN as u32
            + if self.kind == ReportKind::Normal {
                4
            } else {
                0
            };
        match self.size {
            Some(locked) if locked != size => {
                self.buf.clear();
                return Err(Error::XArmReportSize {
                    expected: locked,
                    got: size,
                });
            }
            None if !(min..=REPORT_MAX_LEN).contains(&size) => {
                self.buf.clear();
                return Err(Error::XArmReportSize {
                    expected: min,
                    got: size,
                });
            }
            _ => {}
        }
        if self.buf.len() < size as usize {
            return Ok(None);
        }
        self.size = Some(size);
        let frame: Vec<u8> = self.buf.drain(..size as usize).collect();
        Report::parse(&frame, self.kind).map(Some)
    }
}
