//! Clock offset between a server and the robot: NTP-style ping/pong, minimum-RTT sample.
//!
//! The robot sends a ping at `t0` (its clock); the server stamps `ts` on receipt (its
//! clock); the pong arrives at `t1`. If both legs take the same time,
//! `offset = ts − (t0 + t1)/2` is exact; in general the error is at most `(t1 − t0)/2`
//! of that sample, so the sample with the smallest round trip is kept.

use std::time::{Duration, Instant};

use zenoh::query::ConsolidationMode;
use zenoh::Wait;

use super::wire;
use super::{transport, Error, Result};
use crate::clock::{Clock, Nanos};

/// One ping/pong exchange.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OffsetSample {
    /// Ping sent (robot clock).
    pub t0: Nanos,
    /// Ping received (server clock).
    pub t_server: Nanos,
    /// Pong received (robot clock).
    pub t1: Nanos,
}

impl OffsetSample {
    /// Round trip, ns.
    pub fn rtt(&self) -> Nanos {
        self.t1.saturating_sub(self.t0)
    }
    /// Server minus robot clock, assuming symmetric legs.
    pub fn offset(&self) -> i64 {
        let mid = (self.t0 as i128 + self.t1 as i128) / 2;
        (self.t_server as i128 - mid).clamp(i64::MIN as i128, i64::MAX as i128) as i64
    }
}

/// An offset estimate: `server clock − robot clock`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClockOffset {
    /// Offset, ns.
    pub offset_ns: i64,
    /// Round trip of the sample it came from; the error is at most half of it.
    pub rtt_ns: Nanos,
}

impl ClockOffset {
    /// A server time converted into the robot's clock (saturating at 0).
    pub fn to_local(&self, t_server: Nanos) -> Nanos {
        (t_server as i128 - self.offset_ns as i128).clamp(0, u64::MAX as i128) as Nanos
    }
}

/// The estimate from the sample with the smallest round trip (`None` if no samples).
pub fn estimate_offset(samples: &[OffsetSample]) -> Option<ClockOffset> {
    samples
        .iter()
        .filter(|s| s.t1 >= s.t0)
        .min_by_key(|s| s.rtt())
        .map(|s| ClockOffset {
            offset_ns: s.offset(),
            rtt_ns: s.rtt(),
        })
}

/// Send one request on `key` and hand each reply's payload to `each` as it arrives, until
/// `each` returns `Some` (returned), `timeout` passes or every responder has answered
/// (`Ok(None)`). Error replies of the transport (not of a server) are skipped.
pub(crate) fn query_each<T>(
    session: &zenoh::Session,
    key: &zenoh::key_expr::KeyExpr<'static>,
    payload: zenoh::bytes::ZBytes,
    timeout: Duration,
    mut each: impl FnMut(&[u8]) -> Result<Option<T>>,
) -> Result<Option<T>> {
    let deadline = Instant::now() + timeout;
    let replies = session
        .get(key)
        .payload(payload)
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .wait()
        .map_err(transport("query"))?;
    loop {
        match replies.recv_deadline(deadline) {
            Ok(Some(reply)) => {
                if let Ok(sample) = reply.result() {
                    if let Some(t) = each(&sample.payload().to_bytes())? {
                        return Ok(Some(t));
                    }
                }
            }
            // Timed out, or the query finished (every responder answered).
            Ok(None) | Err(_) => return Ok(None),
        }
    }
}

/// Ping `key` `n` times and estimate the offset of the server `sender` (pongs from another
/// instance are ignored: with `Some(sender)`, only that instance's pongs count; with `None`,
/// the first instance that answers is pinned for the rest). Errors: nothing answered, or a
/// wire error.
pub(crate) fn sync_clock(
    session: &zenoh::Session,
    key: &zenoh::key_expr::KeyExpr<'static>,
    clock: &dyn Clock,
    me: u64,
    sender: Option<u64>,
    n: usize,
    timeout: Duration,
) -> Result<(u64, ClockOffset)> {
    let mut samples = Vec::with_capacity(n);
    let mut from = sender;
    for i in 0..n.max(1) {
        let t0 = clock.now();
        let ping = wire::encode_ping(me, i as u64, t0);
        let pong = query_each(session, key, ping.into(), timeout, |bytes| {
            let pong = match wire::decode_pong(bytes) {
                Ok(p) => p,
                Err(e @ wire::WireError::Version { .. }) => return Err(e.into()),
                // Not a pong (another responder, damage): not this server's answer.
                Err(_) => return Ok(None),
            };
            let ours = pong.t_a == t0 && from.is_none_or(|s| s == pong.sender);
            Ok(ours.then_some(pong))
        })?;
        let Some(pong) = pong else {
            continue;
        };
        let t1 = clock.now();
        from = Some(pong.sender);
        samples.push(OffsetSample {
            t0,
            t_server: pong.t_b,
            t1,
        });
    }
    match (from, estimate_offset(&samples)) {
        (Some(s), Some(o)) => Ok((s, o)),
        _ => Err(Error::Timeout {
            what: "clock offset (ping)",
            after: timeout,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn min_rtt_sample_wins_and_symmetric_legs_are_exact() {
        // Server clock = robot clock + 5 s. Symmetric 10 µs legs: exact.
        let off = 5_000_000_000i64;
        let exact = OffsetSample {
            t0: 1_000_000,
            t_server: (1_010_000 + off) as u64,
            t1: 1_020_000,
        };
        // Asymmetric: 1 ms out, 10 µs back → error ~0.5 ms, larger RTT.
        let skewed = OffsetSample {
            t0: 2_000_000,
            t_server: (3_000_000 + off) as u64,
            t1: 3_010_000,
        };
        let e = estimate_offset(&[skewed, exact]).unwrap();
        assert_eq!(e.offset_ns, off);
        assert_eq!(e.rtt_ns, 20_000);
        assert!((skewed.offset() - off).abs() <= skewed.rtt() as i64 / 2);
        assert_eq!(e.to_local((1_010_000 + off) as u64), 1_010_000);
        assert_eq!(estimate_offset(&[]), None);
    }

    #[test]
    fn negative_offsets_saturate_at_zero() {
        let e = ClockOffset {
            offset_ns: -1_000,
            rtt_ns: 0,
        };
        assert_eq!(e.to_local(5), 1_005);
        let e = ClockOffset {
            offset_ns: 1_000,
            rtt_ns: 0,
        };
        assert_eq!(e.to_local(5), 0);
    }
}
