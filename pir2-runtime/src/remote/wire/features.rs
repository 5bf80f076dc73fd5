//! Kind 1: slow features with their capture time.

use super::codec::*;

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
