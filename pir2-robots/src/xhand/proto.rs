//! XHand RS-485 wire format.
//!
//! # Frame
//!
//! ```text
//! offset  size  field
//! 0       2     sync 55 AA
//! 2       1     source id   (host 0xFE in requests, hand id in replies)
//! 3       1     destination (hand id in requests, 0xFE in replies)
//! 4       1     command     (0x02 set command, 0x01 read state, 0x13 version)
//! 5       2     payload length n, u16 little-endian
//! 7       n     payload
//! 7+n     2     CRC-16/XMODEM (poly 0x1021, init 0, no reflection), little-endian,
//!               computed over bytes 0..7+n (sync included)
//! ```
//!
//! # Payloads (packed, little-endian)
//!
//! `FingerCommand` (24 B): `id u16 | kp i16 | ki i16 | kd i16 | position (see
//! [`consts::POSITION_ENCODING`]) 4 B | tor_max u16 | mode u16 | reserved 4 × u16`.
//! The command payload is 12 of them (288 B).
//!
//! `FingerState` (24 B): `id u16 | sensor_id u16 | position 4 B | torque f32 | raw_position i32 |
//! temperature u16 | error u16 × 3`.
//!
//! Fingertip sensor (384 B): `computed force i8 x, i8 y, u8 z | 120 × (i8, i8, u8) raw |
//! 20 × u8 temperature | u8 summary`.
//!
//! The state payload is 12 finger states then 5 fingertip sensors (288 + 1920 = 2208 B).

use super::consts::{self, PositionEncoding};
use crate::error::{Error, Result};

/// CRC-16/XMODEM: poly 0x1021, init 0x0000, no reflection, no final xor.
pub fn crc16_xmodem(data: &[u8]) -> u16 {
    let mut crc: u16 = 0;
    for &b in data {
        crc ^= (b as u16) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x1021
            } else {
                crc << 1
            };
        }
    }
    crc
}

/// Append one frame with the given header and payload to `out` (no intermediate allocation).
pub fn encode_frame(src: u8, dst: u8, cmd: u8, payload: &[u8], out: &mut Vec<u8>) -> Result<()> {
    if payload.len() > consts::MAX_PAYLOAD {
        return Err(Error::XHandFrame {
            reason: format!(
                "payload of {} bytes exceeds {}",
                payload.len(),
                consts::MAX_PAYLOAD
            ),
        });
    }
    let start = out.len();
    out.extend_from_slice(&[consts::SYNC0, consts::SYNC1, src, dst, cmd]);
    out.extend_from_slice(&(payload.len() as u16).to_le_bytes());
    out.extend_from_slice(payload);
    let crc = crc16_xmodem(&out[start..]);
    out.extend_from_slice(&crc.to_le_bytes());
    Ok(())
}

/// One XHand frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    /// Source id.
    pub src: u8,
    /// Destination id.
    pub dst: u8,
    /// Command byte.
    pub cmd: u8,
    /// Payload.
    pub payload: Vec<u8>,
}

