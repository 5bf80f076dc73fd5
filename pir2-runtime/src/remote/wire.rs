//! The wire format of the remote slow channel and the remote action head (version 1).
//!
//! Every message is one Zenoh payload: a fixed 40-byte header, then `n_tensors` tensors.
//! All integers and floats are little-endian.
//!
//! ```text
//! offset size  field
//!  0     4     magic       b"PIR2"
//!  4     2     version     u16 (= WIRE_VERSION); any other value is Error::Version
//!  6     1     kind        u8  (Kind below)
//!  7     1     n_tensors   u8
//!  8     8     sender      u64 random id of the sending process instance (changes on restart)
//! 16     8     seq         u64 sequence number (a reply echoes its request's)
//! 24     8     t_a         u64 ns, kind-specific timestamp (see Kind)
//! 32     8     t_b         u64 ns, kind-specific timestamp (see Kind)
//! 40     ...   tensors, back to back:
//!              dtype u8 (1 = f32, 2 = u32, 3 = u8), rank u8 (0..=4), reserved u16 (= 0),
//!              dims rank × u32, then prod(dims) elements (4, 4 or 1 bytes each)
//! ```
//!
//! The payload ends exactly after the last tensor (trailing bytes are malformed).
//!
//! | kind | name          | t_a                     | t_b                      | tensors |
//! |------|---------------|-------------------------|--------------------------|---------|
//! | 1    | Features      | capture time (sender clock) | publish time (sender clock) | f32 `[T, D]` |
//! | 2    | PolicyRequest | send time (robot clock) | 0                        | f32 x `[B,H,A]`, f32 τ `[B,H]`, f32 obs `[B,n_obs,F]`, u32 d_vis `[B]`, optional f32 slow `[B,S]` or `[B,T,D]` |
//! | 3    | PolicyReply   | echo of request t_a     | model time, ns           | f32 v `[B,H,A]` |
//! | 4    | Ping          | send time (robot clock) | 0                        | none |
//! | 5    | Pong          | echo of ping t_a        | receive time (server clock) | none |
//! | 6    | Error         | 0                       | 0                        | u8 `[n]` UTF-8 message |
//!
//! Decoding checks every length before allocating, so garbage of any length returns a
//! [`WireError`] and never panics or allocates more than the input's size.

use crate::model::{ModelInput, SlowInput};

/// Magic bytes at the start of every message.
pub const MAGIC: [u8; 4] = *b"PIR2";
/// The version this build speaks.
pub const WIRE_VERSION: u16 = 1;
/// Size of the fixed header.
pub const HEADER_LEN: usize = 40;
/// Largest tensor rank.
pub const MAX_RANK: usize = 4;

/// Message kinds (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Kind {
    /// Slow features with their capture time.
    Features = 1,
    /// One NFE request.
    PolicyRequest = 2,
    /// The velocity for a request.
    PolicyReply = 3,
    /// Liveness / clock-offset request.
    Ping = 4,
    /// Answer to a ping, stamped with the server clock.
    Pong = 5,
    /// The server could not answer; carries a message.
    Error = 6,
}

impl Kind {
    fn from_u8(b: u8) -> Option<Self> {
        Some(match b {
            1 => Kind::Features,
            2 => Kind::PolicyRequest,
            3 => Kind::PolicyReply,
            4 => Kind::Ping,
            5 => Kind::Pong,
            6 => Kind::Error,
            _ => return None,
        })
    }
}

/// A message that could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// Fewer bytes than the header or a declared tensor needs.
    #[error("truncated message: {what} needs {need} bytes, {got} left")]
    Truncated {
        /// What was being read.
        what: &'static str,
        /// Bytes needed.
        need: usize,
        /// Bytes left.
        got: usize,
    },
    /// The first four bytes are not `PIR2`.
    #[error("not a pir2 message (magic {0:02x?})")]
    BadMagic([u8; 4]),
    /// The peer speaks another version of this format.
    #[error("wire version mismatch: peer speaks v{got}, this build speaks v{expected}")]
    Version {
        /// The peer's version.
        got: u16,
        /// Ours.
        expected: u16,
    },
    /// Unknown message kind.
    #[error("unknown message kind {0}")]
    UnknownKind(u8),
    /// A message of the wrong kind for this exchange.
    #[error("expected a {expected:?} message, got {got:?}")]
    UnexpectedKind {
        /// The kind expected.
        expected: Kind,
        /// The kind received.
        got: Kind,
    },
    /// Structurally invalid content (bad dtype, rank, shapes, trailing bytes, ...).
    #[error("malformed message: {0}")]
    Malformed(String),
}

