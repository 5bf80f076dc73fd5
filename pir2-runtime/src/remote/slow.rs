//! The remote slow channel: `serve_slow` publishes features, `RemoteSlowSource` receives
//! them on the robot and converts their capture times into the robot's clock.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use zenoh::handlers::{RingChannel, RingChannelHandler};
use zenoh::key_expr::KeyExpr;
use zenoh::sample::Sample;
use zenoh::Wait;

use super::clock_sync::{sync_clock, ClockOffset};
use super::{bump, instance_id, transport, wire, Error, Link, RemoteStats, Result};
use crate::clock::Clock;
use crate::io::{SlowEncoder, SlowFeatures, SlowFrame, SlowSource};
use crate::realtime::{block_on, SlowChannel};

/// Settings of [`serve_slow`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlowServerConfig {
    /// Where to listen / connect (default: listen on `tcp/127.0.0.1:7448`).
    pub link: Link,
    /// Key the features are published on; pings are answered on `<key>/clock`.
    pub key: String,
}

impl Default for SlowServerConfig {
    fn default() -> Self {
        Self {
            link: Link::listen("tcp/127.0.0.1:7448"),
            key: "pir2/slow".into(),
        }
    }
}

fn key(k: &str) -> Result<KeyExpr<'static>> {
    KeyExpr::try_from(k.to_string()).map_err(|e| Error::Config(format!("key `{k}`: {e}")))
}

/// Capture and encode slow frames until `stop` is set, publishing each one with its capture
/// time (on `clock`, the clock the source stamps with) and answering clock pings on
/// `<key>/clock`. Returns when `stop` is set (after the current frame), or with the first
/// error of the source or encoder.
pub fn serve_slow(
    mut source: Box<dyn SlowSource>,
    mut encoder: Box<dyn SlowEncoder>,
    clock: Arc<dyn Clock>,
    cfg: &SlowServerConfig,
    stop: Arc<AtomicBool>,
) -> Result<()> {
    let me = instance_id();
    let data_key = key(&cfg.key)?;
    let clock_key = key(&format!("{}/clock", cfg.key))?;
    let session = cfg.link.open()?;
    let publisher = session
        .declare_publisher(data_key)
        .wait()
        .map_err(transport("declare publisher"))?;
    let pings = session
        .declare_queryable(clock_key)
        .wait()
        .map_err(transport("declare clock queryable"))?;
    let done = AtomicBool::new(false);
    std::thread::scope(|s| -> Result<()> {
        let clk = &*clock;
        let (stop_ref, done_ref) = (&stop, &done);
        s.spawn(move || {
            // Pong thread: stamp on receipt, answer at once.
            while !stop_ref.load(Ordering::Acquire) && !done_ref.load(Ordering::Acquire) {
                let Ok(Some(q)) = pings.recv_timeout(Duration::from_millis(20)) else {
                    continue;
                };
                let t_recv = clk.now();
                let Some(bytes) = q.payload().map(|p| p.to_bytes()) else {
                    continue;
                };
                let reply = match wire::decode(&bytes) {
                    Ok(m) if m.header.kind == wire::Kind::Ping => {
                        wire::encode_pong(me, &m.header, t_recv)
                    }
                    Ok(m) => wire::encode_error(me, m.header.seq, "expected a ping"),
                    Err(e) => wire::encode_error(me, 0, &e.to_string()),
                };
                let _ = q.reply(q.key_expr().clone(), reply).wait();
            }
        });
        let mut seq = 0u64;
        let r = (|| -> Result<()> {
            while !stop.load(Ordering::Acquire) {
                let feats = block_on(async {
                    let frame = source.capture().await?;
                    encoder.encode(frame).await
                })?;
                if feats.tokens * feats.dim != feats.data.len() {
                    return Err(crate::Error::shape(
                        "slow features [T, D]",
                        (feats.tokens, feats.dim),
                        feats.data.len(),
                    )
                    .into());
                }
                seq += 1;
                let bytes = wire::encode_features(
                    me,
                    seq,
                    feats.t_capture,
                    clock.now(),
                    feats.tokens,
                    feats.dim,
                    &feats.data,
                );
                publisher.put(bytes).wait().map_err(transport("publish"))?;
            }
            Ok(())
        })();
        done.store(true, Ordering::Release);
        r
    })?;
    session.close().wait().map_err(transport("close"))?;
    Ok(())
}

/// Settings of the robot side of the remote slow channel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RemoteSlowConfig {
    /// Where the slow server is (default: connect to `tcp/127.0.0.1:7448`).
    pub link: Link,
    /// The server's key.
    pub key: String,
    /// Without a fresh message for this long, the last features are handed again (same
    /// capture time, so `d_vis` keeps growing), a stale poll is counted and the slow worker
    /// gets a chance to see the stop flag. Make it longer than the server's frame interval.
    pub stale_poll: Duration,
    /// How long the first features may take before `capture` fails.
    pub first_timeout: Duration,
    /// Without a fresh message for this long, `capture` fails instead of handing the last
    /// features again: a dead slow server ends the run (fail closed) even where no
    /// stale-slow grace is set on the action head.
    #[serde(default = "default_max_stale")]
    pub max_stale: Duration,
    /// Pings per clock-offset estimate.
    pub sync_samples: usize,
    /// Timeout of one ping.
    pub ping_timeout: Duration,
    /// Re-estimate the offset this often (drift); always on a new server instance.
    pub resync_every: Duration,
}

