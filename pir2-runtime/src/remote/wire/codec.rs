//! The message header, the tensor codec and the checks every message family shares.

/// Magic bytes at the start of every message.
pub const MAGIC: [u8; 4] = *b"PIR2";
/// The version this build speaks.
pub const WIRE_VERSION: u16 = 2;
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

pub(super) fn expect(msg: &Message, kind: Kind) -> Result<(), WireError> {
    if msg.header.kind == kind {
        Ok(())
    } else {
        Err(WireError::UnexpectedKind {
            expected: kind,
            got: msg.header.kind,
        })
    }
}

pub(super) fn f32_tensor(t: Tensor, what: &str) -> Result<(Vec<usize>, Vec<f32>), WireError> {
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

pub(super) fn shape_is(what: &str, got: &[usize], want: &[usize]) -> Result<(), WireError> {
    if got == want {
        Ok(())
    } else {
        Err(WireError::Malformed(format!(
            "{what}: shape {got:?}, expected {want:?}"
        )))
    }
}
