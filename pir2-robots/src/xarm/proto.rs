//! UFACTORY xArm wire protocol as controller firmware speaks it: command frames (port 502),
//! the version string, and the report streams (ports 30001–30003).
//!
//! One file on purpose: the frame layouts, the register table and their encoders/decoders are the
//! protocol reference in one place, read side by side with UFACTORY's SDK.
//!
//! This module doc is the crate's reference for the protocol. **Source:** UFACTORY's
//! official Python SDK, `xarm-python-sdk` 1.18.4 (PyPI; repository
//! xArm-Developer/xArm-Python-SDK), files `xarm/core/comm/base.py` (stream framing, report
//! size handling), `xarm/core/comm/socket_port.py` (ports, keep-alive frame),
//! `xarm/core/wrapper/uxbus_cmd.py` and `uxbus_cmd_tcp.py` (register helpers, header checks,
//! status bits), `xarm/core/config/x_config.py` (register numbers, ports, joint limits),
//! `xarm/x3/base.py` (connect sequence, version parsing, protocol switch, report handlers,
//! report validation), `xarm/x3/report.py` (report structures) and `xarm/x3/decorator.py`.
//! Where the SDK is the only evidence of what firmware sends, the SDK's acceptance rules are
//! what we implement and test: a controller the SDK talks to is a controller we talk to.
//!
//! # Ports
//!
//! | port  | direction           | content                                             |
//! |-------|---------------------|-----------------------------------------------------|
//! | 502   | request / reply     | command frames below                                |
//! | 30001 | controller → client | "normal" report, ~5 Hz                              |
//! | 30002 | controller → client | "rich" report, ~5 Hz (the SDK's default stream)     |
//! | 30003 | controller → client | "real-time" report, ~100 Hz                         |
//!
//! The report ports push frames as soon as a client connects; nothing is ever sent to them.
//! The SDK closes a report connection after 4 socket timeouts of 1 s in a row, so a stream
//! must deliver at least one frame every ~3 s.
//!
//! # Command frame (client → controller) and reply (controller → client)
//!
//! ```text
//! request:  tid u16 BE | proto u16 BE | length u16 BE = 1 + n | register u8 | params[n]
//! reply:    tid u16 BE | proto u16 BE | length u16 BE = 2 + n | register u8 | status u8 | data[n]
//! ```
//!
//! * `tid` starts at 1 and goes `tid % 65535 + 1` (0 is never used by a request).
//! * The reply echoes tid, protocol id and register. The SDK skips a reply with another tid
//!   (it answers an older request) and fails a request whose reply has another protocol id
//!   ("protocol error") or another register ("function error").
//! * A byte stream is split into frames by `6 + length`, never by `recv` boundaries: the SDK
//!   reads the port 1 024 bytes at a time and cuts frames out of its buffer.
//! * Header integers and u16 data are big-endian; **fp32 and int32 data are little-endian**.
//! * A reply whose register byte is `0xFF` is an asynchronous motion-feedback frame (firmware
//!   ≥ 2.0.102), not an answer; the SDK routes it to a separate queue.
//!
//! ## Protocol id
//!
//! 2 is the private protocol. After connecting, the SDK reads the version and, when the
//! firmware is ≥ 1.8.6, switches every later request to protocol id **3**; the controller
//! answers with the id of the request. Firmware older than 1.8.6 stays on 2.
//!
//! ## Keep-alive traffic
//!
//! * With protocol id 3 the SDK keeps the command connection alive itself: when nothing was
//!   exchanged for 30 s it sends `GET_STATE` (at most every 10 s), and it gives the
//!   connection up after 90 s without any reply. Its timed-communication thread does the
//!   same with `GET_CMDNUM` / `GET_STATE` / `GET_ERROR` in turn.
//! * An optional heartbeat (SDK `enable_heartbeat`, off by default) writes the 8 bytes
//!   `00 00 00 01 00 02 00 00` (tid 0, protocol id 1, length 2, two zero bytes) once a
//!   second. Its tid 0 never matches a request, so any answer is ignored by the SDK; the
//!   emulator sends none.
//!
//! ## Status byte of a reply
//!
//! | bit  | meaning                 | what the SDK makes of it                                   |
//! |------|-------------------------|------------------------------------------------------------|
//! | 0x08 | invalid request         | code 10 for every call                                     |
//! | 0x10 | not ready for motion    | motion commands (servo-j, move-j, …) fail with code 9; other calls succeed |
//! | 0x20 | a warning is latched    | code 2; treated as success by every call                   |
//! | 0x40 | an error is latched     | code 1; success for set/get calls, failure for motion commands |
//!
//! "Not ready" is set while the motors are disabled, in state 4/5, or in a mode that does
//! not take the command (servo-j needs mode 1 and `SET_STATE 0` after the mode change).
//!
//! # Registers used here
//!
//! | reg | name           | request params                        | reply data                              |
//! |-----|----------------|---------------------------------------|-----------------------------------------|
//! | 1   | GET_VERSION    | –                                     | 40 bytes ASCII, NUL padded              |
//! | 2   | GET_ROBOT_SN   | –                                     | 40 bytes ASCII, NUL padded              |
//! | 11  | MOTION_EN      | `[axis u8 (8 = all), on u8]`          | –                                       |
//! | 12  | SET_STATE      | `[state u8]` (0 go, 3 pause, 4 stop)  | –                                       |
//! | 13  | GET_STATE      | –                                     | `[state u8]`                            |
//! | 14  | GET_CMDNUM     | –                                     | `[count u16 BE]`                        |
//! | 15  | GET_ERROR      | –                                     | `[error u8, warning u8]`                |
//! | 16  | CLEAN_ERR      | –                                     | –                                       |
//! | 17  | CLEAN_WAR      | –                                     | –                                       |
//! | 19  | SET_MODE       | `[mode u8, detection u8]` (fw ≥ 1.10.0), `[mode u8]` before | –                 |
//! | 29  | MOVE_SERVOJ    | 10 × fp32: j1..j7 rad, speed, acc, mvtime | –                                   |
//! | 41  | GET_TCP_POSE   | –                                     | 6 × fp32 (mm, rad)                      |
//! | 42  | GET_JOINT_POS  | – → 7 × fp32 rad; or `[n u8]` (fw ≥ 1.9.0) → `7·(n & 0x0F)` fp32: positions, velocities, efforts | |
//! | 55  | GET_JOINT_TAU  | –                                     | 7 × fp32 N·m                            |
//!
//! Servo-j always carries 7 joints; a 6-axis arm gets `j7 = 0`. Speed, acceleration and time
//! are not used by servo mode. The SDK's `get_servo_angle(is_real=True)` uses the
//! `GET_JOINT_POS [1]` form on firmware ≥ 1.9.110 (the measured positions); the form with
//! `n = 3` returns positions, velocities and efforts in one reply. The high nibble of `n`
//! is only passed through on firmware ≥ 2.6.107 and unused here.
//!
//! # Version string (GET_VERSION)
//!
//! Current firmware answers `axis,type,robot-SN,control-box-SN,vX.Y.Z`, for example
//! `6,6,XI1304,AC1303,v2.6.0`. From it the SDK takes:
//!
//! | field      | example      | used for                                                       |
//! |------------|--------------|----------------------------------------------------------------|
//! | axis       | `6`          | the number of joints (5, 6 or 7); servo-j zeroes joints past it |
//! | type       | `6`          | arm model (6 = xArm6 X4, 9 = Lite 6, 12 = 850, …), joint-limit table |
//! | robot SN   | `XI1304…`    | `X` + axis letter (`F` 5, `I` 6, `S` 7) + 4-digit hardware revision; revision ≥ 1305 selects the later joint-limit table, ≥ 1300 marks "type 1300" hardware |
//! | box SN     | `AC1303…`    | control box revision (≥ 1300: more controller GPIO)            |
//! | version    | `v2.6.0`     | every firmware switch below                                    |
//!
//! The reply is 40 bytes, NUL padded; the SDK cuts the string at the first NUL and, when
//! there is none, drops the last character (a 40-character string loses its last digit).
//! The serial numbers in the string are 6-character prefixes (`XI1304`); GET_ROBOT_SN
//! answers the full 14-character number. The SDK matches the string with one greedy pattern; when it does not match (no commas)
//! it falls back to any `X.Y.Z` in the string and **keeps its default axis, 7**. With neither
//! (an old `…-YYYY-MM-DD` date string before 2019-02-01) it uses the "V0" protocol below.
//!
//! Firmware switches in the SDK: protocol id 3 from 1.8.6; the readiness check before motion
//! commands only before 1.5.20; the `GET_JOINT_POS [n]` form from 1.9.0 (measured positions
//! from 1.9.110); the two-byte `SET_MODE` from 1.10.0; motion feedback frames from 2.0.102.
//!
//! # Report frames
//!
//! Every report starts with its total size as a **u32 BE** (header included). The SDK reads
//! the size of the first frame and then expects every frame of the connection to have it; a
//! different size header closes the stream. One exception: a size header of **233** on the
//! rich port is taken to mean a 245-byte frame (firmware that did not update the header when
//! 12 bytes were added), unless the next size header follows at byte 233.
//!
//! Common part (all three ports on current firmware):
//!
//! ```text
//! 0   u32 BE   total size
//! 4   u8       state (low nibble) | mode (high nibble)
//! 5   u16 BE   command count (queued motion commands)
//! 7   7×fp32   joint angles, rad
//! 35  6×fp32   TCP pose: x, y, z mm; roll, pitch, yaw rad
//! 59  7×fp32   joint torques (estimated), N·m
//! ```
//!
//! Port 30003 ("real"): the common part, **87** bytes on old firmware and **135** on current
//! firmware, which adds external F/T force `6×fp32 @87` and raw F/T force `6×fp32 @111`.
//!
//! Port 30001 ("normal"), **133** bytes (legacy) or **145** (current):
//!
//! ```text
//! 87  u8       motor brake bits (bit i = joint i+1 released)
//! 88  u8       motor enable bits (bit i = joint i+1 enabled)
//! 89  u8       error code
//! 90  u8       warning code
//! 91  6×fp32   TCP offset
//! 115 4×fp32   TCP payload: mass kg, centre of mass x, y, z mm
//! 131 u8       collision sensitivity (0..=5)
//! 132 u8       teach sensitivity (0..=5)
//! 133 3×fp32   gravity direction (current firmware only)
//! ```
//!
//! Port 30002 ("rich"): the normal layout, then (offsets on current firmware; the SDK reads
//! each block only if the frame is long enough; **587** bytes is the full layout SDK 1.18.4
//! knows, legacy firmware sends 233/245):
//!
//! ```text
//! 145 6×u8     arm type, axis count, master id, slave id, motor tid, motor fid
//! 151 30 B     version text
//! 181 12×fp32  TCP jerk, TCP min/max acc, TCP min/max speed, joint jerk, joint min/max acc,
//!              joint min/max speed, rotation jerk, rotation max acc
//! 229 16×u8    servo (status, code) per joint 1..7, then the tool board's pair
//! 245 7×i8     joint temperatures, °C                                   (frame ≥ 252)
//! 252 8×fp32   TCP speed, then 7 joint speeds                           (frame ≥ 284)
//! 284 u32 BE   counter                                                  (frame ≥ 288)
//! 288 6×fp32   world offset                                             (frame ≥ 312)
//! 312 2×u8     controller / tool GPIO reset-on-stop flags                (frame ≥ 314)
//! 314 u8       simulation robot flag; 315 collision detection on; 316 collision tool type;
//! 317 6×fp32   collision tool parameters; 341 7×u16 BE joint voltages (/100 V);
//! 355 7×fp32   joint currents; 383..417 controller GPIO block               (frame ≥ 417)
//! 417 16 B     more controller GPIO configuration (type-1300 boxes)       (frame ≥ 433)
//! 433 6×fp32   external F/T force; 457 6×fp32 raw F/T force              (frame ≥ 481)
//! 481 u8       identification progress; 482 3×fp32 axis-angle pose      (frame ≥ 494)
//! 494 u8       configuration bits (reduced mode, fence, current report, approx motion, …)
//! 495..574     reduced-mode limits; 574 u32 GPIO alarm; 578 switches; 579..587 monitor
//! ```
//!
//! ## What the SDK validates
//!
//! On the normal and rich streams the SDK closes the connection when the size header
//! differs from the bytes of the frame (except 233/245 as above), the collision or teach
//! sensitivity is outside 0..=5, the mode is ≥ 12 or the state is ≥ 10. The real stream is
//! not validated beyond its size. The simulation flag (rich byte 314) matters: when it is
//! set, the SDK's `motion_enable` returns 0 without sending anything. The SDK treats the arm
//! as not ready when a report shows state 4 or 5 or, on normal/rich, a joint whose brake or
//! enable bit is clear; it also ignores reported angles while the error code is 1..=17.
//!
//! ## V0 (firmware before 2019-02-01)
//!
//! The oldest firmware reports `state, brake bits, enable bits, error, warning` at bytes
//! 4..9, angles at 9, pose at 37, the command count at 61 and the TCP offset at 63 (87
//! bytes; the rich stream appends type, axis, ids, version and limits to 187 bytes). This
//! crate refuses V0 firmware (see [`FirmwareVersion::parse`]).
//!
//! # Motion states
//!
//! 0 go (request only), 1 moving, 2 sleeping (ready, idle), 3 paused, 4 stopped, 5 not
//! ready / emergency stop, 6 (reported during some transitions). States 4 and 5 mean "not
//! ready"; after a mode change the controller needs `SET_STATE 0` before it moves.