impl Default for RemoteSlowConfig {
    fn default() -> Self {
        Self {
            link: Link::connect("tcp/127.0.0.1:7448"),
            key: "pir2/slow".into(),
            stale_poll: Duration::from_millis(250),
            first_timeout: Duration::from_secs(10),
            max_stale: default_max_stale(),
            sync_samples: 16,
            ping_timeout: Duration::from_millis(200),
            resync_every: Duration::from_secs(10),
        }
    }
}

fn default_max_stale() -> Duration {
    Duration::from_secs(2)
}

struct Sync {
    sender: u64,
    offset: ClockOffset,
    at: Instant,
    last_seq: u64,
}

/// The robot side of the remote slow channel (a [`SlowSource`]); pair it with
/// [`RemoteSlowEncoder`], or build both with [`remote_slow_channel`].
pub struct RemoteSlowSource {
    session: zenoh::Session,
    sub: zenoh::pubsub::Subscriber<RingChannelHandler<Sample>>,
    clock_key: KeyExpr<'static>,
    clock: Arc<dyn Clock>,
    cfg: RemoteSlowConfig,
    me: u64,
    sync: Option<Sync>,
    last: Option<SlowFrame>,
    last_fresh: Option<Instant>,
    stale: bool,
    shape: Arc<Mutex<(usize, usize)>>,
    stats: Arc<RemoteStats>,
}

impl std::fmt::Debug for RemoteSlowSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemoteSlowSource")
            .field("key", &self.cfg.key)
            .field("stats", &self.stats.counters())
            .finish_non_exhaustive()
    }
}

impl RemoteSlowSource {
    /// Open a session and subscribe. `clock` is the runtime's clock (capture times are
    /// converted into it).
    pub fn connect(cfg: RemoteSlowConfig, clock: Arc<dyn Clock>) -> Result<Self> {
        if cfg.stale_poll.is_zero() || cfg.max_stale.is_zero() || cfg.sync_samples == 0 {
            return Err(Error::Config(
                "stale_poll, max_stale and sync_samples must be positive".into(),
            ));
        }
        let data_key = key(&cfg.key)?;
        let clock_key = key(&format!("{}/clock", cfg.key))?;
        let session = cfg.link.open()?;
        let sub = session
            .declare_subscriber(data_key)
            .with(RingChannel::new(1))
            .wait()
            .map_err(transport("declare subscriber"))?;
        Ok(Self {
            session,
            sub,
            clock_key,
            clock,
            cfg,
            me: instance_id(),
            sync: None,
            last: None,
            last_fresh: None,
            stale: false,
            shape: Arc::new(Mutex::new((0, 0))),
            stats: Arc::new(RemoteStats::default()),
        })
    }

    /// The counters (frames, stale polls, reconnects, clock syncs, offset).
    pub fn stats(&self) -> Arc<RemoteStats> {
        self.stats.clone()
    }

    /// The identity encoder that goes with this source.
    pub fn encoder(&self) -> RemoteSlowEncoder {
        RemoteSlowEncoder {
            shape: self.shape.clone(),
        }
    }

    /// The current offset estimate (server − robot clock), once a frame was received.
    pub fn offset(&self) -> Option<ClockOffset> {
        self.sync.as_ref().map(|s| s.offset)
    }

    /// Make sure the offset for `sender` is known and fresh. `false`: no estimate, drop the
    /// frame.
    fn ensure_sync(&mut self, sender: u64) -> Result<bool> {
        let fresh = self
            .sync
            .as_ref()
            .is_some_and(|s| s.sender == sender && s.at.elapsed() < self.cfg.resync_every);
        if fresh {
            return Ok(true);
        }
        match sync_clock(
            &self.session,
            &self.clock_key,
            &*self.clock,
            self.me,
            Some(sender),
            self.cfg.sync_samples,
            self.cfg.ping_timeout,
        ) {
            Ok((_, offset)) => {
                bump(&self.stats.clock_syncs);
                self.stats
                    .offset_ns
                    .store(offset.offset_ns, Ordering::Relaxed);
                self.stats
                    .offset_rtt_ns
                    .store(offset.rtt_ns, Ordering::Relaxed);
                let last_seq = match &self.sync {
                    Some(s) if s.sender == sender => s.last_seq,
                    Some(_) => {
                        bump(&self.stats.reconnects);
                        0
                    }
                    None => 0,
                };
                self.sync = Some(Sync {
                    sender,
                    offset,
                    at: Instant::now(),
                    last_seq,
                });
                Ok(true)
            }
            Err(Error::Timeout { .. }) => {
                bump(&self.stats.clock_sync_failures);
                // Keep a stale estimate of the same instance rather than drop its frames.
                Ok(self.sync.as_ref().is_some_and(|s| s.sender == sender))
            }
            Err(e) => Err(e),
        }
    }

