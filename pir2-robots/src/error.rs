//! The crate's error type: one enum, sectioned by where the fault was found.
//!
//! Every variant names what was wrong (which frame, register, CRC, joint...), so a log line
//! is enough to tell a wiring fault from a protocol mismatch from a safety stop.

use std::net::SocketAddr;

/// Errors of the robot drivers, the safety layer and the emulators.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    // ---- transport ----
    /// An OS-level I/O error on a named channel (socket, serial line, PTY).
    #[error("{channel}: I/O error: {source}")]
    Io {
        /// Which channel (e.g. "xArm command port", "XHand serial").
        channel: &'static str,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A TCP connection could not be opened.
    #[error("{channel}: cannot connect to {addr}: {source}")]
    Connect {
        /// Which channel.
        channel: &'static str,
        /// The address tried.
        addr: SocketAddr,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// No complete answer arrived in time.
    #[error("{channel}: timed out after {waited_ms} ms waiting for {what}")]
    Timeout {
        /// Which channel.
        channel: &'static str,
        /// What was awaited (e.g. "reply to register 42").
        what: String,
        /// How long the driver waited.
        waited_ms: u64,
    },
    /// The peer closed the connection.
    #[error("{channel}: peer closed the connection")]
    Disconnected {
        /// Which channel.
        channel: &'static str,
    },

    // ---- xArm protocol ----
    /// A command/reply frame is malformed (bad length field, too short...).
    #[error("xArm frame: {reason}")]
    XArmFrame {
        /// What is wrong with the frame.
        reason: String,
    },
    /// The reply carries another protocol identifier than the one we speak.
    #[error("xArm reply to register {register}: protocol id {got}, expected {expected}")]
    XArmProtocolId {
        /// The register of the request.
        register: u8,
        /// Our protocol id.
        expected: u16,
        /// The id in the reply.
        got: u16,
    },
    /// The reply answers another register than the one asked.
    #[error("xArm reply: register {got}, expected {expected}")]
    XArmRegister {
        /// The register asked.
        expected: u8,
        /// The register in the reply.
        got: u8,
    },
    /// The controller flagged the request as invalid (status bit 0x08).
    #[error("xArm register {register}: controller rejected the request (status 0x{status:02x})")]
    XArmInvalid {
        /// The register asked.
        register: u8,
        /// The full status byte.
        status: u8,
    },
    /// A reply's data is shorter than the register's layout.
    #[error("xArm register {register}: reply has {got} data bytes, expected at least {expected}")]
    XArmShortReply {
        /// The register asked.
        register: u8,
        /// Bytes needed.
        expected: usize,
        /// Bytes received.
        got: usize,
    },
    /// A report frame's size header is implausible or changed mid-stream.
    #[error("xArm report: size header {got}, expected {expected}")]
    XArmReportSize {
        /// The size locked on the first frame (or the minimum size).
        expected: u32,
        /// The size header received.
        got: u32,
    },
    /// The controller reports an error or warning code (from GET_ERROR or a report).
    #[error("xArm controller error code {error}, warning code {warning}")]
    XArmController {
        /// Controller error code (0 = none).
        error: u8,
        /// Controller warning code (0 = none).
        warning: u8,
    },

    // ---- XHand protocol ----
    /// An XHand frame is malformed (sync, length, truncated).
    #[error("XHand frame: {reason}")]
    XHandFrame {
        /// What is wrong with the frame.
        reason: String,
    },
    /// The CRC-16/XMODEM of an XHand frame does not match.
    #[error("XHand frame (command 0x{command:02x}): CRC 0x{got:04x}, computed 0x{computed:04x}")]
    XHandCrc {
        /// Command byte of the frame.
        command: u8,
        /// CRC carried by the frame.
        got: u16,
        /// CRC computed over the frame.
        computed: u16,
    },
    /// A reply of an unexpected command, source id or payload size.
    #[error("XHand reply: {reason}")]
    XHandReply {
        /// What did not match.
        reason: String,
    },

    // ---- cameras (V4L2) ----
    /// A V4L2 call on a camera failed (open, an ioctl, mmap, poll).
    #[error("camera {device}: {op} failed: {source}")]
    CameraIo {
        /// The device path.
        device: String,
        /// The call (e.g. "VIDIOC_S_FMT").
        op: &'static str,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The camera is not usable as a streaming capture device.
    #[error("camera {device}: {reason}")]
    CameraUnsupported {
        /// The device path.
        device: String,
        /// What is missing.
        reason: String,
    },
    /// No pixel format and size both the camera and pir2 support.
    #[error("camera {device}: cannot capture {asked}; offered: {offered}")]
    CameraFormat {
        /// The device path.
        device: String,
        /// What was asked.
        asked: String,
        /// What the device (or its driver) offered.
        offered: String,
    },
    /// The camera delivered no frame in time.
    #[error("camera {device}: no frame within {waited_ms} ms")]
    CameraTimeout {
        /// The device path.
        device: String,
        /// How long the capture waited.
        waited_ms: u64,
    },
    /// The camera disappeared (unplugged, driver unbound).
    #[error("camera {device}: device disappeared ({reason})")]
    CameraGone {
        /// The device path.
        device: String,
        /// What showed it.
        reason: String,
    },
    /// A frame was corrupt, truncated, of the wrong size or not newer than the last one.
    #[error("camera {device}: bad frame {sequence}: {reason}")]
    CameraFrame {
        /// The device path.
        device: String,
        /// The driver's frame counter.
        sequence: u32,
        /// What was wrong.
        reason: String,
    },

    // ---- robot / configuration ----
    /// A slice had the wrong length.
    #[error("{what}: expected {expected} values, got {got}")]
    Dim {
        /// What was checked.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Received length.
        got: usize,
    },
    /// A configuration value is out of range; the message names the field and the limit.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// The driver stopped (after `stop()` or a fault) and needs a reconnect.
    #[error("{device} is stopped: {reason}")]
    Stopped {
        /// Which device.
        device: &'static str,
        /// Why it stopped.
        reason: String,
    },

    // ---- safety ----
    /// The safety layer stopped the robot; it stays stopped until `reset()`.
    #[error("safety stop: {0}")]
    SafetyStop(String),

    // ---- emulators ----
    /// A pseudo-terminal could not be created or configured.
    #[error("pseudo-terminal: {0}")]
    Pty(String),
}

/// Result alias for this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// Wrap an OS error on a named channel.
    pub fn io(channel: &'static str, source: std::io::Error) -> Self {
        Error::Io { channel, source }
    }
    /// Check a slice length.
    pub fn check_dim(what: &'static str, expected: usize, got: usize) -> Result<()> {
        if expected == got {
            Ok(())
        } else {
            Err(Error::Dim {
                what,
                expected,
                got,
            })
        }
    }
}

impl From<Error> for pir2_runtime::Error {
    fn from(e: Error) -> Self {
        match e {
            Error::SafetyStop(msg) => pir2_runtime::Error::SafetyStop(msg),
            Error::Dim {
                what,
                expected,
                got,
            } => pir2_runtime::Error::shape(what, expected, got),
            other => pir2_runtime::Error::io("robot", other),
        }
    }
}
