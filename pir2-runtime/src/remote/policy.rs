//! The remote action head: `serve_policy` answers one-NFE requests with a local model;
//! `RemoteModel` is the robot's `VelocityModel` that forwards each call.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use zenoh::key_expr::KeyExpr;
use zenoh::Wait;

use super::clock_sync::query_each;
use super::wire::SessionToken;
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
    /// Requests larger than this are refused before they are decoded (bytes).
    #[serde(default = "default_max_request_bytes")]
    pub max_request_bytes: usize,
    /// Requests with a larger batch are refused before the model runs.
    #[serde(default = "default_max_batch")]
    pub max_batch: usize,
    /// What the server runs (e.g. the checkpoint's identity), sent with every pong so a
    /// client can refuse a server running another model ([`RemoteModel::server_identity`]).
    #[serde(default)]
    pub identity: Option<String>,
}

/// 64 MiB: a GR00T-sized request (a few hundred VL tokens × 2048 floats per sample) fits
/// many times over.
fn default_max_request_bytes() -> usize {
    64 << 20
}

fn default_max_batch() -> usize {
    64
}

impl Default for PolicyServerConfig {
    fn default() -> Self {
        Self {
            link: Link::listen("tcp/127.0.0.1:7447"),
            key: "pir2/policy".into(),
            reply_delay: Duration::ZERO,
            max_request_bytes: default_max_request_bytes(),
            max_batch: default_max_batch(),
            identity: None,
        }
    }
}

/// Counters of a policy server (relaxed atomics; read them with [`Self::counters`]).
#[derive(Debug, Default)]
pub struct PolicyServerStats {
    requests: AtomicU64,
    answered: AtomicU64,
    oversized: AtomicU64,
    too_large_batch: AtomicU64,
    malformed: AtomicU64,
    model_errors: AtomicU64,
    model_panics: AtomicU64,
    reply_failures: AtomicU64,
    no_session: AtomicU64,
}

/// A snapshot of [`PolicyServerStats`]. Every request that was not answered with
/// velocities was answered with an error message naming why, and counted here.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PolicyServerCounters {
    /// Queries received (pings included).
    pub requests: u64,
    /// Requests answered with velocities.
    pub answered: u64,
    /// Refused before decoding: larger than `max_request_bytes`.
    pub oversized: u64,
    /// Refused: batch larger than `max_batch`.
    pub too_large_batch: u64,
    /// Could not be decoded (bad magic, version, kind, shapes...).
    pub malformed: u64,
    /// The model returned an error (e.g. shapes it does not take).
    pub model_errors: u64,
    /// The model panicked; the server answered with an error and kept serving.
    pub model_panics: u64,
    /// A reply could not be sent (the client went away); the server kept serving.
    pub reply_failures: u64,
    /// Refused: the client has no session with this server instance (it never pinged this
    /// instance, e.g. the server restarted); the client shakes hands again.
    #[serde(default)]
    pub no_session: u64,
}

impl PolicyServerStats {
    /// Read every counter.
    pub fn counters(&self) -> PolicyServerCounters {
        let r = |a: &AtomicU64| a.load(Ordering::Relaxed);
        PolicyServerCounters {
            requests: r(&self.requests),
            answered: r(&self.answered),
            oversized: r(&self.oversized),
            too_large_batch: r(&self.too_large_batch),
            malformed: r(&self.malformed),
            model_errors: r(&self.model_errors),
            model_panics: r(&self.model_panics),
            reply_failures: r(&self.reply_failures),
            no_session: r(&self.no_session),
        }
    }
}

fn key(k: &str) -> Result<KeyExpr<'static>> {
    KeyExpr::try_from(k.to_string()).map_err(|e| Error::Config(format!("key `{k}`: {e}")))
}

