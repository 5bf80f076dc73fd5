//! The slow channel and the action head across machines, over Zenoh (feature `remote`).
//!
//! ```text
//!  robot (realtime::run)                               servers
//!  slow worker ── RemoteSlowSource ◄── pub/sub ──────── serve_slow(source, encoder)
//!              (clock offset: ping/pong, min RTT)  ◄──── (pong on `<key>/clock`)
//!  action worker ─ RemoteModel ────── query/reply ────► serve_policy(model)
//! ```
//!
//! - [`serve_slow`] publishes backbone features with their capture time on the server's
//!   clock. The robot's [`RemoteSlowSource`] subscribes, estimates the clock offset with an
//!   NTP-style ping/pong exchange (the sample with the smallest round trip wins, accuracy
//!   ±RTT/2), converts the capture time into the robot's clock and feeds the runtime's slow
//!   cache through [`RemoteSlowEncoder`] (identity). `d_vis` therefore includes the backbone
//!   time, the transport delay and the offset error.
//! - [`serve_policy`] answers one-NFE requests with any local [`crate::VelocityModel`];
//!   [`RemoteModel`] is a `VelocityModel` that sends the request and waits for the reply.
//!   The real-time worker measures each call, so the round trip lands in the latency
//!   window and `d` grows with the network.
//!
//! Security: endpoints `tls/HOST:PORT` run mutual TLS with the user's CA ([`Link::tls`],
//! [`TlsFiles`]): both sides present a certificate signed by that CA and verify the other's,
//! and a connecting side checks that the server's certificate names the host it dialled.
//! [`Link::check_exposure`] refuses to listen beyond this machine without TLS unless the
//! user accepts the risk explicitly (`pir2 serve --insecure`). TLS files are checked before a
//! session opens and a refused TLS handshake is reported as such ([`Error::Tls`]).
//!
//! Trust in the peer: a client uses only replies of the peer it shook hands with. The policy
//! client pins the [`wire::SessionToken`] the server's pong issued and drops (and counts in
//! [`RemoteCounters::foreign_replies`]) every reply without it; a restarted server is used
//! only after a new handshake with the same identity. The slow client pins the server
//! instance it synchronised its clock with and drops features of any other instance while
//! that one keeps publishing. Limit: without TLS, a peer that answers the very first
//! handshake alone (before the real server is up), or that publishes alone after the real
//! slow server went quiet, cannot be told from the server; with mutual TLS only peers holding
//! a certificate of the user's CA can answer at all.
//!
//! Faults (see `docs/remote-faults.md` for the measured behaviour):
//! - a message larger than [`Link::max_message_bytes`] is dropped by the transport before it
//!   is reassembled; a policy request over [`PolicyServerConfig::max_request_bytes`] or
//!   [`PolicyServerConfig::max_batch`] is refused with an error reply; a message that does
//!   not decode is dropped and counted ([`PolicyServerCounters`], [`RemoteCounters::malformed`]).
//!   None of these ends a server or a run by itself (a policy call still stops the robot
//!   after [`RemoteModelConfig::max_failed_calls`] unusable replies in a row);
//! - slow server gone: [`RemoteSlowSource`] hands the last features again (same capture
//!   time) every [`RemoteSlowConfig::stale_poll`], so `d_vis` keeps growing; the head's
//!   stale-slow check ([`crate::head::ActionHead::set_slow_grace`]) stops the robot with
//!   [`crate::Error::SafetyStop`] once the features are older than `d_vis_max` ticks for
//!   longer than the grace period. A restarted server (new sender id) is detected, the
//!   clock offset is estimated again, and the features resume;
//! - policy server gone: a call that gets no reply within [`RemoteModelConfig::timeout`]
//!   is retried (same snapshot) while the control thread runs the overrun path (`x̂`, then
//!   holds); after [`RemoteModelConfig::max_failed_calls`] consecutive failures the call
//!   returns [`Error::ServerGone`], a safety stop. A reply after failures counts a
//!   reconnect; nothing on the robot side restarts.
//!
//! Every event is counted in a shared [`RemoteStats`] (read it after a run with
//! [`RemoteStats::counters`]). The control thread never touches Zenoh: only the slow and
//! action workers block on it, through Zenoh's synchronous `wait()` API.