/// Element type of a tensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum DType {
    /// 32-bit float.
    F32 = 1,
    /// 32-bit unsigned integer.
    U32 = 2,
    /// Byte.
    U8 = 3,
}

/// The fixed header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    /// Message kind.
    pub kind: Kind,
    /// Sender instance id.
    pub sender: u64,
    /// Sequence number.
    pub seq: u64,
    /// First timestamp (kind-specific).
    pub t_a: u64,
    /// Second timestamp (kind-specific).
    pub t_b: u64,
}

/// A decoded tensor.
#[derive(Debug, Clone, PartialEq)]
pub enum Tensor {
    /// f32 data.
    F32 {
        /// Shape.
        shape: Vec<usize>,
        /// Row-major data.
        data: Vec<f32>,
    },
    /// u32 data.
    U32 {
        /// Shape.
        shape: Vec<usize>,
        /// Row-major data.
        data: Vec<u32>,
    },
    /// Bytes.
    U8 {
        /// Shape.
        shape: Vec<usize>,
        /// Row-major data.
        data: Vec<u8>,
    },
}

impl Tensor {
    /// The shape.
    pub fn shape(&self) -> &[usize] {
        match self {
            Tensor::F32 { shape, .. } | Tensor::U32 { shape, .. } | Tensor::U8 { shape, .. } => {
                shape
            }
        }
    }
}

/// A decoded message.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    /// The header.
    pub header: Header,
    /// The tensors, in order.
    pub tensors: Vec<Tensor>,
}

/// Builds one message into a byte vector.
#[derive(Debug)]
pub struct Writer {
    buf: Vec<u8>,
    declared: u8,
    written: u8,
}

impl Writer {
    /// Start a message with room for `capacity` payload bytes.
    pub fn new(header: Header, n_tensors: u8, capacity: usize) -> Self {
        Self::with_version(header, n_tensors, capacity, WIRE_VERSION)
    }

    /// Start a message claiming another version (tests of the version check).
    pub fn with_version(header: Header, n_tensors: u8, capacity: usize, version: u16) -> Self {
        let mut buf = Vec::with_capacity(HEADER_LEN + capacity);
        buf.extend_from_slice(&MAGIC);
        buf.extend_from_slice(&version.to_le_bytes());
        buf.push(header.kind as u8);
        buf.push(n_tensors);
        for v in [header.sender, header.seq, header.t_a, header.t_b] {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        Self {
            buf,
            declared: n_tensors,
            written: 0,
        }
    }

    fn tensor_header(&mut self, dtype: DType, shape: &[usize], len: usize) {
        debug_assert!(shape.len() <= MAX_RANK);
        debug_assert_eq!(shape.iter().product::<usize>(), len);
        self.buf.push(dtype as u8);
        self.buf.push(shape.len() as u8);
        self.buf.extend_from_slice(&[0, 0]);
        for &d in shape {
            self.buf.extend_from_slice(&(d as u32).to_le_bytes());
        }
        self.written += 1;
    }

    /// Append an f32 tensor (`data.len()` must equal the product of `shape`).
    pub fn f32(mut self, shape: &[usize], data: &[f32]) -> Self {
        self.tensor_header(DType::F32, shape, data.len());
        self.buf.reserve(4 * data.len());
        for v in data {
            self.buf.extend_from_slice(&v.to_le_bytes());
        }
        self
    }

    /// Append a u32 tensor.
    pub fn u32(mut self, shape: &[usize], data: &[u32]) -> Self {
        self.tensor_header(DType::U32, shape, data.len());
        for v in data {
            self.buf.extend_from_slice(&v.to_le_bytes());
        }
        self
    }

    /// Append a byte tensor.
    pub fn u8(mut self, shape: &[usize], data: &[u8]) -> Self {
        self.tensor_header(DType::U8, shape, data.len());
        self.buf.extend_from_slice(data);
        self
    }

    /// The encoded message.
    pub fn finish(self) -> Vec<u8> {
        debug_assert_eq!(self.declared, self.written, "tensor count");
        self.buf
    }
}

struct Reader<'a> {
    b: &'a [u8],
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], WireError> {
        if self.b.len() < n {
            return Err(WireError::Truncated {
                what,
                need: n,
                got: self.b.len(),
            });
        }
        let (h, t) = self.b.split_at(n);
        self.b = t;
        Ok(h)
    }
    fn u8(&mut self, what: &'static str) -> Result<u8, WireError> {
        Ok(self.take(1, what)?[0])
    }
    fn u16(&mut self, what: &'static str) -> Result<u16, WireError> {
        let s = self.take(2, what)?;
        Ok(u16::from_le_bytes([s[0], s[1]]))
    }
    fn u32(&mut self, what: &'static str) -> Result<u32, WireError> {
        let s = self.take(4, what)?;
        Ok(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
    }
    fn u64(&mut self, what: &'static str) -> Result<u64, WireError> {
        let s = self.take(8, what)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(s);
        Ok(u64::from_le_bytes(a))
    }
}