/// Answer requests with `model` until `stop` is set (checked every 20 ms). A request that
/// does not decode, or a model error, is answered with an error message (the caller gets a
/// typed error) and serving goes on. Pings are answered (liveness) and are the handshake:
/// each pong issues the pinging client a fresh [`SessionToken`] that every later reply to
/// that client carries; a request from a client without one is refused (it pings again).
pub fn serve_policy<M: VelocityModel>(
    model: M,
    cfg: &PolicyServerConfig,
    stop: Arc<AtomicBool>,
) -> Result<()> {
    serve_policy_counted(model, cfg, stop, Arc::new(PolicyServerStats::default()))
}

/// [`serve_policy`], counting into `stats` (e.g. to print them when the server stops).
///
/// A bad request never ends the server: one larger than
/// [`PolicyServerConfig::max_request_bytes`] is refused before decoding, one that does not
/// decode or has a batch over [`PolicyServerConfig::max_batch`] is refused after, a model
/// error or panic is answered with an error, and a reply that cannot be sent is dropped;
/// each is counted. Only a failure of the server's own session ends it.
pub fn serve_policy_counted<M: VelocityModel>(
    mut model: M,
    cfg: &PolicyServerConfig,
    stop: Arc<AtomicBool>,
    stats: Arc<PolicyServerStats>,
) -> Result<()> {
    if cfg.max_request_bytes == 0 || cfg.max_batch == 0 {
        return Err(Error::Config(
            "max_request_bytes and max_batch must be positive".into(),
        ));
    }
    let me = instance_id();
    let clock = SystemClock::new();
    let session = cfg.link.open()?;
    let queryable = session
        .declare_queryable(key(&cfg.key)?)
        .wait()
        .map_err(transport("declare queryable"))?;
    let mut v = Vec::new();
    let mut sessions = std::collections::HashMap::<u64, SessionToken>::new();
    while !stop.load(Ordering::Acquire) {
        let q = match queryable.recv_timeout(Duration::from_millis(20)) {
            Ok(Some(q)) => q,
            Ok(None) => continue,
            Err(e) => return Err(transport("receive requests")(e)),
        };
        let t_recv = clock.now();
        bump(&stats.requests);
        let size = q.payload().map_or(0, |p| p.len());
        let reply = if size > cfg.max_request_bytes {
            bump(&stats.oversized);
            // Only the header is read: the refusal goes to the client it names.
            let mut head = [0u8; wire::HEADER_LEN];
            let header = q
                .payload()
                .and_then(|p| std::io::Read::read_exact(&mut p.reader(), &mut head).ok())
                .and_then(|()| wire::decode_header(&head).ok())
                .map(|(h, _)| h);
            wire::encode_error_with_token(
                me,
                header.map_or(0, |h| h.seq),
                &format!(
                    "request of {size} bytes refused: the server takes at most {} bytes",
                    cfg.max_request_bytes
                ),
                header.and_then(|h| sessions.get(&h.sender).copied()),
            )
        } else {
            let bytes = q.payload().map(|p| p.to_bytes()).unwrap_or_default();
            match wire::decode_header(&bytes) {
                Err(e) => {
                    bump(&stats.malformed);
                    wire::encode_error(me, 0, &e.to_string())
                }
                Ok((h, _)) if h.kind == wire::Kind::Ping => {
                    // A client that floods pings with made-up ids cannot grow this without
                    // bound; the clients it forgets ping again.
                    if sessions.len() >= MAX_SESSIONS && !sessions.contains_key(&h.sender) {
                        sessions.clear();
                    }
                    let token = session_token();
                    sessions.insert(h.sender, token);
                    wire::encode_pong_with_token(
                        me,
                        &h,
                        t_recv,
                        cfg.identity.as_deref(),
                        Some(token),
                    )
                }
                Ok((h, _)) => match sessions.get(&h.sender).copied() {
                    None => {
                        bump(&stats.no_session);
                        wire::encode_error(
                            me,
                            h.seq,
                            "no session with this server instance: ping it first (handshake)",
                        )
                    }
                    Some(token) => match answer(&mut model, &bytes, &mut v, cfg.max_batch) {
                        Ok((req, shape)) => {
                            bump(&stats.answered);
                            let took = clock.now().saturating_sub(t_recv);
                            wire::encode_reply_with_token(me, &req, took, shape, &v, Some(token))
                        }
                        Err(refused) => {
                            bump(match refused {
                                Refused::Malformed(_) => &stats.malformed,
                                Refused::Batch(_) => &stats.too_large_batch,
                                Refused::Model(_) => &stats.model_errors,
                                Refused::Panic(_) => &stats.model_panics,
                            });
                            wire::encode_error_with_token(
                                me,
                                h.seq,
                                &refused.to_string(),
                                Some(token),
                            )
                        }
                    },
                },
            }
        };
        if !cfg.reply_delay.is_zero() {
            std::thread::sleep(cfg.reply_delay);
        }
        if q.reply(q.key_expr().clone(), reply).wait().is_err() {
            bump(&stats.reply_failures);
        }
    }
    drop(queryable);
    session.close().wait().map_err(transport("close"))?;
    Ok(())
}

