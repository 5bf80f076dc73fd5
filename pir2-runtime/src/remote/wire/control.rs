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
    let header = Header {
        kind: Kind::Pong,
        sender,
        seq: ping.seq,
        t_a: ping.t_a,
        t_b: t_recv,
    };
    match identity {
        None => Writer::new(header, 0, 0).finish(),
        Some(text) => {
            let b = text.as_bytes();
            Writer::new(header, 1, 8 + b.len())
                .u8(&[b.len()], b)
                .finish()
        }
    }
}

/// Decode a pong (anything else, e.g. a server error, is `Err(UnexpectedKind)`).
pub fn decode_pong(bytes: &[u8]) -> Result<Header, WireError> {
    decode_pong_identity(bytes).map(|(h, _)| h)
}

/// Decode a pong and the identity it carries (`None`: a pong without one).
pub fn decode_pong_identity(bytes: &[u8]) -> Result<(Header, Option<String>), WireError> {
    let msg = decode(bytes)?;
    expect(&msg, Kind::Pong)?;
    let header = msg.header;
    match msg.tensors.len() {
        0 => Ok((header, None)),
        1 => Ok((header, Some(error_text(msg)?))),
        n => Err(WireError::Malformed(format!(
            "a pong carries at most one tensor (the identity), got {n}"
        ))),
    }
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

pub(super) fn error_text(msg: Message) -> Result<String, WireError> {
    match msg.tensors.into_iter().next() {
        Some(Tensor::U8 { data, .. }) => Ok(String::from_utf8_lossy(&data).into_owned()),
        _ => Err(WireError::Malformed("error message without text".into())),
    }
}