impl Frame {
    /// Append the encoded frame to `out`.
    pub fn encode_into(&self, out: &mut Vec<u8>) -> Result<()> {
        encode_frame(self.src, self.dst, self.cmd, &self.payload, out)
    }
    /// The encoded frame.
    pub fn encode(&self) -> Result<Vec<u8>> {
        let mut v = Vec::with_capacity(consts::HEADER_LEN + self.payload.len() + consts::CRC_LEN);
        self.encode_into(&mut v)?;
        Ok(v)
    }
    /// Decode exactly one complete frame.
    pub fn decode(bytes: &[u8]) -> Result<Self> {
        if bytes.len() < consts::HEADER_LEN + consts::CRC_LEN {
            return Err(Error::XHandFrame {
                reason: format!("{} bytes is shorter than an empty frame (9)", bytes.len()),
            });
        }
        if bytes[0] != consts::SYNC0 || bytes[1] != consts::SYNC1 {
            return Err(Error::XHandFrame {
                reason: format!("sync {:02x} {:02x}, expected 55 aa", bytes[0], bytes[1]),
            });
        }
        let n = u16::from_le_bytes([bytes[5], bytes[6]]) as usize;
        if n > consts::MAX_PAYLOAD {
            return Err(Error::XHandFrame {
                reason: format!("length field {n} exceeds {}", consts::MAX_PAYLOAD),
            });
        }
        let total = consts::HEADER_LEN + n + consts::CRC_LEN;
        if bytes.len() != total {
            return Err(Error::XHandFrame {
                reason: format!(
                    "length field {n} implies {total} bytes, got {}",
                    bytes.len()
                ),
            });
        }
        let body = &bytes[..consts::HEADER_LEN + n];
        let got = u16::from_le_bytes([bytes[total - 2], bytes[total - 1]]);
        let computed = crc16_xmodem(body);
        if got != computed {
            return Err(Error::XHandCrc {
                command: bytes[4],
                got,
                computed,
            });
        }
        Ok(Frame {
            src: bytes[2],
            dst: bytes[3],
            cmd: bytes[4],
            payload: bytes[consts::HEADER_LEN..][..n].to_vec(),
        })
    }
}

/// Splits a serial byte stream into frames: skips bytes until `55 AA`, waits for the whole
/// frame, checks the CRC. Garbage is dropped and counted, never fatal.
#[derive(Debug, Default)]
pub struct FrameParser {
    buf: Vec<u8>,
    dropped: u64,
}

impl FrameParser {
    /// An empty parser.
    pub fn new() -> Self {
        Self::default()
    }
    /// Append received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }
    /// Bytes skipped while hunting for a sync pattern, so far.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }
    /// Forget everything buffered.
    pub fn clear(&mut self) {
        self.buf.clear();
    }
    /// The next frame: `None` if none is complete yet; `Some(Err)` for a frame with a bad CRC
    /// or an impossible length (its first byte is dropped and the hunt resumes).
    pub fn next_frame(&mut self) -> Option<Result<Frame>> {
        let start = self
            .buf
            .windows(2)
            .position(|w| w == [consts::SYNC0, consts::SYNC1]);
        match start {
            None => {
                // Keep a trailing 0x55: it may be the first half of a sync pair.
                let keep = usize::from(self.buf.last() == Some(&consts::SYNC0));
                let drop = self.buf.len() - keep;
                self.dropped += drop as u64;
                self.buf.drain(..drop);
                return None;
            }
            Some(s) => {
                self.dropped += s as u64;
                self.buf.drain(..s);
            }
        }
        if self.buf.len() < consts::HEADER_LEN {
            return None;
        }
        let n = u16::from_le_bytes([self.buf[5], self.buf[6]]) as usize;
        if n > consts::MAX_PAYLOAD {
            self.buf.drain(..1);
            self.dropped += 1;
            return Some(Err(Error::XHandFrame {
                reason: format!("length field {n} exceeds {}", consts::MAX_PAYLOAD),
            }));
        }
        let total = consts::HEADER_LEN + n + consts::CRC_LEN;
        if self.buf.len() < total {
            return None;
        }
        let res = Frame::decode(&self.buf[..total]);
        if res.is_ok() {
            self.buf.drain(..total);
        } else {
            // A false sync inside garbage, or a corrupted frame: resync one byte later.
            self.buf.drain(..1);
            self.dropped += 1;
        }
        Some(res)
    }
}

fn put_position(out: &mut [u8], q: f32) {
    let b = match consts::POSITION_ENCODING {
        PositionEncoding::F32Radians => q.to_le_bytes(),
        PositionEncoding::I32MilliRadians => ((q as f64 * 1000.0).round() as i32).to_le_bytes(),
    };
    out[..4].copy_from_slice(&b);
}

fn get_position(b: &[u8]) -> f32 {
    let raw = [b[0], b[1], b[2], b[3]];
    match consts::POSITION_ENCODING {
        PositionEncoding::F32Radians => f32::from_le_bytes(raw),
        PositionEncoding::I32MilliRadians => i32::from_le_bytes(raw) as f32 / 1000.0,
    }
}