/// Clients a policy server keeps session tokens for (then it forgets them all at once).
const MAX_SESSIONS: usize = 4096;

/// 128 unpredictable bits: std's randomly keyed SipHash (keys from the OS) over the time,
/// the process and a counter.
fn session_token() -> SessionToken {
    use std::hash::{BuildHasher, Hasher};
    static N: AtomicU64 = AtomicU64::new(0);
    let half = || {
        let mut h = std::collections::hash_map::RandomState::new().build_hasher();
        h.write_u64(N.fetch_add(1, Ordering::Relaxed));
        h.write_u64(instance_id());
        h.finish()
    };
    let (a, b) = (half(), half());
    [a as u32, (a >> 32) as u32, b as u32, (b >> 32) as u32]
}

/// What answered one handshake ping.
enum Handshake {
    /// Nobody (in time).
    Nobody,
    /// Exactly one server: its pong.
    One(wire::Pong),
    /// More than one peer answered: the client cannot tell which is its server.
    Many(usize),
}

/// Ping `key` and gather every pong until all responders answered or `timeout` passed.
/// Pongs without a session token (not a policy server of this version) are not counted.
fn handshake(
    session: &zenoh::Session,
    key: &KeyExpr<'static>,
    me: u64,
    seq: u64,
    clock: &dyn Clock,
    timeout: Duration,
) -> Result<Handshake> {
    let t0 = clock.now();
    let ping = wire::encode_ping(me, seq, t0);
    let mut pongs = Vec::new();
    query_each::<()>(session, key, ping.into(), timeout, |bytes| {
        match wire::decode_pong_full(bytes) {
            Ok(p) if p.header.t_a == t0 && p.header.seq == seq && p.token.is_some() => {
                pongs.push(p)
            }
            Ok(_) => {}
            Err(e @ wire::WireError::Version { .. }) => return Err(e.into()),
            Err(_) => {}
        }
        Ok(None)
    })?;
    Ok(match pongs.len() {
        0 => Handshake::Nobody,
        1 => Handshake::One(pongs.remove(0)),
        n => Handshake::Many(n),
    })
}

/// Why a request got an error instead of velocities.
enum Refused {
    Malformed(String),
    Batch(String),
    Model(String),
    Panic(String),
}

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refused::Malformed(m) | Refused::Batch(m) | Refused::Model(m) => f.write_str(m),
            Refused::Panic(m) => write!(f, "the model panicked: {m}"),
        }
    }
}

