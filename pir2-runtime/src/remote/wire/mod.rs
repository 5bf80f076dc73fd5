//! The wire format of the remote slow channel and the remote action head (version 2).
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
//! | 3    | PolicyReply   | echo of request t_a     | model time, ns           | f32 v `[B,H,A]`, u32 session token `[4]` |
//! | 4    | Ping          | send time (robot clock) | 0                        | none |
//! | 5    | Pong          | echo of ping t_a        | receive time (server clock) | optional u8 `[n]` UTF-8 identity of a policy server's checkpoint, then (policy server) u32 session token `[4]` |
//! | 6    | Error         | 0                       | 0                        | u8 `[n]` UTF-8 message, then the session token `[4]` when the server knows the client |
//!
//! A policy server's pong may carry its identity (for a candle checkpoint, the JSON of
//! `pir2_backends::checkpoint::Identity`: the policy it was trained as and the SHA-256 of
//! its weights), so a client can refuse a server running another checkpoint.
//!
//! Version 2 added the session token ([`SessionToken`]): a policy server issues a fresh one
//! in each pong (per client `sender`) and repeats it in every reply and error to that
//! client; the client takes only replies carrying the token of its last handshake, so a
//! peer that merely answers on the same key cannot have its replies used.
//!
//! Decoding checks every length before allocating, so garbage of any length returns a
//! [`WireError`] and never panics or allocates more than the input's size.

mod codec;
mod control;
mod features;
mod policy;
#[cfg(test)]
mod tests;

pub use codec::*;
pub use control::*;
pub use features::*;
pub use policy::*;