fn u16_at(b: &[u8], i: usize) -> u16 {
    u16::from_le_bytes([b[i], b[i + 1]])
}
fn i16_at(b: &[u8], i: usize) -> i16 {
    i16::from_le_bytes([b[i], b[i + 1]])
}
fn f32_at(b: &[u8], i: usize) -> f32 {
    f32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
}

/// One finger joint's command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FingerCommand {
    /// Joint id (0..12).
    pub id: u16,
    /// Proportional gain.
    pub kp: i16,
    /// Integral gain.
    pub ki: i16,
    /// Derivative gain.
    pub kd: i16,
    /// Target position, rad.
    pub position: f32,
    /// Torque limit.
    pub tor_max: u16,
    /// Control mode (3 = position).
    pub mode: u16,
}

impl FingerCommand {
    /// Write the 24-byte packed form.
    pub fn write(&self, out: &mut [u8]) {
        out[..consts::FINGER_COMMAND_LEN].fill(0);
        out[0..2].copy_from_slice(&self.id.to_le_bytes());
        out[2..4].copy_from_slice(&self.kp.to_le_bytes());
        out[4..6].copy_from_slice(&self.ki.to_le_bytes());
        out[6..8].copy_from_slice(&self.kd.to_le_bytes());
        put_position(&mut out[8..12], self.position);
        out[12..14].copy_from_slice(&self.tor_max.to_le_bytes());
        out[14..16].copy_from_slice(&self.mode.to_le_bytes());
    }
    /// Read the 24-byte packed form.
    pub fn read(b: &[u8]) -> Self {
        FingerCommand {
            id: u16_at(b, 0),
            kp: i16_at(b, 2),
            ki: i16_at(b, 4),
            kd: i16_at(b, 6),
            position: get_position(&b[8..12]),
            tor_max: u16_at(b, 12),
            mode: u16_at(b, 14),
        }
    }
}

/// Encode 12 finger commands as the 288-byte command payload.
pub fn encode_hand_command(fingers: &[FingerCommand; consts::JOINTS]) -> Vec<u8> {
    let mut p = Vec::with_capacity(consts::COMMAND_PAYLOAD_LEN);
    encode_hand_command_into(fingers, &mut p);
    p
}

/// Write the 288-byte command payload into `p` (cleared first; reuses its allocation).
pub fn encode_hand_command_into(fingers: &[FingerCommand; consts::JOINTS], p: &mut Vec<u8>) {
    p.clear();
    p.resize(consts::COMMAND_PAYLOAD_LEN, 0);
    for (f, chunk) in fingers
        .iter()
        .zip(p.chunks_exact_mut(consts::FINGER_COMMAND_LEN))
    {
        f.write(chunk);
    }
}

/// Decode the 288-byte command payload.
pub fn decode_hand_command(p: &[u8]) -> Result<[FingerCommand; consts::JOINTS]> {
    if p.len() != consts::COMMAND_PAYLOAD_LEN {
        return Err(Error::XHandReply {
            reason: format!(
                "command payload of {} bytes, expected {}",
                p.len(),
                consts::COMMAND_PAYLOAD_LEN
            ),
        });
    }
    let mut out = [FingerCommand {
        id: 0,
        kp: 0,
        ki: 0,
        kd: 0,
        position: 0.0,
        tor_max: 0,
        mode: 0,
    }; consts::JOINTS];
    for (o, chunk) in out
        .iter_mut()
        .zip(p.chunks_exact(consts::FINGER_COMMAND_LEN))
    {
        *o = FingerCommand::read(chunk);
    }
    Ok(out)
}

/// One finger joint's state.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FingerState {
    /// Joint id.
    pub id: u16,
    /// Sensor id.
    pub sensor_id: u16,
    /// Position, rad.
    pub position: f32,
    /// Torque (driver units).
    pub torque: f32,
    /// Raw encoder position.
    pub raw_position: i32,
    /// Temperature.
    pub temperature: u16,
    /// Three error words (0 = none).
    pub errors: [u16; 3],
}

