//! The remote action head: `serve_policy` answers one-NFE requests with a local model;
//! `RemoteModel` is the robot's `VelocityModel` that forwards each call.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use zenoh::key_expr::KeyExpr;
use zenoh::Wait;

use super::clock_sync::query;
use super::{bump, instance_id, transport, wire, Error, Link, RemoteStats, Result};
use crate::clock::{Clock, SystemClock};
use crate::model::{ModelInput, VelocityModel};

/// Settings of [`serve_policy`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolicyServerConfig {
    /// Where to listen / connect (default: listen on `tcp/127.0.0.1:7447`).
    pub link: Link,
    /// Key the requests arrive on.
    pub key: String,
    /// Extra delay before each reply: a stand-in for a slow network in tests and
    /// measurements (zero in deployment).
    pub reply_delay: Duration,
}

impl Default for PolicyServerConfig {
    fn default() -> Self {
        Self {
            link: Link::listen("tcp/127.0.0.1:7447"),
            key: "pir2/policy".into(),
            reply_delay: Duration::ZERO,
        }
    }
}

fn key(k: &str) -> Result<KeyExpr<'static>> {
    KeyExpr::try_from(k.to_string()).map_err(|e| Error::Config(format!("key `{k}`: {e}")))
}

/// Answer requests with `model` until `stop` is set (checked every 20 ms). A request that
/// does not decode, or a model error, is answered with an error message (the caller gets a
/// typed error) and serving goes on. Pings are answered (liveness).
pub fn serve_policy<M: VelocityModel>(
    mut model: M,
    cfg: &PolicyServerConfig,
    stop: Arc<AtomicBool>,
) -> Result<()> {
    let me = instance_id();
    let clock = SystemClock::new();
    let session = cfg.link.open()?;
    let queryable = session
        .declare_queryable(key(&cfg.key)?)
        .wait()
        .map_err(transport("declare queryable"))?;
    let mut v = Vec::new();
    while !stop.load(Ordering::Acquire) {
        let q = match queryable.recv_timeout(Duration::from_millis(20)) {
            Ok(Some(q)) => q,
            Ok(None) => continue,
            Err(e) => return Err(transport("receive requests")(e)),
        };
        let t_recv = clock.now();
        let Some(bytes) = q.payload().map(|p| p.to_bytes()) else {
            continue;
        };
        let reply = match wire::decode_header(&bytes) {
            Err(e) => wire::encode_error(me, 0, &e.to_string()),
            Ok((h, _)) if h.kind == wire::Kind::Ping => wire::encode_pong(me, &h, t_recv),
            Ok((h, _)) => match answer(&mut model, &bytes, &mut v) {
                Ok((req, shape)) => {
                    wire::encode_reply(me, &req, clock.now().saturating_sub(t_recv), shape, &v)
                }
                Err(e) => wire::encode_error(me, h.seq, &e.to_string()),
            },
        };
        if !cfg.reply_delay.is_zero() {
            std::thread::sleep(cfg.reply_delay);
        }
        q.reply(q.key_expr().clone(), reply)
            .wait()
            .map_err(transport("reply"))?;
    }
    drop(queryable);
    session.close().wait().map_err(transport("close"))?;
    Ok(())
}

fn answer<M: VelocityModel>(
    model: &mut M,
    bytes: &[u8],
    v: &mut Vec<f32>,
) -> Result<(wire::Header, [usize; 3])> {
    let req = wire::decode_request(bytes)?;
    let input = req.input();
    input.validate()?;
    let shape = [req.batch, req.horizon, req.action_dim];
    v.clear();
    v.resize(shape.iter().product(), 0.0);
    model.velocity(&input, v)?;
    Ok((req.header, shape))
}

/// Settings of [`RemoteModel`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RemoteModelConfig {
    /// Where the policy server is (default: connect to `tcp/127.0.0.1:7447`).
    pub link: Link,
    /// The server's key.
    pub key: String,
    /// How long one request may take before it counts as failed and is sent again.
    pub timeout: Duration,
    /// Consecutive failed requests before the call gives up with a safety stop.
    pub max_failed_calls: u32,
    /// How long [`RemoteModel::connect`] waits for the server to answer a ping.
    pub connect_timeout: Duration,
}

impl Default for RemoteModelConfig {
    fn default() -> Self {
        Self {
            link: Link::connect("tcp/127.0.0.1:7447"),
            key: "pir2/policy".into(),
            timeout: Duration::from_millis(200),
            max_failed_calls: 10,
            connect_timeout: Duration::from_secs(10),
        }
    }
}