/// Decode only the header (cheap; checks magic and version).
pub fn decode_header(bytes: &[u8]) -> Result<(Header, u8), WireError> {
    let mut r = Reader { b: bytes };
    if bytes.len() < HEADER_LEN {
        return Err(WireError::Truncated {
            what: "header",
            need: HEADER_LEN,
            got: bytes.len(),
        });
    }
    let magic = r.take(4, "magic")?;
    if magic != MAGIC {
        return Err(WireError::BadMagic([
            magic[0], magic[1], magic[2], magic[3],
        ]));
    }
    let version = r.u16("version")?;
    if version != WIRE_VERSION {
        return Err(WireError::Version {
            got: version,
            expected: WIRE_VERSION,
        });
    }
    let kind_b = r.u8("kind")?;
    let kind = Kind::from_u8(kind_b).ok_or(WireError::UnknownKind(kind_b))?;
    let n = r.u8("n_tensors")?;
    let header = Header {
        kind,
        sender: r.u64("sender")?,
        seq: r.u64("seq")?,
        t_a: r.u64("t_a")?,
        t_b: r.u64("t_b")?,
    };
    Ok((header, n))
}

/// Decode a whole message.
pub fn decode(bytes: &[u8]) -> Result<Message, WireError> {
    let (header, n) = decode_header(bytes)?;
    let mut r = Reader {
        b: &bytes[HEADER_LEN..],
    };
    let mut tensors = Vec::with_capacity(n as usize);
    for _ in 0..n {
        let dtype = r.u8("tensor dtype")?;
        let rank = r.u8("tensor rank")? as usize;
        let reserved = r.u16("tensor reserved")?;
        if rank > MAX_RANK {
            return Err(WireError::Malformed(format!(
                "tensor rank {rank} > {MAX_RANK}"
            )));
        }
        if reserved != 0 {
            return Err(WireError::Malformed(format!(
                "tensor reserved field is {reserved}, expected 0"
            )));
        }
        let mut shape = Vec::with_capacity(rank);
        let mut count: usize = 1;
        for _ in 0..rank {
            let d = r.u32("tensor dim")? as usize;
            count = count
                .checked_mul(d)
                .ok_or_else(|| WireError::Malformed("tensor element count overflows".into()))?;
            shape.push(d);
        }
        let size = match dtype {
            1 | 2 => 4,
            3 => 1,
            _ => return Err(WireError::Malformed(format!("unknown dtype {dtype}"))),
        };
        let nbytes = count
            .checked_mul(size)
            .ok_or_else(|| WireError::Malformed("tensor byte count overflows".into()))?;
        let raw = r.take(nbytes, "tensor data")?;
        tensors.push(match dtype {
            1 => Tensor::F32 {
                shape,
                data: raw
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                    .collect(),
            },
            2 => Tensor::U32 {
                shape,
                data: raw
                    .chunks_exact(4)
                    .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                    .collect(),
            },
            _ => Tensor::U8 {
                shape,
                data: raw.to_vec(),
            },
        });
    }
    if !r.b.is_empty() {
        return Err(WireError::Malformed(format!(
            "{} trailing bytes after the last tensor",
            r.b.len()
        )));
    }
    Ok(Message { header, tensors })
}