mod clock_sync;
mod policy;
mod slow;
pub mod wire;

use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::time::Duration;

use serde::{Deserialize, Serialize};

pub use clock_sync::{estimate_offset, ClockOffset, OffsetSample};
pub use policy::{
    serve_policy, serve_policy_counted, PolicyServerConfig, PolicyServerCounters,
    PolicyServerStats, RemoteModel, RemoteModelConfig,
};
pub use slow::{
    remote_slow_channel, serve_slow, RemoteSlowConfig, RemoteSlowEncoder, RemoteSlowSource,
    SlowServerConfig,
};
pub use wire::{WireError, WIRE_VERSION};

/// Errors of the remote channels.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A message could not be decoded (version mismatch, malformed, wrong kind).
    #[error(transparent)]
    Wire(#[from] WireError),
    /// Zenoh failed (open, declare, send).
    #[error("zenoh {what}: {message}")]
    Transport {
        /// What was being done.
        what: &'static str,
        /// Zenoh's message.
        message: String,
    },
    /// Nothing arrived in time.
    #[error("{what}: no answer within {after:?}")]
    Timeout {
        /// What was awaited.
        what: &'static str,
        /// The timeout.
        after: Duration,
    },
    /// The policy server answered with an error.
    #[error("policy server error: {0}")]
    Server(String),
    /// The policy server did not answer `failed` calls in a row: stop the robot.
    #[error("policy server unreachable: {failed} consecutive calls timed out after {timeout:?}")]
    ServerGone {
        /// Consecutive failed attempts.
        failed: u32,
        /// Timeout per attempt.
        timeout: Duration,
    },
    /// The policy server's replies could not be used `failed` times in a row (malformed,
    /// or answering another request): stop the robot.
    #[error("policy server: {failed} replies in a row were unusable (last: {last})")]
    Unusable {
        /// Consecutive unusable replies.
        failed: u32,
        /// Why the last one was unusable.
        last: String,
    },
    /// More than one peer answered the handshake on a key: the client cannot tell which one
    /// is its server and pins none.
    #[error(
        "{responders} peers answered the handshake on `{key}`: refusing to pick one (another \
         server, or an impostor, answers on the same key; use mutual TLS or another key)"
    )]
    Ambiguous {
        /// The key.
        key: String,
        /// How many answered.
        responders: usize,
    },
    /// The server that answered a new handshake (e.g. after a restart) announces another
    /// identity than the one the client connected to: stop the robot.
    #[error(
        "the policy server on `{key}` now announces identity {got:?}, not {expected:?} as when \
         the client connected: its replies are not used"
    )]
    IdentityChanged {
        /// The key.
        key: String,
        /// The identity announced at connect.
        expected: Option<String>,
        /// The identity announced now.
        got: Option<String>,
    },
    /// TLS failed: a certificate or key file that cannot be used, or a handshake the peer
    /// refused (what was wrong, and the usual causes).
    #[error("TLS: {0}")]
    Tls(String),
    /// Invalid configuration.
    #[error("invalid remote configuration: {0}")]
    Config(String),
    /// A runtime error (a model, source or encoder on the server side).
    #[error(transparent)]
    Runtime(#[from] crate::Error),
}

/// Result alias of this module.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl From<Error> for crate::Error {
    fn from(e: Error) -> Self {
        match e {
            Error::Runtime(e) => e,
            Error::ServerGone { .. } | Error::Unusable { .. } | Error::IdentityChanged { .. } => {
                crate::Error::SafetyStop(e.to_string())
            }
            Error::Server(m) => crate::Error::Model(format!("remote: {m}")),
            Error::Config(m) => crate::Error::Config(m),
            other => crate::Error::io("remote", other),
        }
    }
}