/// A [`VelocityModel`] served by [`serve_policy`] on another machine.
///
/// Each call sends the request and waits up to [`RemoteModelConfig::timeout`]; without a
/// reply it sends the same request again (the control thread meanwhile runs the overrun
/// path), and after [`RemoteModelConfig::max_failed_calls`] consecutive failures it returns
/// [`Error::ServerGone`] (→ [`crate::Error::SafetyStop`]). The real-time worker measures
/// the whole call, retries included, so `d` reflects the network honestly.
pub struct RemoteModel {
    session: zenoh::Session,
    key: KeyExpr<'static>,
    cfg: RemoteModelConfig,
    clock: Arc<dyn Clock>,
    me: u64,
    seq: u64,
    failing: bool,
    stats: Arc<RemoteStats>,
}

impl std::fmt::Debug for RemoteModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemoteModel")
            .field("key", &self.cfg.key)
            .field("stats", &self.stats.counters())
            .finish_non_exhaustive()
    }
}

impl RemoteModel {
    /// Open a session and wait (up to `connect_timeout`) until the server answers a ping.
    pub fn connect(cfg: RemoteModelConfig) -> Result<Self> {
        if cfg.timeout.is_zero() || cfg.max_failed_calls == 0 {
            return Err(Error::Config(
                "timeout and max_failed_calls must be positive".into(),
            ));
        }
        let key = key(&cfg.key)?;
        let session = cfg.link.open()?;
        let me = instance_id();
        let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
        let until = Instant::now() + cfg.connect_timeout;
        loop {
            let t0 = Instant::now();
            let ping = wire::encode_ping(me, 0, clock.now());
            if let Some(bytes) = query(&session, &key, ping.into(), cfg.timeout)? {
                wire::decode_pong(&bytes)?;
                break;
            }
            if Instant::now() >= until {
                return Err(Error::Timeout {
                    what: "policy server (ping)",
                    after: cfg.connect_timeout,
                });
            }
            // No queryable yet: the query may return at once; pace the retries.
            std::thread::sleep(Duration::from_millis(20).saturating_sub(t0.elapsed()));
        }
        Ok(Self {
            session,
            key,
            cfg,
            clock,
            me,
            seq: 0,
            failing: false,
            stats: Arc::new(RemoteStats::default()),
        })
    }

    /// Measure round trips on `clock` (default: a [`SystemClock`]).
    pub fn with_clock(mut self, clock: Arc<dyn Clock>) -> Self {
        self.clock = clock;
        self
    }

    /// The counters (calls, attempts, timeouts, reconnects, failed calls, last RTT).
    pub fn stats(&self) -> Arc<RemoteStats> {
        self.stats.clone()
    }

    /// One call with the typed error (see the type docs for retries and the safety stop).
    pub fn call(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        input.validate()?;
        let want = [input.batch, input.horizon, input.action_dim];
        if out.len() != want.iter().product::<usize>() {
            return Err(crate::Error::shape("v [B,H,A]", want, out.len()).into());
        }
        bump(&self.stats.calls);
        self.seq += 1;
        let t_send = self.clock.now();
        let payload: zenoh::bytes::ZBytes =
            wire::encode_request(self.me, self.seq, t_send, input).into();
        let mut failed = 0u32;
        loop {
            bump(&self.stats.attempts);
            let t0 = Instant::now();
            match query(&self.session, &self.key, payload.clone(), self.cfg.timeout)? {
                Some(bytes) => {
                    return match wire::decode_reply(&bytes)? {
                        wire::Reply::Error(m) => {
                            bump(&self.stats.server_errors);
                            Err(Error::Server(m))
                        }
                        wire::Reply::Velocity { header, shape, v } => {
                            if header.seq != self.seq || shape != want {
                                return Err(Error::Mismatch(format!(
                                    "reply seq {} shape {shape:?} for request seq {} shape {want:?}",
                                    header.seq, self.seq
                                )));
                            }
                            out.copy_from_slice(&v);
                            if self.failing {
                                self.failing = false;
                                bump(&self.stats.reconnects);
                            }
                            self.stats.last_rtt_ns.store(
                                self.clock.now().saturating_sub(t_send),
                                std::sync::atomic::Ordering::Relaxed,
                            );
                            Ok(())
                        }
                    };
                }
                None => {
                    bump(&self.stats.timeouts);
                    self.failing = true;
                    failed += 1;
                    if failed >= self.cfg.max_failed_calls {
                        bump(&self.stats.failed_calls);
                        return Err(Error::ServerGone {
                            failed,
                            timeout: self.cfg.timeout,
                        });
                    }
                    // A missing server answers "no reply" at once: wait out the timeout so
                    // `max_failed_calls × timeout` is the time to the safety stop.
                    std::thread::sleep(self.cfg.timeout.saturating_sub(t0.elapsed()));
                }
            }
        }
    }
}

