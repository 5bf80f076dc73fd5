//! Blocking request/reply client for the xArm command port, and a report-stream reader.

use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::{Clock, Nanos};

use super::proto::{
    self, reg, status, FirmwareVersion, FrameBuf, Reply, Report, ReportBuf, ReportKind,
};
use crate::error::{Error, Result};

const CH_CMD: &str = "xArm command port";
const CH_REPORT: &str = "xArm report port";
/// Socket read timeout used to poll the deadline (the deadline itself is on the clock).
const POLL: Duration = Duration::from_millis(5);

/// Counters of a client's life, for reports and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ClientStats {
    /// Requests sent.
    pub requests: u64,
    /// Replies whose transaction id did not match the request (skipped, as the SDK does).
    pub stale_replies: u64,
    /// Asynchronous motion-feedback frames (register 0xFF) skipped.
    pub feedback_frames: u64,
}

/// A connection to the command port (502).
///
/// Every request waits for the reply with the same transaction id; replies with another id
/// are skipped (they answer a request that already timed out), and so are motion-feedback
/// frames (register 0xFF). Any framing error, wrong protocol id or wrong register closes the
/// stream: the byte stream cannot be trusted after it.
///
/// Requests use protocol id 2 until [`XArmClient::identify`] reads the firmware version;
/// from then on they use what that firmware expects (id 3 from 1.8.6 on) and
/// [`XArmClient::set_mode`] sends the parameter form of that firmware.
#[derive(Debug)]
pub struct XArmClient {
    stream: Option<TcpStream>,
    rx: FrameBuf,
    tid: u16,
    proto: u16,
    timeout: Nanos,
    clock: Arc<dyn Clock>,
    stats: ClientStats,
    scratch: Vec<u8>,
    firmware: Option<FirmwareVersion>,
}

impl XArmClient {
    /// Connect to `addr` (normally port 502). `timeout` bounds connect and every request.
    pub fn connect(addr: SocketAddr, timeout: Duration, clock: Arc<dyn Clock>) -> Result<Self> {
        let stream =
            TcpStream::connect_timeout(&addr, timeout).map_err(|source| Error::Connect {
                channel: CH_CMD,
                addr,
                source,
            })?;
        stream.set_nodelay(true).map_err(|e| Error::io(CH_CMD, e))?;
        stream
            .set_read_timeout(Some(POLL))
            .map_err(|e| Error::io(CH_CMD, e))?;
        stream
            .set_write_timeout(Some(timeout))
            .map_err(|e| Error::io(CH_CMD, e))?;
        Ok(Self {
            stream: Some(stream),
            rx: FrameBuf::new(),
            tid: 1,
            proto: proto::PROTO_PRIVATE,
            timeout: timeout.as_nanos() as Nanos,
            clock,
            stats: ClientStats::default(),
            scratch: Vec::with_capacity(64),
            firmware: None,
        })
    }

    /// Read and parse the firmware version, then switch to the protocol id that firmware
    /// expects (see [`FirmwareVersion::protocol_id`]).
    pub fn identify(&mut self) -> Result<FirmwareVersion> {
        let text = self.version()?;
        let v = FirmwareVersion::parse(&text)?;
        self.proto = v.protocol_id();
        self.firmware = Some(v.clone());
        Ok(v)
    }

    /// The firmware version read by [`XArmClient::identify`].
    pub fn firmware(&self) -> Option<&FirmwareVersion> {
        self.firmware.as_ref()
    }

    /// The protocol id requests are sent with.
    pub fn protocol_id(&self) -> u16 {
        self.proto
    }

    /// Counters so far.
    pub fn stats(&self) -> ClientStats {
        self.stats
    }

    /// Whether the stream is still open (it is closed after an I/O or framing error).
    pub fn is_open(&self) -> bool {
        self.stream.is_some()
    }

    /// Close the stream.
    pub fn close(&mut self) {
        if let Some(s) = self.stream.take() {
            let _ = s.shutdown(std::net::Shutdown::Both);
        }
    }

    fn fail<T>(&mut self, e: Error) -> Result<T> {
        self.close();
        Err(e)
    }