pub(crate) fn transport(what: &'static str) -> impl FnOnce(zenoh::Error) -> Error {
    move |e| Error::Transport {
        what,
        message: e.to_string(),
    }
}

/// Where a Zenoh session listens and what it connects to. Endpoints are Zenoh locators,
/// e.g. `tcp/127.0.0.1:7447` or `unixsock-stream//tmp/pir2.sock`. Multicast and gossip
/// scouting are off: peers meet only through these endpoints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Link {
    /// Endpoints to listen on (servers usually listen).
    pub listen: Vec<String>,
    /// Endpoints to connect to (the robot usually connects).
    pub connect: Vec<String>,
    /// First retry period after a lost connection (then doubles, up to 10×).
    pub retry: Duration,
    /// Mutual TLS for `tls/…` endpoints (`None`: plain TCP / Unix sockets only).
    #[serde(default)]
    pub tls: Option<TlsFiles>,
    /// Largest message the transport reassembles, bytes: larger ones are dropped before
    /// anything is decoded.
    #[serde(default = "default_max_message_bytes")]
    pub max_message_bytes: usize,
}

fn default_max_message_bytes() -> usize {
    64 << 20
}

/// PEM files of a mutual-TLS link. Both sides present a certificate signed by `ca` and
/// verify the other's against it; a connecting side also checks that the server's
/// certificate names the host it dialled.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TlsFiles {
    /// The certificate authority both sides trust (the user's CA).
    pub ca: std::path::PathBuf,
    /// This side's certificate chain, signed by `ca`.
    pub cert: std::path::PathBuf,
    /// This side's private key.
    pub key: std::path::PathBuf,
}