use crate::error::{Error, Result};

/// Command port.
pub const PORT_CMD: u16 = 502;
/// "Normal" report stream (~5 Hz).
pub const PORT_REPORT_NORMAL: u16 = 30001;
/// "Rich" report stream (~5 Hz).
pub const PORT_REPORT_RICH: u16 = 30002;
/// "Real-time" report stream (~100 Hz).
pub const PORT_REPORT_REAL: u16 = 30003;

/// Private protocol identifier (what every request uses until the version is known).
pub const PROTO_PRIVATE: u16 = 2;
/// Private protocol identifier the SDK switches to on firmware ≥ 1.8.6.
pub const PROTO_PRIVATE_V3: u16 = 3;
/// Protocol id of the SDK's optional heartbeat frame.
pub const PROTO_HEARTBEAT: u16 = 1;
/// The SDK's optional heartbeat frame (tid 0, protocol 1, length 2, two zero bytes).
pub const HEARTBEAT_FRAME: [u8; 8] = [0, 0, 0, 1, 0, 2, 0, 0];
/// Register byte of an asynchronous motion-feedback frame on the command port.
pub const FEEDBACK_REGISTER: u8 = 0xFF;

/// Register numbers (SDK `XCONF.UxbusReg`).
pub mod reg {
    /// Firmware version string.
    pub const GET_VERSION: u8 = 1;
    /// Robot serial number.
    pub const GET_ROBOT_SN: u8 = 2;
    /// Enable/disable motors.
    pub const MOTION_EN: u8 = 11;
    /// Set the motion state.
    pub const SET_STATE: u8 = 12;
    /// Read the motion state.
    pub const GET_STATE: u8 = 13;
    /// Read the number of queued motion commands.
    pub const GET_CMDNUM: u8 = 14;
    /// Read the error and warning codes.
    pub const GET_ERROR: u8 = 15;
    /// Clear the error.
    pub const CLEAN_ERR: u8 = 16;
    /// Clear the warning.
    pub const CLEAN_WAR: u8 = 17;
    /// Set the control mode.
    pub const SET_MODE: u8 = 19;
    /// Servo-j: joint target executed at once (servo mode only).
    pub const MOVE_SERVOJ: u8 = 29;
    /// Read the TCP pose.
    pub const GET_TCP_POSE: u8 = 41;
    /// Read joint positions (or positions, velocities, efforts).
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
    /// Not ready (e.g. emergency stop).
    pub const NOT_READY: u8 = 5;
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

// ---------------------------------------------------------------------------------------------
// Version string
// ---------------------------------------------------------------------------------------------

/// What a GET_VERSION string says (see the module docs, "Version string").
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FirmwareVersion {
    /// The string as received (NULs and surrounding blanks removed).
    pub text: String,
    /// Number of joints, when the string names it.
    pub axis: Option<u8>,
    /// Arm type, when the string names it.
    pub arm_type: Option<u8>,
    /// Robot serial number (or its prefix), when the string names it.
    pub robot_sn: Option<String>,
    /// Control box serial number (or its prefix), when the string names it.
    pub control_box_sn: Option<String>,
    /// `(major, minor, patch)`.
    pub number: (u32, u32, u32),
}

impl FirmwareVersion {
    /// Parse a version string. Errors for the pre-2019 "V0" date strings and for anything
    /// without an `X.Y.Z` version number: this crate speaks only the V1 protocol.
    pub fn parse(s: &str) -> Result<Self> {
        let s = s.trim_matches(char::from(0)).trim();
        let number = last_version_number(s).ok_or_else(|| Error::XArmFrame {
            reason: format!(
                "firmware version string {s:?} has no X.Y.Z version number (V0 firmware from \
                 before 2019 is not supported)"
            ),
        })?;
        let parts: Vec<&str> = s.split(',').collect();
        let mut v = FirmwareVersion {
            text: s.to_string(),
            axis: None,
            arm_type: None,
            robot_sn: None,
            control_box_sn: None,
            number,
        };
        if parts.len() >= 5 {
            if let (Ok(axis), Ok(ty)) = (parts[0].trim().parse(), parts[1].trim().parse()) {
                v.axis = Some(axis);
                v.arm_type = Some(ty);
                v.robot_sn = Some(parts[2].trim().to_string());
                v.control_box_sn = Some(parts[3].trim().to_string());
            }
        }
        Ok(v)
    }
    /// Whether the firmware is at least `major.minor.patch`.
    pub fn at_least(&self, major: u32, minor: u32, patch: u32) -> bool {
        self.number >= (major, minor, patch)
    }
    /// The protocol id to use after the version is known (3 from 1.8.6 on).
    pub fn protocol_id(&self) -> u16 {
        if self.at_least(1, 8, 6) {
            PROTO_PRIVATE_V3
        } else {
            PROTO_PRIVATE
        }
    }
    /// SET_MODE parameters for `mode` (two bytes, detection parameter 0, from 1.10.0 on).
    pub fn set_mode_params(&self, mode: u8) -> Vec<u8> {
        if self.at_least(1, 10, 0) {
            vec![mode, 0]
        } else {
            vec![mode]
        }
    }
    /// Whether `GET_JOINT_POS [3]` (measured positions, velocities, efforts in one reply)
    /// is available (1.9.110 on; see the module docs).
    pub fn has_joint_states(&self) -> bool {
        self.at_least(1, 9, 110)
    }
}

/// The last `X.Y.Z` (optionally after `v`/`V`) in `s`.
fn last_version_number(s: &str) -> Option<(u32, u32, u32)> {
    let b = s.as_bytes();
    let mut best = None;
    let mut i = 0;
    while i < b.len() {
        if b[i].is_ascii_digit() && (i == 0 || !b[i - 1].is_ascii_digit()) {
            let mut nums = [0u32; 3];
            let mut j = i;
            let mut ok = true;
            for (k, n) in nums.iter_mut().enumerate() {
                let st = j;
                while j < b.len() && b[j].is_ascii_digit() {
                    j += 1;
                }
                if j == st || j - st > 9 {
                    ok = false;
                    break;
                }
                *n = s[st..j].parse().unwrap_or(0);
                if k < 2 {
                    if j < b.len() && b[j] == b'.' {
                        j += 1;
                    } else {
                        ok = false;
                        break;
                    }
                }
            }
            if ok {
                best = Some((nums[0], nums[1], nums[2]));
                i = j;
                continue;
            }
        }
        i += 1;
    }
    best
}

// ---------------------------------------------------------------------------------------------
// Command and reply frames
// ---------------------------------------------------------------------------------------------

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
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ReportKind {
    /// Port 30003: 87 bytes (legacy) or 135 (with F/T data).
    Real,
    /// Port 30001: 133 bytes (legacy) or 145 (with the gravity direction).
    Normal,
    /// Port 30002: the normal layout plus configuration blocks; 233/245 legacy, 587 current.
    Rich,
}

impl ReportKind {
    /// The standard port of the stream.
    pub fn port(self) -> u16 {
        match self {
            ReportKind::Real => PORT_REPORT_REAL,
            ReportKind::Normal => PORT_REPORT_NORMAL,
            ReportKind::Rich => PORT_REPORT_RICH,
        }
    }
    /// Smallest frame this crate accepts on the stream (the legacy size).
    pub fn min_len(self) -> usize {
        match self {
            ReportKind::Real => REPORT_REAL_LEGACY_LEN,
            ReportKind::Normal => REPORT_NORMAL_LEGACY_LEN,
            ReportKind::Rich => REPORT_RICH_LEGACY_LEN,
        }
    }
    /// Frame size on current firmware.
    pub fn current_len(self) -> usize {
        match self {
            ReportKind::Real => REPORT_REAL_LEN,
            ReportKind::Normal => REPORT_NORMAL_LEN,
            ReportKind::Rich => REPORT_RICH_LEN,
        }
    }
}

/// Size of the common part of every report.
pub const REPORT_COMMON_LEN: usize = 87;
/// "Real" report on old firmware (common part only).
pub const REPORT_REAL_LEGACY_LEN: usize = 87;
/// "Real" report on current firmware (with F/T data).
pub const REPORT_REAL_LEN: usize = 135;
/// "Normal" report on old firmware (no gravity direction).
pub const REPORT_NORMAL_LEGACY_LEN: usize = 133;
/// "Normal" report on current firmware.
pub const REPORT_NORMAL_LEN: usize = 145;
/// "Rich" report size header of old firmware (the frame may really be 245 bytes).
pub const REPORT_RICH_LEGACY_LEN: usize = 233;
/// "Rich" report of old firmware once the gravity direction was added.
pub const REPORT_RICH_LEGACY_FULL_LEN: usize = 245;
/// "Rich" report with every block SDK 1.18.4 knows.
pub const REPORT_RICH_LEN: usize = 587;
/// Largest report size we accept.
pub const REPORT_MAX_LEN: u32 = 4096;

/// Rich-report information past the normal layout (current offsets; see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RichInfo {
    /// Arm type (6 = xArm6).
    pub arm_type: u8,
    /// Number of joints.
    pub axis: u8,
    /// Version text (NUL padded).
    pub version: [u8; 30],
    /// TCP jerk, TCP min/max acc, TCP min/max speed, joint jerk, joint min/max acc, joint
    /// min/max speed, rotation jerk, rotation max acc.
    pub limits: [f32; 12],
    /// Servo (status, code) pairs, joints 1..7 then the tool board.
    pub servo_codes: [u8; 16],
    /// Joint temperatures, °C (frames ≥ 252 bytes).
    pub temperatures: Option<[i8; 7]>,
    /// Counter (frames ≥ 288 bytes).
    pub counter: Option<u32>,
    /// Simulation-robot flag (frames ≥ 417 bytes).
    pub simulation: Option<bool>,
    /// Collision detection on (frames ≥ 417 bytes).
    pub collision_detection: Option<bool>,
}