    pub(crate) fn next(&mut self) -> Result<SlowFrame> {
        let first = self.last.is_none();
        let wait = if first {
            self.cfg.first_timeout
        } else {
            self.cfg.stale_poll
        };
        let deadline = Instant::now() + wait;
        loop {
            let sample = match self.sub.recv_deadline(deadline) {
                Ok(Some(s)) => s,
                Ok(None) => break,
                Err(e) => return Err(transport("receive features")(e)),
            };
            let bytes = sample.payload().to_bytes();
            let msg = match wire::decode_features(&bytes) {
                Ok(m) => m,
                // A server of another wire version: a typed error, it cannot heal.
                Err(e @ wire::WireError::Version { .. }) => return Err(e.into()),
                Err(_) => {
                    // Not ours or damaged: dropped and counted, never the end of a run.
                    bump(&self.stats.malformed);
                    continue;
                }
            };
            if self
                .sync
                .as_ref()
                .is_some_and(|s| s.sender == msg.sender && msg.seq <= s.last_seq)
            {
                continue; // old or duplicated
            }
            // Another instance while the pinned one keeps publishing: not the server this
            // source synchronised with (an impostor on the key). A restarted server is taken
            // once the pinned one has been quiet for a stale poll.
            let pinned_alive = self
                .last_fresh
                .is_some_and(|t| t.elapsed() < self.cfg.stale_poll);
            if pinned_alive && self.sync.as_ref().is_some_and(|s| s.sender != msg.sender) {
                bump(&self.stats.foreign_replies);
                continue;
            }
            if !self.ensure_sync(msg.sender)? {
                continue;
            }
            let Some(sync) = self.sync.as_mut() else {
                continue;
            };
            sync.last_seq = msg.seq;
            // A capture can not be in the future: clamp the offset error.
            let t_capture = sync.offset.to_local(msg.t_capture).min(self.clock.now());
            *self.shape.lock().unwrap_or_else(|p| p.into_inner()) = (msg.tokens, msg.dim);
            bump(&self.stats.frames);
            self.stale = false;
            self.last_fresh = Some(Instant::now());
            let frame = SlowFrame {
                t_capture,
                values: msg.data,
                ..Default::default()
            };
            self.last = Some(frame.clone());
            return Ok(frame);
        }
        match &self.last {
            None => Err(self
                .cfg
                .link
                .no_answer(&self.session, "first slow features", wait)),
            Some(_)
                if self
                    .last_fresh
                    .is_some_and(|t| t.elapsed() > self.cfg.max_stale) =>
            {
                Err(Error::Timeout {
                    what: "fresh slow features (the slow server stopped sending)",
                    after: self.cfg.max_stale,
                })
            }
            Some(last) => {
                bump(&self.stats.stale_polls);
                if !self.stale {
                    self.stale = true;
                    bump(&self.stats.stale_episodes);
                }
                Ok(last.clone())
            }
        }
    }
}

#[async_trait::async_trait]
impl SlowSource for RemoteSlowSource {
    /// The next fresh features (capture time in the robot's clock), or the last ones again
    /// after [`RemoteSlowConfig::stale_poll`] without a message; an error once no fresh
    /// message came for [`RemoteSlowConfig::max_stale`]. Blocks the slow worker.
    async fn capture(&mut self) -> crate::Result<SlowFrame> {
        self.next().map_err(Into::into)
    }
}

/// Identity encoder for [`RemoteSlowSource`]: the features were computed on the server.
#[derive(Debug, Clone)]
pub struct RemoteSlowEncoder {
    shape: Arc<Mutex<(usize, usize)>>,
}

#[async_trait::async_trait]
impl SlowEncoder for RemoteSlowEncoder {
    async fn encode(&mut self, frame: SlowFrame) -> crate::Result<SlowFeatures> {
        let (tokens, dim) = *self.shape.lock().unwrap_or_else(|p| p.into_inner());
        let (tokens, dim) = if tokens * dim == frame.values.len() {
            (tokens, dim)
        } else {
            (1, frame.values.len())
        };
        Ok(SlowFeatures {
            t_capture: frame.t_capture,
            data: frame.values,
            tokens,
            dim,
        })
    }
}

/// The runtime's asynchronous slow channel fed by a remote server, and its counters.
pub fn remote_slow_channel(
    cfg: RemoteSlowConfig,
    clock: Arc<dyn Clock>,
) -> Result<(SlowChannel, Arc<RemoteStats>)> {
    let source = RemoteSlowSource::connect(cfg, clock)?;
    let stats = source.stats();
    let encoder = source.encoder();
    Ok((
        SlowChannel::Async {
            source: Box::new(source),
            encoder: Box::new(encoder),
        },
        stats,
    ))
}