/// Whether an endpoint (`tcp/HOST:PORT`, `tls/…`, `unixsock-stream/PATH`) only reaches this
/// machine.
pub fn is_loopback_endpoint(endpoint: &str) -> bool {
    let Some((proto, addr)) = endpoint.split_once('/') else {
        return false;
    };
    if proto == "unixsock-stream" {
        return true;
    }
    // Strip Zenoh's `#…` / `?…` suffixes and the port.
    let addr = addr.split(['#', '?']).next().unwrap_or(addr);
    let host = match addr.rsplit_once(':') {
        Some((h, _)) => h.trim_start_matches('[').trim_end_matches(']'),
        None => addr,
    };
    host == "localhost"
        || host
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

impl Link {
    /// Listen on `endpoint`.
    pub fn listen(endpoint: impl Into<String>) -> Self {
        Self {
            listen: vec![endpoint.into()],
            connect: Vec::new(),
            retry: Duration::from_millis(100),
            tls: None,
            max_message_bytes: default_max_message_bytes(),
        }
    }
    /// Connect to `endpoint`.
    pub fn connect(endpoint: impl Into<String>) -> Self {
        Self {
            listen: Vec::new(),
            connect: vec![endpoint.into()],
            retry: Duration::from_millis(100),
            tls: None,
            max_message_bytes: default_max_message_bytes(),
        }
    }

    /// The same link with mutual TLS.
    pub fn with_tls(mut self, tls: TlsFiles) -> Self {
        self.tls = Some(tls);
        self
    }

    /// Refuse to talk beyond this machine without TLS: every listen *and* connect endpoint
    /// must be a loopback or Unix-socket one, or a `tls/…` one with [`Link::tls`] set, unless
    /// `insecure`. A robot connecting in plain TCP to another host would take actions or
    /// features from whoever answers on that address. Also refuses `tls/…` endpoints without
    /// TLS files.
    pub fn check_exposure(&self, insecure: bool) -> Result<()> {
        for e in self.listen.iter().chain(&self.connect) {
            if e.starts_with("tls/") && self.tls.is_none() {
                return Err(Error::Config(format!(
                    "endpoint `{e}` is TLS but no CA, certificate and key were given"
                )));
            }
        }
        for e in &self.listen {
            let protected = e.starts_with("tls/") && self.tls.is_some();
            if !protected && !is_loopback_endpoint(e) && !insecure {
                return Err(Error::Config(format!(
                    "refusing to listen on `{e}` without TLS: anyone on that network could read \
                     the features, query the policy or impersonate the server. Listen on \
                     `tls/…` with a CA, certificate and key, or accept the risk explicitly \
                     (insecure)"
                )));
            }
        }
        for e in &self.connect {
            let protected = e.starts_with("tls/") && self.tls.is_some();
            if !protected && !is_loopback_endpoint(e) && !insecure {
                return Err(Error::Config(format!(
                    "refusing to connect to `{e}` without TLS: whoever answers on that address \
                     (or sits between) would feed the robot its actions or features. Connect to \
                     `tls/…` with a CA, certificate and key (mutual TLS), or accept the risk \
                     explicitly on a lab network (insecure)"
                )));
            }
        }
        Ok(())
    }

    fn zenoh_config(&self) -> Result<zenoh::Config> {
        if self.listen.is_empty() && self.connect.is_empty() {
            return Err(Error::Config(
                "a link needs at least one listen or connect endpoint".into(),
            ));
        }
        if self.max_message_bytes == 0 {
            return Err(Error::Config("max_message_bytes must be positive".into()));
        }
        self.check_exposure(true)?;
        let json = |v: &[String]| serde_json::to_string(v).unwrap_or_else(|_| "[]".into());
        let retry = self.retry.as_millis().max(1);
        let mut c = zenoh::Config::default();
        let mut entries = vec![
            ("mode", "\"peer\"".to_string()),
            ("scouting/multicast/enabled", "false".into()),
            ("scouting/gossip/enabled", "false".into()),
            ("listen/endpoints", json(&self.listen)),
            ("connect/endpoints", json(&self.connect)),
            (
                "connect/retry",
                format!(
                    "{{ period_init_ms: {retry}, period_max_ms: {}, period_increase_factor: 2 }}",
                    retry * 10
                ),
            ),
            (
                "transport/link/rx/max_message_size",
                self.max_message_bytes.to_string(),
            ),
        ];
        if let Some(t) = &self.tls {
            t.check()?;
            let path = |p: &std::path::Path| {
                serde_json::to_string(&p.display().to_string()).unwrap_or_else(|_| "\"\"".into())
            };
            entries.extend([
                ("transport/link/tls/root_ca_certificate", path(&t.ca)),
                ("transport/link/tls/listen_certificate", path(&t.cert)),
                ("transport/link/tls/listen_private_key", path(&t.key)),
                ("transport/link/tls/connect_certificate", path(&t.cert)),
                ("transport/link/tls/connect_private_key", path(&t.key)),
                ("transport/link/tls/enable_mtls", "true".into()),
                ("transport/link/tls/verify_name_on_connect", "true".into()),
            ]);
        }
        for (k, v) in entries {
            c.insert_json5(k, &v)
                .map_err(|e| Error::Config(format!("zenoh config `{k}` = {v}: {e}")))?;
        }
        Ok(c)
    }

    pub(crate) fn open(&self) -> Result<zenoh::Session> {
        use zenoh::Wait;
        let config = self.zenoh_config()?;
        zenoh::open(config).wait().map_err(|e| {
            let m = e.to_string();
            let l = m.to_lowercase();
            match &self.tls {
                // The files looked like PEM but Zenoh's TLS stack refused them.
                Some(t) if ["tls", "cert", "key", "pem"].iter().any(|w| l.contains(w)) => {
                    Error::Tls(format!(
                        "the TLS files were refused ({m}); CA {}, certificate {}, key {}",
                        t.ca.display(),
                        t.cert.display(),
                        t.key.display()
                    ))
                }
                _ => Error::Transport {
                    what: "open session",
                    message: m,
                },
            }
        })
    }

    /// The error for "nothing answered within `after`" on `session`: with TLS, when no peer
    /// is connected and a `tls/…` endpoint this side dials accepts a plain TCP connection,
    /// the TLS handshake is what failed ([`Error::Tls`], naming the usual causes); otherwise
    /// [`Error::Timeout`].
    pub(crate) fn no_answer(
        &self,
        session: &zenoh::Session,
        what: &'static str,
        after: Duration,
    ) -> Error {
        use zenoh::Wait;
        let timeout = Error::Timeout { what, after };
        let Some(t) = &self.tls else {
            return timeout;
        };
        if session.info().peers_zid().wait().next().is_some() {
            return timeout;
        }
        let refused: Vec<&str> = self
            .connect
            .iter()
            .filter(|e| e.starts_with("tls/") && tcp_accepts(e))
            .map(String::as_str)
            .collect();
        if refused.is_empty() {
            return timeout;
        }
        Error::Tls(format!(
            "the TLS handshake with `{}` failed: the port accepts connections but no session \
             was established within {after:?} ({what}). Usual causes: the server's certificate \
             is not signed by the CA given here ({}) or ours ({}) not by the CA the server \
             trusts; the server's certificate does not name the host dialled; a certificate \
             has expired; or the server does not speak TLS on that port",
            refused.join("`, `"),
            t.ca.display(),
            t.cert.display(),
        ))
    }
}

/// Whether `tls/HOST:PORT` accepts a TCP connection within half a second.
fn tcp_accepts(endpoint: &str) -> bool {
    use std::net::ToSocketAddrs;
    let addr = endpoint.split_once('/').map_or(endpoint, |(_, a)| a);
    let addr = addr.split(['#', '?']).next().unwrap_or(addr);
    let Ok(addrs) = addr.to_socket_addrs() else {
        return false;
    };
    addrs
        .into_iter()
        .any(|a| std::net::TcpStream::connect_timeout(&a, Duration::from_millis(500)).is_ok())
}

impl TlsFiles {
    /// Check that each file can be read and holds what it should in PEM (a certificate for
    /// `ca` and `cert`, a private key for `key`), before any session is opened: a missing or
    /// garbled file is an [`Error::Tls`] naming it, not a peer that never answers.
    pub fn check(&self) -> Result<()> {
        for (what, p, label) in [
            ("CA", &self.ca, "CERTIFICATE"),
            ("certificate", &self.cert, "CERTIFICATE"),
            ("private key", &self.key, "PRIVATE KEY"),
        ] {
            let bytes = std::fs::read(p).map_err(|e| {
                Error::Tls(format!(
                    "the {what} file {} cannot be read: {e}",
                    p.display()
                ))
            })?;
            pem_block(&String::from_utf8_lossy(&bytes), label).map_err(|why| {
                Error::Tls(format!(
                    "the {what} file {} is not a PEM {}: {why}",
                    p.display(),
                    label.to_lowercase()
                ))
            })?;
        }
        Ok(())
    }
}

/// Check that `text` holds at least one PEM block whose label ends with `label`, with a
/// base64 body; every block must be well formed.
fn pem_block(text: &str, label: &str) -> std::result::Result<(), String> {
    let mut found = false;
    let mut rest = text;
    while let Some(i) = rest.find("-----BEGIN ") {
        let after = &rest[i + 11..];
        let Some(j) = after.find("-----") else {
            return Err("a BEGIN line without its closing dashes".into());
        };
        let name = &after[..j];
        let body_and_more = &after[j + 5..];
        let end = format!("-----END {name}-----");
        let Some(k) = body_and_more.find(&end) else {
            return Err(format!("`BEGIN {name}` without `END {name}`"));
        };
        let body: String = body_and_more[..k]
            .chars()
            .filter(|c| !c.is_whitespace())
            .collect();
        let base64 = |c: char| c.is_ascii_alphanumeric() || matches!(c, '+' | '/' | '=');
        if body.is_empty() || body.len() % 4 != 0 || !body.chars().all(base64) {
            return Err(format!("the `{name}` block is not base64"));
        }
        found |= name.ends_with(label);
        rest = &body_and_more[k + end.len()..];
    }
    if found {
        Ok(())
    } else {
        Err(format!("no `-----BEGIN …{label}-----` block"))
    }
}

/// Counters of the remote channels, shared between a channel and whoever reads them.
/// All updates are relaxed atomics (never on the control thread).
#[derive(Debug, Default)]
pub struct RemoteStats {
    frames: AtomicU64,
    stale_polls: AtomicU64,
    stale_episodes: AtomicU64,
    reconnects: AtomicU64,
    clock_syncs: AtomicU64,
    clock_sync_failures: AtomicU64,
    calls: AtomicU64,
    attempts: AtomicU64,
    timeouts: AtomicU64,
    failed_calls: AtomicU64,
    server_errors: AtomicU64,
    malformed: AtomicU64,
    foreign_replies: AtomicU64,
    abandoned: AtomicU64,
    offset_ns: AtomicI64,
    offset_rtt_ns: AtomicU64,
    last_rtt_ns: AtomicU64,
}

/// A snapshot of [`RemoteStats`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RemoteCounters {
    /// Slow: fresh feature messages accepted.
    pub frames: u64,
    /// Slow: polls without a fresh message (the last features were handed again).
    pub stale_polls: u64,
    /// Slow: transitions from fresh to stale.
    pub stale_episodes: u64,
    /// A new server instance (slow) or a reply after failures (policy).
    pub reconnects: u64,
    /// Slow: successful clock-offset estimates.
    pub clock_syncs: u64,
    /// Slow: clock-offset estimates that got no answer.
    pub clock_sync_failures: u64,
    /// Policy: calls made.
    pub calls: u64,
    /// Policy: requests sent (calls plus retries).
    pub attempts: u64,
    /// Policy: requests without a reply in time.
    pub timeouts: u64,
    /// Policy: calls that gave up (safety stop).
    pub failed_calls: u64,
    /// Policy: error replies from the server.
    pub server_errors: u64,
    /// Messages that could not be used (malformed, or a reply to another request): dropped.
    #[serde(default)]
    pub malformed: u64,
    /// Messages from a peer other than the one of the last handshake (policy: replies
    /// without the session token; slow: features or pongs from another server instance
    /// while the pinned one is alive): dropped, never used.
    #[serde(default)]
    pub foreign_replies: u64,
    /// Policy: calls given up because the run stopped while they were retrying (the robot
    /// was already stopped; see [`crate::StopSignal`]).
    #[serde(default)]
    pub abandoned: u64,
    /// Slow: current offset estimate, server clock − robot clock, ns.
    pub offset_ns: i64,
    /// Slow: round trip of the sample the offset came from (accuracy bound = half), ns.
    pub offset_rtt_ns: u64,
    /// Policy: round trip of the last successful call, ns.
    pub last_rtt_ns: u64,
}