impl RichInfo {
    /// The version text up to the first NUL.
    pub fn version_str(&self) -> String {
        let end = self.version.iter().position(|&b| b == 0).unwrap_or(30);
        String::from_utf8_lossy(&self.version[..end]).into_owned()
    }
}

/// One parsed report frame.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Report {
    /// Frame size in bytes.
    pub size: u32,
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
    /// External and raw F/T force (real ≥ 135 bytes, rich ≥ 481 bytes).
    pub ft: Option<([f32; 6], [f32; 6])>,
    /// Motor brake bits (normal/rich; 0 in real reports).
    pub brake_bits: u8,
    /// Motor enable bits (normal/rich; 0 in real reports).
    pub enable_bits: u8,
    /// Error code (normal/rich; 0 in real reports).
    pub error: u8,
    /// Warning code (normal/rich; 0 in real reports).
    pub warning: u8,
    /// TCP offset (normal/rich).
    pub tcp_offset: [f32; 6],
    /// TCP payload: mass, centre of mass x, y, z (normal/rich).
    pub tcp_load: [f32; 4],
    /// Collision sensitivity 0..=5 (normal/rich).
    pub collision_sens: u8,
    /// Teach sensitivity 0..=5 (normal/rich).
    pub teach_sens: u8,
    /// Gravity direction (normal ≥ 145 bytes, rich ≥ 245 bytes).
    pub gravity: Option<[f32; 3]>,
    /// Rich-only information (rich frames ≥ 245 bytes).
    pub rich: Option<RichInfo>,
}