    /// Send one request and wait for its reply. Status bit `0x08` (invalid) is an error; the
    /// warning/error bits are returned in [`Reply::status`] for the caller to act on.
    pub fn request(&mut self, register: u8, params: &[u8]) -> Result<Reply> {
        let tid = self.tid;
        self.tid = proto::next_tid(self.tid);
        self.scratch.clear();
        proto::encode_command(tid, self.proto, register, params, &mut self.scratch)?;
        let Some(stream) = self.stream.as_mut() else {
            return Err(Error::Disconnected { channel: CH_CMD });
        };
        self.stats.requests += 1;
        if let Err(e) = stream.write_all(&self.scratch) {
            return self.fail(Error::io(CH_CMD, e));
        }
        let start = self.clock.now();
        let mut buf = [0u8; 512];
        loop {
            loop {
                let frame = match self.rx.next_frame() {
                    Ok(Some(f)) => f,
                    Ok(None) => break,
                    Err(e) => return self.fail(e),
                };
                let reply = match Reply::decode(&frame) {
                    Ok(r) => r,
                    Err(e) => return self.fail(e),
                };
                if reply.register == proto::FEEDBACK_REGISTER {
                    self.stats.feedback_frames += 1;
                    continue;
                }
                if reply.tid != tid {
                    self.stats.stale_replies += 1;
                    continue;
                }
                if reply.proto != self.proto {
                    return self.fail(Error::XArmProtocolId {
                        register,
                        expected: self.proto,
                        got: reply.proto,
                    });
                }
                if reply.register != register {
                    return self.fail(Error::XArmRegister {
                        expected: register,
                        got: reply.register,
                    });
                }
                if reply.status & status::INVALID != 0 {
                    return Err(Error::XArmInvalid {
                        register,
                        status: reply.status,
                    });
                }
                return Ok(reply);
            }
            let waited = self.clock.now().saturating_sub(start);
            if waited >= self.timeout {
                // The late reply would desynchronise nothing (tids differ), but a peer that
                // stalls this long is not fit to servo a robot: close.
                return self.fail(Error::Timeout {
                    channel: CH_CMD,
                    what: format!("reply to register {register} (tid {tid})"),
                    waited_ms: waited / 1_000_000,
                });
            }
            let Some(stream) = self.stream.as_mut() else {
                return Err(Error::Disconnected { channel: CH_CMD });
            };
            match stream.read(&mut buf) {
                Ok(0) => return self.fail(Error::Disconnected { channel: CH_CMD }),
                Ok(n) => self.rx.push(&buf[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                    ) => {}
                Err(e) => return self.fail(Error::io(CH_CMD, e)),
            }
        }
    }

    fn request_data(&mut self, register: u8, params: &[u8], need: usize) -> Result<Reply> {
        let r = self.request(register, params)?;
        if r.data.len() < need {
            return Err(Error::XArmShortReply {
                register,
                expected: need,
                got: r.data.len(),
            });
        }
        Ok(r)
    }

    /// Firmware version string (register 1).
    pub fn version(&mut self) -> Result<String> {
        let r = self.request_data(reg::GET_VERSION, &[], 1)?;
        let end = r.data.iter().position(|&b| b == 0).unwrap_or(r.data.len());
        Ok(String::from_utf8_lossy(&r.data[..end]).trim().to_string())
    }
    /// Enable or disable all motors (register 11, axis 8).
    pub fn motion_enable(&mut self, on: bool) -> Result<u8> {
        Ok(self
            .request(reg::MOTION_EN, &[proto::AXIS_ALL, on as u8])?
            .status)
    }
    /// Set the motion state (register 12).
    pub fn set_state(&mut self, state: u8) -> Result<u8> {
        Ok(self.request(reg::SET_STATE, &[state])?.status)
    }
    /// Read the motion state (register 13).
    pub fn state(&mut self) -> Result<u8> {
        Ok(self.request_data(reg::GET_STATE, &[], 1)?.data[0])
    }
    /// Read `(error, warning)` codes (register 15).
    pub fn error_codes(&mut self) -> Result<(u8, u8)> {
        let r = self.request_data(reg::GET_ERROR, &[], 2)?;
        Ok((r.data[0], r.data[1]))
    }
    /// Clear the controller error (register 16).
    pub fn clean_error(&mut self) -> Result<u8> {
        Ok(self.request(reg::CLEAN_ERR, &[])?.status)
    }
    /// Clear the controller warning (register 17).
    pub fn clean_warning(&mut self) -> Result<u8> {
        Ok(self.request(reg::CLEAN_WAR, &[])?.status)
    }
    /// Set the control mode (register 19): `[mode, 0]` on firmware ≥ 1.10.0, `[mode]` on
    /// older firmware or before [`XArmClient::identify`].
    pub fn set_mode(&mut self, mode: u8) -> Result<u8> {
        let params = match &self.firmware {
            Some(v) => v.set_mode_params(mode),
            None => vec![mode],
        };
        Ok(self.request(reg::SET_MODE, &params)?.status)
    }
    /// Servo-j to 6 joint targets in rad (register 29). Returns the reply status.
    pub fn servo_j(&mut self, joints: &[f32; 6]) -> Result<u8> {
        Ok(self
            .request(reg::MOVE_SERVOJ, &proto::servoj_params(joints))?
            .status)
    }
    /// Joint positions, rad (register 42).
    pub fn joint_positions(&mut self) -> Result<[f32; 7]> {
        let r = self.request_data(reg::GET_JOINT_POS, &[], 28)?;
        let mut q = [0f32; 7];
        proto::read_fp32s_le(&r.data, &mut q)?;
        Ok(q)
    }
    /// Measured joint positions (rad) and efforts in one request: `GET_JOINT_POS [3]`
    /// (firmware ≥ 1.9.110; see [`FirmwareVersion::has_joint_states`]).
    pub fn joint_states(&mut self) -> Result<([f32; 7], [f32; 7])> {
        let r = self.request_data(reg::GET_JOINT_POS, &[3], 84)?;
        let mut q = [0f32; 7];
        let mut e = [0f32; 7];
        proto::read_fp32s_le(&r.data, &mut q)?;
        proto::read_fp32s_le(&r.data[56..], &mut e)?;
        Ok((q, e))
    }
    /// Joint torques (register 55).
    pub fn joint_torques(&mut self) -> Result<[f32; 7]> {
        let r = self.request_data(reg::GET_JOINT_TAU, &[], 28)?;
        let mut t = [0f32; 7];
        proto::read_fp32s_le(&r.data, &mut t)?;
        Ok(t)
    }
}

/// A connection to a report port that yields parsed reports.
#[derive(Debug)]
pub struct ReportReader {
    stream: TcpStream,
    buf: ReportBuf,
    rx: Vec<u8>,
}

impl ReportReader {
    /// Connect to a report port; `kind` must match the port (30003 real, 30001 normal).
    pub fn connect(addr: SocketAddr, kind: ReportKind, timeout: Duration) -> Result<Self> {
        let stream =
            TcpStream::connect_timeout(&addr, timeout).map_err(|source| Error::Connect {
                channel: CH_REPORT,
                addr,
                source,
            })?;
        stream
            .set_read_timeout(Some(POLL))
            .map_err(|e| Error::io(CH_REPORT, e))?;
        Ok(Self {
            stream,
            buf: ReportBuf::new(kind),
            rx: vec![0; 4096],
        })
    }

    /// Read what arrived; return the newest complete report if any (older ones are dropped:
    /// only the newest state matters). `Ok(None)` when nothing complete arrived within the
    /// poll interval.
    pub fn poll(&mut self) -> Result<Option<Report>> {
        match self.stream.read(&mut self.rx) {
            Ok(0) => return Err(Error::Disconnected { channel: CH_REPORT }),
            Ok(n) => self.buf.push(&self.rx[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                ) => {}
            Err(e) => return Err(Error::io(CH_REPORT, e)),
        }
        let mut newest = None;
        while let Some(r) = self.buf.next_report()? {
            newest = Some(r);
        }
        Ok(newest)
    }

    /// Wait up to `timeout` on `clock` for one report.
    pub fn next(&mut self, clock: &dyn Clock, timeout: Duration) -> Result<Report> {
        let start = clock.now();
        loop {
            if let Some(r) = self.poll()? {
                return Ok(r);
            }
            let waited = clock.now().saturating_sub(start);
            if waited >= timeout.as_nanos() as Nanos {
                return Err(Error::Timeout {
                    channel: CH_REPORT,
                    what: "a report".into(),
                    waited_ms: waited / 1_000_000,
                });
            }
        }
    }
}