fn expect(msg: &Message, kind: Kind) -> Result<(), WireError> {
    if msg.header.kind == kind {
        Ok(())
    } else {
        Err(WireError::UnexpectedKind {
            expected: kind,
            got: msg.header.kind,
        })
    }
}

fn f32_tensor(t: Tensor, what: &str) -> Result<(Vec<usize>, Vec<f32>), WireError> {
    match t {
        Tensor::F32 { shape, data } => Ok((shape, data)),
        other => Err(WireError::Malformed(format!(
            "{what}: expected f32, got {other_dtype}",
            other_dtype = match other {
                Tensor::U32 { .. } => "u32",
                _ => "u8",
            }
        ))),
    }
}

fn shape_is(what: &str, got: &[usize], want: &[usize]) -> Result<(), WireError> {
    if got == want {
        Ok(())
    } else {
        Err(WireError::Malformed(format!(
            "{what}: shape {got:?}, expected {want:?}"
        )))
    }
}

// ---------------------------------------------------------------- features

/// Slow features as sent by `serve_slow`.
#[derive(Debug, Clone, PartialEq)]
pub struct FeaturesMsg {
    /// Sender instance.
    pub sender: u64,
    /// Sequence number (increasing per sender).
    pub seq: u64,
    /// Capture time on the sender's clock.
    pub t_capture: u64,
    /// Publish time on the sender's clock.
    pub t_sent: u64,
    /// Tokens.
    pub tokens: usize,
    /// Token width.
    pub dim: usize,
    /// `[tokens, dim]` data.
    pub data: Vec<f32>,
}

/// Encode slow features (`data` is `[tokens, dim]`).
pub fn encode_features(
    sender: u64,
    seq: u64,
    t_capture: u64,
    t_sent: u64,
    tokens: usize,
    dim: usize,
    data: &[f32],
) -> Vec<u8> {
    Writer::new(
        Header {
            kind: Kind::Features,
            sender,
            seq,
            t_a: t_capture,
            t_b: t_sent,
        },
        1,
        16 + 4 * data.len(),
    )
    .f32(&[tokens, dim], data)
    .finish()
}

/// Decode slow features.
pub fn decode_features(bytes: &[u8]) -> Result<FeaturesMsg, WireError> {
    let msg = decode(bytes)?;
    expect(&msg, Kind::Features)?;
    let h = msg.header;
    let [t]: [Tensor; 1] = msg
        .tensors
        .try_into()
        .map_err(|v: Vec<Tensor>| WireError::Malformed(format!("features: {} tensors", v.len())))?;
    let (shape, data) = f32_tensor(t, "features")?;
    if shape.len() != 2 {
        return Err(WireError::Malformed(format!(
            "features: rank {}, expected 2",
            shape.len()
        )));
    }
    Ok(FeaturesMsg {
        sender: h.sender,
        seq: h.seq,
        t_capture: h.t_a,
        t_sent: h.t_b,
        tokens: shape[0],
        dim: shape[1],
        data,
    })
}

// ---------------------------------------------------------------- policy

/// Slow input of a decoded request.
#[derive(Debug, Clone, PartialEq)]
pub enum SlowOwned {
    /// None.
    None,
    /// `[B, dim]`.
    Vector {
        /// Data.
        data: Vec<f32>,
        /// Width.
        dim: usize,
    },
    /// `[B, tokens, dim]`.
    Tokens {
        /// Data.
        data: Vec<f32>,
        /// Tokens per sample.
        tokens: usize,
        /// Token width.
        dim: usize,
    },
}

/// A decoded one-NFE request (owns its tensors).
#[derive(Debug, Clone, PartialEq)]
pub struct Request {
    /// Header (sender, seq, send time).
    pub header: Header,
    /// `B`.
    pub batch: usize,
    /// `H`.
    pub horizon: usize,
    /// `A`.
    pub action_dim: usize,
    /// `n_obs`.
    pub n_obs: usize,
    /// `F`.
    pub fast_dim: usize,
    /// `[B, H, A]`.
    pub x: Vec<f32>,
    /// `[B, H]`.
    pub tau: Vec<f32>,
    /// `[B, n_obs, F]`.
    pub obs_fast: Vec<f32>,
    /// `[B]`.
    pub d_vis: Vec<u32>,
    /// Slow input.
    pub slow: SlowOwned,
}