fn answer<M: VelocityModel>(
    model: &mut M,
    bytes: &[u8],
    v: &mut Vec<f32>,
    max_batch: usize,
) -> std::result::Result<(wire::Header, [usize; 3]), Refused> {
    let req = wire::decode_request(bytes).map_err(|e| Refused::Malformed(e.to_string()))?;
    if req.batch > max_batch {
        return Err(Refused::Batch(format!(
            "batch of {} refused: the server takes at most {max_batch}",
            req.batch
        )));
    }
    let input = req.input();
    input
        .validate()
        .map_err(|e| Refused::Malformed(e.to_string()))?;
    let shape = [req.batch, req.horizon, req.action_dim];
    v.clear();
    v.resize(shape.iter().product(), 0.0);
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| model.velocity(&input, v))) {
        Ok(Ok(())) => Ok((req.header, shape)),
        Ok(Err(e)) => Err(Refused::Model(e.to_string())),
        Err(p) => Err(Refused::Panic(crate::error::panic_message(&*p))),
    }
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
/// Trust: [`RemoteModel::connect`] pings the server (the handshake) and pins the peer that
/// answered through the session token its pong issued; afterwards only replies carrying
/// that token are used. Replies from anyone else on the key (another responder, a restarted
/// server the client has not shaken hands with yet) are dropped and counted in
/// [`RemoteCounters::foreign_replies`](super::RemoteCounters::foreign_replies). After an
/// attempt that got only such replies the client pings again: a single answering server
/// with the same identity as at connect is pinned (a restart), another identity ends the
/// call ([`Error::IdentityChanged`], a safety stop), several answering peers pin nobody
/// ([`Error::Ambiguous`] at connect). Limit: without TLS, a peer that answers the very
/// first handshake alone cannot be told from the server; with mutual TLS only peers with a
/// certificate of the user's CA can answer at all.
///
/// Each call sends the request and waits up to [`RemoteModelConfig::timeout`]; without a
/// reply it sends the same request again (the control thread meanwhile runs the overrun
/// path), and after [`RemoteModelConfig::max_failed_calls`] consecutive failures it returns
/// [`Error::ServerGone`] (→ [`crate::Error::SafetyStop`]). A reply that cannot be used
/// (malformed, or velocities for another request) is dropped, counted in
/// [`RemoteCounters::malformed`](super::RemoteCounters::malformed) and counts as a failed
/// attempt ([`Error::Unusable`] at the limit, also a safety stop); a reply from a peer of
/// another wire version is an error at once. The real-time worker measures
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
    server_identity: Option<String>,
    /// The session token of the last handshake: only replies carrying it are used.
    token: SessionToken,
    handshakes: u64,
    /// The run's stop signal ([`VelocityModel::watch_stop`]): retries end once it is raised.
    stop: Option<crate::StopSignal>,
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
        let mut handshakes = 0;
        let (server_identity, token) = loop {
            let t0 = Instant::now();
            handshakes += 1;
            match handshake(&session, &key, me, handshakes, &*clock, cfg.timeout)? {
                Handshake::One(p) => break (p.identity, p.token.unwrap_or_default()),
                Handshake::Many(n) => {
                    return Err(Error::Ambiguous {
                        key: cfg.key.clone(),
                        responders: n,
                    })
                }
                Handshake::Nobody => {}
            }
            if Instant::now() >= until {
                return Err(cfg.link.no_answer(
                    &session,
                    "policy server (ping)",
                    cfg.connect_timeout,
                ));
            }
            // No queryable yet: the query may return at once; pace the retries.
            std::thread::sleep(Duration::from_millis(20).saturating_sub(t0.elapsed()));
        };
        Ok(Self {
            session,
            key,
            cfg,
            clock,
            me,
            seq: 0,
            failing: false,
            stats: Arc::new(RemoteStats::default()),
            server_identity,
            token,
            handshakes,
            stop: None,
        })
    }

    /// Shake hands again after an attempt that got only foreign replies (e.g. the server
    /// restarted and refuses the old session): pin a single answering server of the same
    /// identity; several answering peers pin nobody (counted as foreign replies).
    fn handshake_again(&mut self) -> Result<()> {
        self.handshakes += 1;
        let timeout = self.cfg.timeout;
        match handshake(
            &self.session,
            &self.key,
            self.me,
            self.handshakes,
            &*self.clock,
            timeout,
        )? {
            Handshake::One(p) if p.identity == self.server_identity => {
                self.token = p.token.unwrap_or_default();
            }
            Handshake::One(p) => {
                bump(&self.stats.failed_calls);
                return Err(Error::IdentityChanged {
                    key: self.cfg.key.clone(),
                    expected: self.server_identity.clone(),
                    got: p.identity,
                });
            }
            Handshake::Many(n) => {
                self.stats
                    .foreign_replies
                    .fetch_add(n as u64, Ordering::Relaxed);
            }
            Handshake::Nobody => {}
        }
        Ok(())
    }

    /// The identity the server announced when it answered the connecting ping
    /// ([`PolicyServerConfig::identity`]; `None` for a server that announces none).
    pub fn server_identity(&self) -> Option<&str> {
        self.server_identity.as_deref()
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
            let (seq, token, stats) = (self.seq, self.token, &*self.stats);
            let (mut foreign, mut unusable) = (0u64, None::<String>);
            let got = query_each(
                &self.session,
                &self.key,
                payload.clone(),
                self.cfg.timeout,
                |bytes| match wire::decode_reply_with_token(bytes) {
                    // A peer of another wire version cannot heal by retrying.
                    Err(e @ wire::WireError::Version { .. }) => Err(e.into()),
                    Err(e) => {
                        bump(&stats.malformed);
                        unusable = Some(e.to_string());
                        Ok(None)
                    }
                    // Not from the peer of the last handshake: never used.
                    Ok((_, t)) if t != Some(token) => {
                        bump(&stats.foreign_replies);
                        foreign += 1;
                        Ok(None)
                    }
                    Ok((wire::Reply::Error(m), _)) => Ok(Some(Err(m))),
                    Ok((wire::Reply::Velocity { header, shape, v }, _))
                        if header.seq == seq && shape == want =>
                    {
                        Ok(Some(Ok(v)))
                    }
                    Ok((wire::Reply::Velocity { header, shape, .. }, _)) => {
                        bump(&stats.malformed);
                        unusable = Some(format!(
                            "reply seq {} shape {shape:?} for request seq {seq} shape {want:?}",
                            header.seq
                        ));
                        Ok(None)
                    }
                },
            )?;
            match got {
                Some(Err(m)) => {
                    bump(&self.stats.server_errors);
                    return Err(Error::Server(m));
                }
                Some(Ok(v)) => {
                    out.copy_from_slice(&v);
                    if self.failing {
                        self.failing = false;
                        bump(&self.stats.reconnects);
                    }
                    self.stats.last_rtt_ns.store(
                        self.clock.now().saturating_sub(t_send),
                        std::sync::atomic::Ordering::Relaxed,
                    );
                    return Ok(());
                }
                None => {}
            }
            // No usable reply from our server in this attempt.
            self.failing = true;
            failed += 1;
            if unusable.is_none() {
                bump(&self.stats.timeouts);
            }
            if failed >= self.cfg.max_failed_calls {
                bump(&self.stats.failed_calls);
                return Err(match unusable {
                    // Dropped and counted; each counted as a failed attempt, like no reply.
                    Some(last) => Error::Unusable { failed, last },
                    None => Error::ServerGone {
                        failed,
                        timeout: self.cfg.timeout,
                    },
                });
            }
            if self.stop.as_ref().is_some_and(|s| s.is_raised()) {
                // The run is stopping (the robot is already stopped): retrying would only
                // hold its exit for up to `max_failed_calls × timeout`.
                bump(&self.stats.abandoned);
                return Err(Error::Runtime(crate::Error::Abandoned));
            }
            if foreign > 0 {
                self.handshake_again()?;
            }
            // A missing server answers "no reply" at once: wait out the timeout so
            // `max_failed_calls × timeout` is the time to the safety stop.
            std::thread::sleep(self.cfg.timeout.saturating_sub(t0.elapsed()));
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
    fn watch_stop(&mut self, stop: crate::StopSignal) {
        self.stop = Some(stop);
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
                    wire::encode_pong_with_token(1, &h, 0, None, Some([1, 2, 3, 4]))
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