impl VelocityModel for RemoteModel {
    fn backend(&self) -> &'static str {
        "remote"
    }
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> crate::Result<()> {
        self.call(input, out).map_err(Into::into)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::SlowInput;
    use crate::remote::slow::{RemoteSlowConfig, RemoteSlowSource};
    use crate::remote::wire::{Header, Kind, WireError, Writer};

    fn free_endpoint() -> String {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        format!("tcp/127.0.0.1:{}", l.local_addr().unwrap().port())
    }

    fn v2(kind: Kind) -> Vec<u8> {
        let h = Header {
            kind,
            sender: 1,
            seq: 1,
            t_a: 0,
            t_b: 0,
        };
        Writer::with_version(h, 0, 0, WIRE_VERSION_NEXT).finish()
    }

    const WIRE_VERSION_NEXT: u16 = wire::WIRE_VERSION + 1;

    #[test]
    fn version_mismatch_from_a_policy_server_is_a_typed_error() {
        let ep = free_endpoint();
        let server = Link::listen(ep.clone()).open().unwrap();
        let q = server.declare_queryable("t/policy").wait().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let s = stop.clone();
        // A server that answers pings in v1 but requests in v2 (a newer build).
        let fake = std::thread::spawn(move || {
            while !s.load(Ordering::Acquire) {
                let Ok(Some(q)) = q.recv_timeout(Duration::from_millis(20)) else {
                    continue;
                };
                let bytes = q.payload().map(|p| p.to_bytes().into_owned()).unwrap();
                let (h, _) = wire::decode_header(&bytes).unwrap();
                let reply = if h.kind == Kind::Ping {
                    wire::encode_pong(1, &h, 0)
                } else {
                    v2(Kind::PolicyReply)
                };
                q.reply(q.key_expr().clone(), reply).wait().unwrap();
            }
        });
        let mut m = RemoteModel::connect(RemoteModelConfig {
            link: Link::connect(ep),
            key: "t/policy".into(),
            timeout: Duration::from_secs(2),
            connect_timeout: Duration::from_secs(5),
            ..Default::default()
        })
        .unwrap();
        let (x, tau, obs, dv) = (vec![0.0; 6], vec![0.0; 3], vec![0.0; 4], [0u32]);
        let input = ModelInput {
            batch: 1,
            horizon: 3,
            action_dim: 2,
            x: &x,
            tau: &tau,
            obs_fast: &obs,
            n_obs: 1,
            fast_dim: 4,
            slow: SlowInput::None,
            d_vis: &dv,
        };
        let mut out = vec![0.0; 6];
        let err = m.call(&input, &mut out).unwrap_err();
        stop.store(true, Ordering::Release);
        fake.join().unwrap();
        assert!(
            matches!(
                err,
                Error::Wire(WireError::Version {
                    got: WIRE_VERSION_NEXT,
                    expected: wire::WIRE_VERSION
                })
            ),
            "{err}"
        );
        // Not retried: a version mismatch cannot heal.
        assert_eq!(m.stats().counters().attempts, 1);
        let e: crate::Error = err.into();
        assert!(e.to_string().contains("wire version mismatch"), "{e}");
    }

    #[test]
    fn version_mismatch_on_the_slow_channel_is_a_typed_error() {
        let ep = free_endpoint();
        let server = Link::listen(ep.clone()).open().unwrap();
        let publisher = server.declare_publisher("t/slow").wait().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let s = stop.clone();
        let fake = std::thread::spawn(move || {
            while !s.load(Ordering::Acquire) {
                publisher.put(v2(Kind::Features)).wait().unwrap();
                std::thread::sleep(Duration::from_millis(10));
            }
        });
        let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
        let mut src = RemoteSlowSource::connect(
            RemoteSlowConfig {
                link: Link::connect(ep),
                key: "t/slow".into(),
                first_timeout: Duration::from_secs(5),
                ..Default::default()
            },
            clock,
        )
        .unwrap();
        let err = src.next().unwrap_err();
        stop.store(true, Ordering::Release);
        fake.join().unwrap();
        assert!(
            matches!(
                err,
                Error::Wire(WireError::Version {
                    got: WIRE_VERSION_NEXT,
                    ..
                })
            ),
            "{err}"
        );
    }
}
