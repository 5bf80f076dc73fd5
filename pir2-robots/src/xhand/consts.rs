//! Every XHand protocol choice in one place.
//!
//! The vendor SDK is closed; its C++ headers and several community RS-485 drivers are public
//! and do not all agree. Each constant below says what was chosen and, where sources differ,
//! what the alternative is, so a change against a real hand is a one-line edit here.
//!
//! Sources: the public XHand control headers (`FingerCommand`, `FingerState`, `HandCommand`,
//! `HandState`, fingertip sensor structs, all packed little-endian) as reproduced in community
//! XHand driver repositories, and the community RS-485 drivers' framing
//! (`55 AA | src | dst | cmd | len LE | payload | CRC-16/XMODEM LE`). See
//! `docs/xhand-protocol.md`.

/// First sync byte.
pub const SYNC0: u8 = 0x55;
/// Second sync byte.
pub const SYNC1: u8 = 0xAA;
/// Host (PC) id used as source of requests and destination of replies.
pub const HOST_ID: u8 = 0xFE;
/// Default hand id. Choice: 0 (assumed; configurable per hand in `XHandConfig`).
pub const DEFAULT_HAND_ID: u8 = 0x00;
/// Broadcast id. Choice: 0xFF. Sources disagree on the broadcast id; we never broadcast
/// commands, so this only matters for the emulator, which answers it as well as its own id.
pub const BROADCAST_ID: u8 = 0xFF;

/// Command: 12 finger commands (288 bytes), answered by the full hand state (2208 bytes).
pub const CMD_SET_COMMAND: u8 = 0x02;
/// Command: read the hand state without commanding. Choice: 0x01 with an empty payload,
/// answered like [`CMD_SET_COMMAND`]. Not confirmed by every source (some only obtain the
/// state as the answer to 0x02); the driver only uses it before the first command.
pub const CMD_READ_STATE: u8 = 0x01;
/// Command: firmware version, answered by an ASCII string.
pub const CMD_VERSION: u8 = 0x13;

/// Header bytes before the payload: sync (2), src, dst, cmd, len (2).
pub const HEADER_LEN: usize = 7;
/// CRC bytes after the payload.
pub const CRC_LEN: usize = 2;
/// Largest payload accepted (the state is the biggest at 2208).
pub const MAX_PAYLOAD: usize = 4096;

/// Number of finger joints.
pub const JOINTS: usize = 12;
/// Number of fingertip sensors.
pub const TIPS: usize = 5;
/// One packed `FingerCommand`.
pub const FINGER_COMMAND_LEN: usize = 24;
/// The command payload: 12 finger commands.
pub const COMMAND_PAYLOAD_LEN: usize = JOINTS * FINGER_COMMAND_LEN;
/// One packed `FingerState`.
pub const FINGER_STATE_LEN: usize = 24;
/// One fingertip sensor block: computed force (3), 120 × 3 raw, 20 temperatures, summary.
pub const TIP_SENSOR_LEN: usize = 3 + 120 * 3 + 20 + 1;
/// The state payload: 12 finger states + 5 fingertip sensors = 288 + 1920.
pub const STATE_PAYLOAD_LEN: usize = JOINTS * FINGER_STATE_LEN + TIPS * TIP_SENSOR_LEN;

/// Finger control mode: position.
pub const MODE_POSITION: u16 = 3;
/// Finger control mode: powerless (used by `stop()` only if configured to release).
pub const MODE_POWERLESS: u16 = 0;

/// How joint positions travel on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PositionEncoding {
    /// IEEE-754 f32, radians, little-endian (the header structs declare `float position`).
    F32Radians,
    /// i32 milliradians, little-endian: an integer alternative kept so a hand that encodes
    /// positions as integers is a one-line change (not confirmed by a source we could read).
    I32MilliRadians,
}

/// Choice: the header structs' `float` radians. Sources disagree; switch here.
pub const POSITION_ENCODING: PositionEncoding = PositionEncoding::F32Radians;

/// Serial baud rate of the RS-485 adapter (8N1).
pub const BAUD: u32 = 3_000_000;

/// Paper's gains for position mode (kp 100, torque limit 300); ki, kd 0.
pub const DEFAULT_KP: i16 = 100;
/// Integral gain.
pub const DEFAULT_KI: i16 = 0;
/// Derivative gain.
pub const DEFAULT_KD: i16 = 0;
/// Torque limit (driver units).
pub const DEFAULT_TORQUE_LIMIT: u16 = 300;

/// Scale from the fingertip "computed force" bytes (i8 x, i8 y, u8 z) to the force values the
/// driver reports. Choice: 0.1 N per count (assumed, not confirmed by a source). The emulator
/// uses the same constant, so changing it here keeps tests consistent.
pub const TIP_FORCE_SCALE: f32 = 0.1;