fn f32s<const N: usize>(b: &[u8], at: usize) -> [f32; N] {
    std::array::from_fn(|i| {
        let o = at + 4 * i;
        f32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
    })
}

fn put_f32s(b: &mut [u8], at: usize, v: &[f32]) {
    for (i, x) in v.iter().enumerate() {
        b[at + 4 * i..at + 4 * i + 4].copy_from_slice(&x.to_le_bytes());
    }
}

impl Report {
    /// Parse one complete report frame of a stream of `kind` (size header included), with
    /// the SDK's checks: size header equal to the frame length (233 for a 245-byte rich
    /// frame), at least the legacy size of the stream, and on normal/rich streams the
    /// sensitivities in 0..=5, mode < 12, state < 10.
    pub fn parse(frame: &[u8], kind: ReportKind) -> Result<Self> {
        let min = kind.min_len();
        if frame.len() < 4 {
            return Err(Error::XArmReportSize {
                expected: min as u32,
                got: frame.len() as u32,
            });
        }
        let size = u32::from_be_bytes([frame[0], frame[1], frame[2], frame[3]]);
        let quirk = kind == ReportKind::Rich
            && size as usize == REPORT_RICH_LEGACY_LEN
            && frame.len() == REPORT_RICH_LEGACY_FULL_LEN;
        if (size as usize) < min || (size as usize != frame.len() && !quirk) {
            return Err(Error::XArmReportSize {
                expected: frame.len().max(min) as u32,
                got: size,
            });
        }
        let n = frame.len();
        let mut r = Report {
            size: n as u32,
            state: frame[4] & 0x0f,
            mode: frame[4] >> 4,
            cmd_num: u16::from_be_bytes([frame[5], frame[6]]),
            angles: f32s(frame, 7),
            pose: f32s(frame, 35),
            torques: f32s(frame, 59),
            ..Report::default()
        };
        match kind {
            ReportKind::Real => {
                if n >= REPORT_REAL_LEN {
                    r.ft = Some((f32s(frame, 87), f32s(frame, 111)));
                }
            }
            ReportKind::Normal | ReportKind::Rich => {
                r.brake_bits = frame[87];
                r.enable_bits = frame[88];
                r.error = frame[89];
                r.warning = frame[90];
                r.tcp_offset = f32s(frame, 91);
                r.tcp_load = f32s(frame, 115);
                r.collision_sens = frame[131];
                r.teach_sens = frame[132];
                let check = |field: &str, v: u8, limit: u8| {
                    if v > limit {
                        Err(Error::XArmFrame {
                            reason: format!("{kind:?} report: {field} {v} outside 0..={limit}"),
                        })
                    } else {
                        Ok(())
                    }
                };
                check("collision sensitivity", r.collision_sens, 5)?;
                check("teach sensitivity", r.teach_sens, 5)?;
                check("mode", r.mode, 11)?;
                check("state", r.state, 9)?;
                if n >= REPORT_NORMAL_LEN {
                    r.gravity = Some(f32s(frame, 133));
                }
                if kind == ReportKind::Rich && n >= REPORT_RICH_LEGACY_FULL_LEN {
                    let mut info = RichInfo {
                        arm_type: frame[145],
                        axis: frame[146],
                        limits: f32s(frame, 181),
                        ..RichInfo::default()
                    };
                    info.version.copy_from_slice(&frame[151..181]);
                    info.servo_codes.copy_from_slice(&frame[229..245]);
                    if n >= 252 {
                        info.temperatures = Some(std::array::from_fn(|i| frame[245 + i] as i8));
                    }
                    if n >= 288 {
                        info.counter = Some(u32::from_be_bytes([
                            frame[284], frame[285], frame[286], frame[287],
                        ]));
                    }
                    if n >= 417 {
                        info.simulation = Some(frame[314] != 0);
                        info.collision_detection = Some(frame[315] != 0);
                    }
                    if n >= 481 {
                        r.ft = Some((f32s(frame, 433), f32s(frame, 457)));
                    }
                    r.rich = Some(info);
                }
            }
        }
        Ok(r)
    }