impl RemoteStats {
    /// Read every counter.
    pub fn counters(&self) -> RemoteCounters {
        let r = |a: &AtomicU64| a.load(Ordering::Relaxed);
        RemoteCounters {
            frames: r(&self.frames),
            stale_polls: r(&self.stale_polls),
            stale_episodes: r(&self.stale_episodes),
            reconnects: r(&self.reconnects),
            clock_syncs: r(&self.clock_syncs),
            clock_sync_failures: r(&self.clock_sync_failures),
            calls: r(&self.calls),
            attempts: r(&self.attempts),
            timeouts: r(&self.timeouts),
            failed_calls: r(&self.failed_calls),
            server_errors: r(&self.server_errors),
            malformed: r(&self.malformed),
            foreign_replies: r(&self.foreign_replies),
            abandoned: r(&self.abandoned),
            offset_ns: self.offset_ns.load(Ordering::Relaxed),
            offset_rtt_ns: r(&self.offset_rtt_ns),
            last_rtt_ns: r(&self.last_rtt_ns),
        }
    }
}

fn bump(a: &AtomicU64) {
    a.fetch_add(1, Ordering::Relaxed);
}

/// A random id for this process instance (distinguishes a restarted server).
pub(crate) fn instance_id() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0),
    );
    h.write_u32(std::process::id());
    h.finish()
}
