//! Kinds 4 to 6: clock pings, pongs and error replies.

use super::codec::*;

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
    encode_pong_with_identity(sender, ping, t_recv, None)
}

/// [`encode_pong`] carrying the server's identity (a policy server's checkpoint: UTF-8
/// text, one u8 tensor) when it has one. A peer that reads only the header (an older
/// build) ignores it.
pub fn encode_pong_with_identity(
    sender: u64,
    ping: &Header,
    t_recv: u64,
    identity: Option<&str>,
) -> Vec<u8> {
    encode_pong_with_token(sender, ping, t_recv, identity, None)
}

/// The secret a policy server issues to one client in the pong that answers its ping, and
/// repeats in every reply to that client's requests (128 random bits). The client takes
/// replies only when they carry the token of its last handshake: a peer that merely listens
/// on the same key never sees the pong, so it cannot forge a reply.
pub type SessionToken = [u32; 4];

/// [`encode_pong_with_identity`] that also issues `token` (a policy server's handshake).
pub fn encode_pong_with_token(
    sender: u64,
    ping: &Header,
    t_recv: u64,
    identity: Option<&str>,
    token: Option<SessionToken>,
) -> Vec<u8> {
    let header = Header {
        kind: Kind::Pong,
        sender,
        seq: ping.seq,
        t_a: ping.t_a,
        t_b: t_recv,
    };
    let id = identity.map(str::as_bytes);
    let n = u8::from(id.is_some()) + u8::from(token.is_some());
    let mut w = Writer::new(header, n, 8 + id.map_or(0, <[u8]>::len) + 24);
    if let Some(b) = id {
        w = w.u8(&[b.len()], b);
    }
    if let Some(t) = token {
        w = w.u32(&[4], &t);
    }
    w.finish()
}

/// A decoded pong.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pong {
    /// Header (echoed ping `t_a`, receive time in `t_b`).
    pub header: Header,
    /// The server's identity, if it announces one.
    pub identity: Option<String>,
    /// The session token a policy server issues with it.
    pub token: Option<SessionToken>,
}

/// Decode a pong (anything else, e.g. a server error, is `Err(UnexpectedKind)`).
pub fn decode_pong(bytes: &[u8]) -> Result<Header, WireError> {
    decode_pong_full(bytes).map(|p| p.header)
}

/// Decode a pong and the identity it carries (`None`: a pong without one).
pub fn decode_pong_identity(bytes: &[u8]) -> Result<(Header, Option<String>), WireError> {
    decode_pong_full(bytes).map(|p| (p.header, p.identity))
}

/// Decode a pong, its identity and its session token.
pub fn decode_pong_full(bytes: &[u8]) -> Result<Pong, WireError> {
    let msg = decode(bytes)?;
    expect(&msg, Kind::Pong)?;
    let mut pong = Pong {
        header: msg.header,
        identity: None,
        token: None,
    };
    for t in msg.tensors {
        match t {
            Tensor::U8 { data, .. } if pong.identity.is_none() && pong.token.is_none() => {
                pong.identity = Some(String::from_utf8_lossy(&data).into_owned());
            }
            t if pong.token.is_none() => pong.token = Some(token(t)?),
            _ => {
                return Err(WireError::Malformed(
                    "a pong carries at most an identity and a session token".into(),
                ))
            }
        }
    }
    Ok(pong)
}

/// A session token tensor: u32 `[4]`.
pub(super) fn token(t: Tensor) -> Result<SessionToken, WireError> {
    match t {
        Tensor::U32 { shape, data } if shape == [4] => {
            let mut out = [0u32; 4];
            out.copy_from_slice(&data);
            Ok(out)
        }
        t => Err(WireError::Malformed(format!(
            "expected a session token (u32 [4]), got a tensor of shape {:?}",
            t.shape()
        ))),
    }
}

/// Encode an error message.
pub fn encode_error(sender: u64, seq: u64, text: &str) -> Vec<u8> {
    encode_error_with_token(sender, seq, text, None)
}

/// [`encode_error`] carrying the session token of the client it answers.
pub fn encode_error_with_token(
    sender: u64,
    seq: u64,
    text: &str,
    token: Option<SessionToken>,
) -> Vec<u8> {
    let b = text.as_bytes();
    let w = Writer::new(
        Header {
            kind: Kind::Error,
            sender,
            seq,
            t_a: 0,
            t_b: 0,
        },
        1 + u8::from(token.is_some()),
        8 + b.len() + 24,
    )
    .u8(&[b.len()], b);
    match token {
        Some(t) => w.u32(&[4], &t),
        None => w,
    }
    .finish()
}

pub(super) fn error_text(msg: Message) -> Result<String, WireError> {
    match msg.tensors.into_iter().next() {
        Some(Tensor::U8 { data, .. }) => Ok(String::from_utf8_lossy(&data).into_owned()),
        _ => Err(WireError::Malformed("error message without text".into())),
    }
}