    /// Encode as a frame of `size` bytes for a stream of `kind` (`size` ≥ the stream's
    /// legacy size). Optional blocks are written when the frame is long enough for them;
    /// bytes not modelled here are zero.
    pub fn encode(&self, kind: ReportKind, size: usize) -> Result<Vec<u8>> {
        let min = kind.min_len();
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
        put_f32s(&mut f, 7, &self.angles);
        put_f32s(&mut f, 35, &self.pose);
        put_f32s(&mut f, 59, &self.torques);
        match kind {
            ReportKind::Real => {
                if let (Some((ext, raw)), true) = (self.ft, size >= REPORT_REAL_LEN) {
                    put_f32s(&mut f, 87, &ext);
                    put_f32s(&mut f, 111, &raw);
                }
            }
            ReportKind::Normal | ReportKind::Rich => {
                f[87] = self.brake_bits;
                f[88] = self.enable_bits;
                f[89] = self.error;
                f[90] = self.warning;
                put_f32s(&mut f, 91, &self.tcp_offset);
                put_f32s(&mut f, 115, &self.tcp_load);
                f[131] = self.collision_sens;
                f[132] = self.teach_sens;
                if let (Some(g), true) = (self.gravity, size >= REPORT_NORMAL_LEN) {
                    put_f32s(&mut f, 133, &g);
                }
                if let (Some(info), true) = (
                    self.rich.as_ref().filter(|_| kind == ReportKind::Rich),
                    size >= REPORT_RICH_LEGACY_FULL_LEN,
                ) {
                    f[145] = info.arm_type;
                    f[146] = info.axis;
                    f[151..181].copy_from_slice(&info.version);
                    put_f32s(&mut f, 181, &info.limits);
                    f[229..245].copy_from_slice(&info.servo_codes);
                    if let (Some(t), true) = (info.temperatures, size >= 252) {
                        for (i, x) in t.iter().enumerate() {
                            f[245 + i] = *x as u8;
                        }
                    }
                    if let (Some(c), true) = (info.counter, size >= 288) {
                        f[284..288].copy_from_slice(&c.to_be_bytes());
                    }
                    if size >= 417 {
                        f[314] = info.simulation.unwrap_or(false) as u8;
                        f[315] = info.collision_detection.unwrap_or(false) as u8;
                    }
                    if let (Some((ext, raw)), true) = (self.ft, size >= 481) {
                        put_f32s(&mut f, 433, &ext);
                        put_f32s(&mut f, 457, &raw);
                    }
                }
            }
        }
        Ok(f)
    }
}