impl Request {
    /// Borrow as a model input.
    pub fn input(&self) -> ModelInput<'_> {
        ModelInput {
            batch: self.batch,
            horizon: self.horizon,
            action_dim: self.action_dim,
            x: &self.x,
            tau: &self.tau,
            obs_fast: &self.obs_fast,
            n_obs: self.n_obs,
            fast_dim: self.fast_dim,
            slow: match &self.slow {
                SlowOwned::None => SlowInput::None,
                SlowOwned::Vector { data, dim } => SlowInput::Vector { data, dim: *dim },
                SlowOwned::Tokens { data, tokens, dim } => SlowInput::Tokens {
                    data,
                    tokens: *tokens,
                    dim: *dim,
                },
            },
            d_vis: &self.d_vis,
        }
    }
}

/// Bytes of an encoded request for these sizes (for the latency example's report).
pub fn request_len(input: &ModelInput<'_>) -> usize {
    let slow = match input.slow {
        SlowInput::None => 0,
        SlowInput::Vector { data, .. } => 4 + 8 + 4 * data.len(),
        SlowInput::Tokens { data, .. } => 4 + 12 + 4 * data.len(),
    };
    HEADER_LEN
        + (4 + 12 + 4 * input.x.len())
        + (4 + 8 + 4 * input.tau.len())
        + (4 + 12 + 4 * input.obs_fast.len())
        + (4 + 4 + 4 * input.d_vis.len())
        + slow
}

/// Encode a request. The input must be valid ([`ModelInput::validate`]).
pub fn encode_request(sender: u64, seq: u64, t_send: u64, input: &ModelInput<'_>) -> Vec<u8> {
    let (b, h, a) = (input.batch, input.horizon, input.action_dim);
    let n = if matches!(input.slow, SlowInput::None) {
        4
    } else {
        5
    };
    let w = Writer::new(
        Header {
            kind: Kind::PolicyRequest,
            sender,
            seq,
            t_a: t_send,
            t_b: 0,
        },
        n,
        request_len(input),
    )
    .f32(&[b, h, a], input.x)
    .f32(&[b, h], input.tau)
    .f32(&[b, input.n_obs, input.fast_dim], input.obs_fast)
    .u32(&[b], input.d_vis);
    match input.slow {
        SlowInput::None => w,
        SlowInput::Vector { data, dim } => w.f32(&[b, dim], data),
        SlowInput::Tokens { data, tokens, dim } => w.f32(&[b, tokens, dim], data),
    }
    .finish()
}

/// Decode a request, checking that every shape agrees.
pub fn decode_request(bytes: &[u8]) -> Result<Request, WireError> {
    let msg = decode(bytes)?;
    expect(&msg, Kind::PolicyRequest)?;
    let header = msg.header;
    let n = msg.tensors.len();
    if n != 4 && n != 5 {
        return Err(WireError::Malformed(format!(
            "policy request: {n} tensors, expected 4 or 5"
        )));
    }
    let mut it = msg.tensors.into_iter();
    let (xs, x) = f32_tensor(it.next().unwrap_or_else(empty), "x")?;
    if xs.len() != 3 {
        return Err(WireError::Malformed(format!(
            "x: rank {}, expected 3",
            xs.len()
        )));
    }
    let (b, h, a) = (xs[0], xs[1], xs[2]);
    let (ts, tau) = f32_tensor(it.next().unwrap_or_else(empty), "tau")?;
    shape_is("tau", &ts, &[b, h])?;
    let (os, obs_fast) = f32_tensor(it.next().unwrap_or_else(empty), "obs_fast")?;
    if os.len() != 3 || os[0] != b {
        return Err(WireError::Malformed(format!(
            "obs_fast: shape {os:?}, expected [{b}, n_obs, F]"
        )));
    }
    let (n_obs, fast_dim) = (os[1], os[2]);
    let d_vis = match it.next().unwrap_or_else(empty) {
        Tensor::U32 { shape, data } => {
            shape_is("d_vis", &shape, &[b])?;
            data
        }
        _ => return Err(WireError::Malformed("d_vis: expected u32".into())),
    };
    let slow = match it.next() {
        None => SlowOwned::None,
        Some(t) => {
            let (ss, data) = f32_tensor(t, "slow")?;
            match ss.as_slice() {
                [bb, dim] if *bb == b => SlowOwned::Vector { data, dim: *dim },
                [bb, tokens, dim] if *bb == b => SlowOwned::Tokens {
                    data,
                    tokens: *tokens,
                    dim: *dim,
                },
                _ => {
                    return Err(WireError::Malformed(format!(
                        "slow: shape {ss:?}, expected [{b}, S] or [{b}, T, D]"
                    )))
                }
            }
        }
    };
    Ok(Request {
        header,
        batch: b,
        horizon: h,
        action_dim: a,
        n_obs,
        fast_dim,
        x,
        tau,
        obs_fast,
        d_vis,
        slow,
    })
}

