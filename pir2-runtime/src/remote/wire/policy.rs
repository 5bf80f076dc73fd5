//! Kinds 2 and 3: action-head requests and replies.

use super::codec::*;
use super::control::{error_text, token, SessionToken};
use crate::model::{ModelInput, SlowInput};

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
    encode_reply_with_token(sender, req, model_ns, shape, v, None)
}

/// [`encode_reply`] carrying the session token of the client it answers.
pub fn encode_reply_with_token(
    sender: u64,
    req: &Header,
    model_ns: u64,
    shape: [usize; 3],
    v: &[f32],
    token: Option<SessionToken>,
) -> Vec<u8> {
    let w = Writer::new(
        Header {
            kind: Kind::PolicyReply,
            sender,
            seq: req.seq,
            t_a: req.t_a,
            t_b: model_ns,
        },
        1 + u8::from(token.is_some()),
        16 + 4 * v.len() + 24,
    )
    .f32(&shape, v);
    match token {
        Some(t) => w.u32(&[4], &t),
        None => w,
    }
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
    decode_reply_with_token(bytes).map(|(r, _)| r)
}

/// Decode a reply and the session token it carries (`None`: a reply without one, which a
/// client never takes as its server's).
pub fn decode_reply_with_token(bytes: &[u8]) -> Result<(Reply, Option<SessionToken>), WireError> {
    let mut msg = decode(bytes)?;
    let n = msg.tensors.len();
    if msg.header.kind != Kind::Error {
        expect(&msg, Kind::PolicyReply)?;
    }
    if n == 0 || n > 2 {
        return Err(WireError::Malformed(format!("reply: {n} tensors")));
    }
    let tok = if n == 2 {
        msg.tensors.pop().map(token).transpose()?
    } else {
        None
    };
    if msg.header.kind == Kind::Error {
        return Ok((Reply::Error(error_text(msg)?), tok));
    }
    let header = msg.header;
    let t = msg.tensors.pop().unwrap_or_else(empty);
    let (shape, v) = f32_tensor(t, "v")?;
    Ok((Reply::Velocity { header, shape, v }, tok))
}