/// Splits a report stream into frames by the size header. The first frame fixes the size;
/// a later header that differs is an error (the SDK closes the stream then, so do we). On
/// the rich stream a size header of 233 means a 245-byte frame unless the next header
/// follows at byte 233 (see the module docs).
#[derive(Debug)]
pub struct ReportBuf {
    kind: ReportKind,
    /// `(size header, frame length)` locked on the first frame.
    size: Option<(u32, usize)>,
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
    /// The frame length locked on the first frame.
    pub fn size(&self) -> Option<u32> {
        self.size.map(|s| s.1 as u32)
    }
    /// Parse the next complete report, if any.
    pub fn next_report(&mut self) -> Result<Option<Report>> {
        if self.buf.len() < 4 {
            return Ok(None);
        }
        let header = u32::from_be_bytes([self.buf[0], self.buf[1], self.buf[2], self.buf[3]]);
        let len = match self.size {
            Some((locked, len)) if locked == header => len,
            Some((locked, _)) => {
                self.buf.clear();
                return Err(Error::XArmReportSize {
                    expected: locked,
                    got: header,
                });
            }
            None => {
                let min = self.kind.min_len() as u32;
                if !(min..=REPORT_MAX_LEN).contains(&header) {
                    self.buf.clear();
                    return Err(Error::XArmReportSize {
                        expected: min,
                        got: header,
                    });
                }
                if self.kind == ReportKind::Rich && header as usize == REPORT_RICH_LEGACY_LEN {
                    // 233 or really 245? Decide once the next header's place is in view.
                    let l = REPORT_RICH_LEGACY_LEN;
                    if self.buf.len() < l + 4 {
                        return Ok(None);
                    }
                    let next = u32::from_be_bytes([
                        self.buf[l],
                        self.buf[l + 1],
                        self.buf[l + 2],
                        self.buf[l + 3],
                    ]);
                    let len = if next as usize == l {
                        l
                    } else {
                        REPORT_RICH_LEGACY_FULL_LEN
                    };
                    self.size = Some((header, len));
                    len
                } else {
                    self.size = Some((header, header as usize));
                    header as usize
                }
            }
        };
        if self.buf.len() < len {
            return Ok(None);
        }
        let frame: Vec<u8> = self.buf.drain(..len).collect();
        match Report::parse(&frame, self.kind) {
            Ok(r) => Ok(Some(r)),
            Err(e) => {
                self.buf.clear();
                Err(e)
            }
        }
    }
}