fn empty() -> Tensor {
    Tensor::U8 {
        shape: vec![0],
        data: Vec::new(),
    }
}

/// Encode the reply to request `req` (`v` is `[B, H, A]`).
pub fn encode_reply(
    sender: u64,
    req: &Header,
    model_ns: u64,
    shape: [usize; 3],
    v: &[f32],
) -> Vec<u8> {
    Writer::new(
        Header {
            kind: Kind::PolicyReply,
            sender,
            seq: req.seq,
            t_a: req.t_a,
            t_b: model_ns,
        },
        1,
        16 + 4 * v.len(),
    )
    .f32(&shape, v)
    .finish()
}

/// A decoded reply.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// The velocity.
    Velocity {
        /// Header (echoed seq, model time in `t_b`).
        header: Header,
        /// `[B, H, A]`.
        shape: Vec<usize>,
        /// Data.
        v: Vec<f32>,
    },
    /// The server failed to answer.
    Error(String),
}

/// Decode a reply (a velocity or a server error).
pub fn decode_reply(bytes: &[u8]) -> Result<Reply, WireError> {
    let msg = decode(bytes)?;
    if msg.header.kind == Kind::Error {
        return Ok(Reply::Error(error_text(msg)?));
    }
    expect(&msg, Kind::PolicyReply)?;
    let header = msg.header;
    let [t]: [Tensor; 1] = msg
        .tensors
        .try_into()
        .map_err(|v: Vec<Tensor>| WireError::Malformed(format!("reply: {} tensors", v.len())))?;
    let (shape, v) = f32_tensor(t, "v")?;
    Ok(Reply::Velocity { header, shape, v })
}

// ---------------------------------------------------------------- ping / error

/// Encode a ping sent at `t_send` (local clock).
pub fn encode_ping(sender: u64, seq: u64, t_send: u64) -> Vec<u8> {
    Writer::new(
        Header {
            kind: Kind::Ping,
            sender,
            seq,
            t_a: t_send,
            t_b: 0,
        },
        0,
        0,
    )
    .finish()
}

/// Encode the answer to `ping`, stamped `t_recv` on the server clock.
pub fn encode_pong(sender: u64, ping: &Header, t_recv: u64) -> Vec<u8> {
    Writer::new(
        Header {
            kind: Kind::Pong,
            sender,
            seq: ping.seq,
            t_a: ping.t_a,
            t_b: t_recv,
        },
        0,
        0,
    )
    .finish()
}

/// Decode a pong (anything else, e.g. a server error, is `Err(UnexpectedKind)`).
pub fn decode_pong(bytes: &[u8]) -> Result<Header, WireError> {
    let msg = decode(bytes)?;
    expect(&msg, Kind::Pong)?;
    Ok(msg.header)
}

/// Encode an error message.
pub fn encode_error(sender: u64, seq: u64, text: &str) -> Vec<u8> {
    let b = text.as_bytes();
    Writer::new(
        Header {
            kind: Kind::Error,
            sender,
            seq,
            t_a: 0,
            t_b: 0,
        },
        1,
        8 + b.len(),
    )
    .u8(&[b.len()], b)
    .finish()
}