/// The hand state this crate uses: 12 joints and 5 fingertip computed forces.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct HandState {
    /// Per-joint states.
    pub fingers: [FingerState; consts::JOINTS],
    /// Per-tip computed force counts `(x i8, y i8, z u8)`, widened to i16.
    pub tip_force: [[i16; 3]; consts::TIPS],
}

impl HandState {
    /// Encode as the 2208-byte state payload (raw sensor arrays, temperatures and summary
    /// bytes are zero).
    pub fn encode(&self) -> Vec<u8> {
        let mut p = vec![0u8; consts::STATE_PAYLOAD_LEN];
        for (f, b) in self
            .fingers
            .iter()
            .zip(p.chunks_exact_mut(consts::FINGER_STATE_LEN))
        {
            b[0..2].copy_from_slice(&f.id.to_le_bytes());
            b[2..4].copy_from_slice(&f.sensor_id.to_le_bytes());
            put_position(&mut b[4..8], f.position);
            b[8..12].copy_from_slice(&f.torque.to_le_bytes());
            b[12..16].copy_from_slice(&f.raw_position.to_le_bytes());
            b[16..18].copy_from_slice(&f.temperature.to_le_bytes());
            for k in 0..3 {
                b[18 + 2 * k..20 + 2 * k].copy_from_slice(&f.errors[k].to_le_bytes());
            }
        }
        let tips = &mut p[consts::JOINTS * consts::FINGER_STATE_LEN..];
        for (t, b) in self
            .tip_force
            .iter()
            .zip(tips.chunks_exact_mut(consts::TIP_SENSOR_LEN))
        {
            b[0] = t[0].clamp(i8::MIN as i16, i8::MAX as i16) as i8 as u8;
            b[1] = t[1].clamp(i8::MIN as i16, i8::MAX as i16) as i8 as u8;
            b[2] = t[2].clamp(0, u8::MAX as i16) as u8;
        }
        p
    }

    /// Decode the 2208-byte state payload.
    pub fn decode(p: &[u8]) -> Result<Self> {
        if p.len() != consts::STATE_PAYLOAD_LEN {
            return Err(Error::XHandReply {
                reason: format!(
                    "state payload of {} bytes, expected {}",
                    p.len(),
                    consts::STATE_PAYLOAD_LEN
                ),
            });
        }
        let mut s = HandState::default();
        for (f, b) in s
            .fingers
            .iter_mut()
            .zip(p.chunks_exact(consts::FINGER_STATE_LEN))
        {
            *f = FingerState {
                id: u16_at(b, 0),
                sensor_id: u16_at(b, 2),
                position: get_position(&b[4..8]),
                torque: f32_at(b, 8),
                raw_position: i32::from_le_bytes([b[12], b[13], b[14], b[15]]),
                temperature: u16_at(b, 16),
                errors: [u16_at(b, 18), u16_at(b, 20), u16_at(b, 22)],
            };
        }
        let tips = &p[consts::JOINTS * consts::FINGER_STATE_LEN..];
        for (t, b) in s
            .tip_force
            .iter_mut()
            .zip(tips.chunks_exact(consts::TIP_SENSOR_LEN))
        {
            *t = [b[0] as i8 as i16, b[1] as i8 as i16, b[2] as i16];
        }
        Ok(s)
    }

    /// Write the hand's 39-value state: 12 positions, 12 torques, 15 tip forces (scaled by
    /// [`consts::TIP_FORCE_SCALE`]).
    pub fn write_vector(&self, out: &mut [f32]) {
        for (i, f) in self.fingers.iter().enumerate() {
            out[i] = f.position;
            out[consts::JOINTS + i] = f.torque;
        }
        for (k, t) in self.tip_force.iter().enumerate() {
            for a in 0..3 {
                out[2 * consts::JOINTS + 3 * k + a] = t[a] as f32 * consts::TIP_FORCE_SCALE;
            }
        }
    }
}