fn error_text(msg: Message) -> Result<String, WireError> {
    match msg.tensors.into_iter().next() {
        Some(Tensor::U8 { data, .. }) => Ok(String::from_utf8_lossy(&data).into_owned()),
        _ => Err(WireError::Malformed("error message without text".into())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn hdr(kind: Kind) -> Header {
        Header {
            kind,
            sender: 7,
            seq: 42,
            t_a: 1_000,
            t_b: 2_000,
        }
    }

    #[test]
    fn version_mismatch_is_a_typed_error() {
        let bytes = Writer::with_version(hdr(Kind::Ping), 0, 0, WIRE_VERSION + 1).finish();
        assert_eq!(
            decode(&bytes).unwrap_err(),
            WireError::Version {
                got: WIRE_VERSION + 1,
                expected: WIRE_VERSION
            }
        );
        let msg = decode_pong(&bytes).unwrap_err().to_string();
        assert!(msg.contains("v2") && msg.contains("v1"), "{msg}");
    }

    #[test]
    fn bad_magic_and_kind_and_trailing_bytes() {
        let mut bytes = encode_ping(1, 2, 3);
        assert_eq!(decode(&bytes).unwrap().header.kind, Kind::Ping);
        bytes.push(0);
        assert!(matches!(decode(&bytes), Err(WireError::Malformed(_))));
        bytes.pop();
        bytes[6] = 99;
        assert_eq!(decode(&bytes).unwrap_err(), WireError::UnknownKind(99));
        bytes[0] = b'X';
        assert!(matches!(decode(&bytes), Err(WireError::BadMagic(_))));
        assert!(matches!(
            decode(&bytes[..10]),
            Err(WireError::Truncated { .. })
        ));
    }

    #[test]
    fn huge_declared_tensor_is_rejected_without_allocating() {
        let mut bytes = Writer::new(hdr(Kind::Features), 0, 0).finish();
        bytes[7] = 1; // one tensor, declared [u32::MAX, u32::MAX] f32 with no data
        bytes.extend_from_slice(&[1, 2, 0, 0]);
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            decode(&bytes),
            Err(WireError::Truncated { .. }) | Err(WireError::Malformed(_))
        ));
    }

    #[test]
    fn wrong_kind_is_reported() {
        let bytes = encode_ping(1, 2, 3);
        assert_eq!(
            decode_features(&bytes).unwrap_err(),
            WireError::UnexpectedKind {
                expected: Kind::Features,
                got: Kind::Ping
            }
        );
        let e = encode_error(1, 2, "model exploded");
        assert_eq!(
            decode_reply(&e).unwrap(),
            Reply::Error("model exploded".into())
        );
    }

    #[test]
    fn request_len_matches_encoding() {
        let x = vec![0.5; 2 * 3 * 4];
        let tau = vec![0.0; 2 * 3];
        let obs = vec![1.0; 2 * 2 * 5];
        let slow = vec![2.0; 2 * 3 * 6];
        let dv = [1, 2];
        let input = ModelInput {
            batch: 2,
            horizon: 3,
            action_dim: 4,
            x: &x,
            tau: &tau,
            obs_fast: &obs,
            n_obs: 2,
            fast_dim: 5,
            slow: SlowInput::Tokens {
                data: &slow,
                tokens: 3,
                dim: 6,
            },
            d_vis: &dv,
        };
        let bytes = encode_request(1, 2, 3, &input);
        assert_eq!(bytes.len(), request_len(&input));
    }

    fn slow_strategy(b: usize) -> impl Strategy<Value = SlowOwned> {
        prop_oneof![
            Just(SlowOwned::None),
            (1usize..6).prop_flat_map(move |dim| {
                prop::collection::vec(-1e6f32..1e6, b * dim)
                    .prop_map(move |data| SlowOwned::Vector { data, dim })
            }),
            (1usize..4, 1usize..5).prop_flat_map(move |(tokens, dim)| {
                prop::collection::vec(-1e6f32..1e6, b * tokens * dim)
                    .prop_map(move |data| SlowOwned::Tokens { data, tokens, dim })
            }),
        ]
    }

    fn request_strategy() -> impl Strategy<Value = Request> {
        (
            1usize..3,
            1usize..6,
            1usize..5,
            1usize..3,
            1usize..5,
            any::<[u64; 3]>(),
        )
            .prop_flat_map(|(b, h, a, n_obs, f, ids)| {
                (
                    prop::collection::vec(any::<f32>(), b * h * a),
                    prop::collection::vec(0f32..=1.0, b * h),
                    prop::collection::vec(any::<f32>(), b * n_obs * f),
                    prop::collection::vec(0u32..10, b),
                    slow_strategy(b),
                )
                    .prop_map(move |(x, tau, obs_fast, d_vis, slow)| Request {
                        header: Header {
                            kind: Kind::PolicyRequest,
                            sender: ids[0],
                            seq: ids[1],
                            t_a: ids[2],
                            t_b: 0,
                        },
                        batch: b,
                        horizon: h,
                        action_dim: a,
                        n_obs,
                        fast_dim: f,
                        x,
                        tau,
                        obs_fast,
                        d_vis,
                        slow,
                    })
            })
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    proptest! {
        #[test]
        fn request_round_trips_bit_exactly(req in request_strategy()) {
            let bytes = encode_request(req.header.sender, req.header.seq, req.header.t_a, &req.input());
            let back = decode_request(&bytes).unwrap();
            prop_assert_eq!(back.header, req.header);
            prop_assert_eq!((back.batch, back.horizon, back.action_dim, back.n_obs, back.fast_dim),
                (req.batch, req.horizon, req.action_dim, req.n_obs, req.fast_dim));
            prop_assert_eq!(bits(&back.x), bits(&req.x)); // NaN payloads survive too
            prop_assert_eq!(bits(&back.tau), bits(&req.tau));
            prop_assert_eq!(bits(&back.obs_fast), bits(&req.obs_fast));
            prop_assert_eq!(&back.d_vis, &req.d_vis);
            prop_assert_eq!(&back.slow, &req.slow);
            back.input().validate().unwrap();
        }

        #[test]
        fn features_round_trip(tokens in 0usize..5, dim in 0usize..7, seed in any::<u64>(), t in any::<[u64; 2]>()) {
            let data: Vec<f32> = (0..tokens * dim).map(|i| (i as f32) * 0.5 - seed as f32).collect();
            let bytes = encode_features(seed, seed ^ 1, t[0], t[1], tokens, dim, &data);
            let m = decode_features(&bytes).unwrap();
            prop_assert_eq!(m, FeaturesMsg { sender: seed, seq: seed ^ 1, t_capture: t[0], t_sent: t[1], tokens, dim, data });
        }

        #[test]
        fn reply_and_pong_round_trip(seq in any::<u64>(), t in any::<[u64; 3]>(), v in prop::collection::vec(any::<f32>(), 6)) {
            let req = Header { kind: Kind::PolicyRequest, sender: 1, seq, t_a: t[0], t_b: 0 };
            match decode_reply(&encode_reply(9, &req, t[1], [1, 2, 3], &v)).unwrap() {
                Reply::Velocity { header, shape, v: back } => {
                    prop_assert_eq!(header.seq, seq);
                    prop_assert_eq!(header.t_a, t[0]);
                    prop_assert_eq!(header.t_b, t[1]);
                    prop_assert_eq!(shape, vec![1, 2, 3]);
                    prop_assert_eq!(bits(&back), bits(&v));
                }
                Reply::Error(e) => prop_assert!(false, "{}", e),
            }
            let ping = decode(&encode_ping(3, seq, t[0])).unwrap().header;
            let pong = decode_pong(&encode_pong(4, &ping, t[2])).unwrap();
            prop_assert_eq!((pong.seq, pong.t_a, pong.t_b, pong.sender), (seq, t[0], t[2], 4));
        }

        #[test]
        fn garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
            let _ = decode(&bytes);
            let _ = decode_request(&bytes);
            let _ = decode_features(&bytes);
            let _ = decode_reply(&bytes);
            let _ = decode_pong(&bytes);
        }

        #[test]
        fn corrupted_valid_messages_never_panic(req in request_strategy(), flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8), cut in any::<prop::sample::Index>()) {
            let mut bytes = encode_request(1, 2, 3, &req.input());
            // Keep magic and version intact so the corruption reaches the tensor parser.
            for (i, b) in &flips {
                let k = 6 + i.index(bytes.len() - 6);
                bytes[k] = *b;
            }
            let _ = decode_request(&bytes);
            let n = cut.index(bytes.len() + 1);
            let _ = decode_request(&bytes[..n]);
            let _ = decode_reply(&bytes[..n]);
        }
    }
}
