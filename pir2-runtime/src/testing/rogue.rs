//! Rogue Zenoh peers for fault tests of the remote channels: a bare Zenoh session (not
//! pir2's) that answers the policy key with well-formed but wrong velocities, or
//! re-publishes the slow server's feature frames under another sender with wrong values.
//! The robot side must drop and count what they send (`RemoteCounters::foreign_replies`),
//! never use it.
//!
//! A rogue either listens (the robot also connects to it: a second endpoint) or joins a
//! server as a Zenoh *client*: a pir2 server is a Zenoh peer, and a peer routes for its
//! clients, so the robot's requests reach the rogue and its replies reach the robot
//! through the very endpoint the robot dialled.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use zenoh::Wait;

use crate::remote::{wire, Error, Result};

/// How a rogue attaches to the network.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Attach {
    /// A peer listening on this endpoint (the robot must be told to connect to it).
    Listen(String),
    /// A client of the server listening on this endpoint (waiting up to a minute for it).
    ClientOf(String),
}

impl Attach {
    fn session(&self) -> Result<zenoh::Session> {
        let (mode, key, ep) = match self {
            Attach::Listen(e) => ("peer", "listen/endpoints", e),
            Attach::ClientOf(e) => ("client", "connect/endpoints", e),
        };
        let mut c = zenoh::Config::default();
        let endpoints = serde_json::to_string(&[ep]).map_err(|e| Error::Config(e.to_string()))?;
        for (k, v) in [
            ("mode", format!("\"{mode}\"")),
            ("scouting/multicast/enabled", "false".into()),
            ("scouting/gossip/enabled", "false".into()),
            (key, endpoints),
            // A client waits (retrying) for a server that is still starting.
            ("connect/timeout_ms", "60000".into()),
            (
                "connect/retry",
                "{ period_init_ms: 50, period_max_ms: 500, period_increase_factor: 2 }".into(),
            ),
        ] {
            c.insert_json5(k, &v)
                .map_err(|e| Error::Config(format!("zenoh config `{k}` = {v}: {e}")))?;
        }
        zenoh::open(c).wait().map_err(transport("open (rogue)"))
    }
}

fn transport(what: &'static str) -> impl Fn(zenoh::Error) -> Error {
    move |e| Error::Transport {
        what,
        message: e.to_string(),
    }
}

/// A running rogue; stopped (and its session closed) when dropped.
#[derive(Debug)]
pub struct Rogue {
    stop: Arc<AtomicBool>,
    sent: Arc<AtomicU64>,
    handle: Option<JoinHandle<()>>,
}

/// The session token rogues put on their replies (a server's is random).
pub const ROGUE_TOKEN: wire::SessionToken = [0x0bad, 0x0bad, 0x0bad, 0x0bad];
/// The sender id rogues put on their messages.
pub const ROGUE_SENDER: u64 = 0x0bad_0bad;

impl Rogue {
    /// Answer every request on `key` with `value` in every velocity entry (right batch,
    /// horizon, action dimension and sequence number), and every handshake ping with a
    /// pong of its own session token.
    pub fn policy_responder(attach: &Attach, key: &str, value: f32) -> Result<Self> {
        let session = attach.session()?;
        let q = session
            .declare_queryable(key.to_string())
            .wait()
            .map_err(transport("declare_queryable (rogue)"))?;
        let key = key.to_string();
        Ok(Self::spawn(move |stop, sent| {
            while !stop.load(Ordering::Acquire) {
                let Ok(Some(query)) = q.recv_timeout(Duration::from_millis(20)) else {
                    continue;
                };
                let Some(bytes) = query.payload().map(|p| p.to_bytes().to_vec()) else {
                    continue;
                };
                let token = Some(ROGUE_TOKEN);
                let reply = match wire::decode_request(&bytes) {
                    Ok(r) => {
                        let shape = [r.batch, r.horizon, r.action_dim];
                        let v = vec![value; shape.iter().product()];
                        wire::encode_reply_with_token(ROGUE_SENDER, &r.header, 0, shape, &v, token)
                    }
                    Err(_) => match wire::decode_header(&bytes) {
                        Ok((h, _)) => {
                            wire::encode_pong_with_token(ROGUE_SENDER, &h, 0, None, token)
                        }
                        Err(_) => continue,
                    },
                };
                if query.reply(key.clone(), reply).wait().is_ok() {
                    sent.fetch_add(1, Ordering::SeqCst);
                }
            }
            drop(q);
            let _ = session.close().wait();
        }))
    }

    /// Re-publish every feature frame seen on `key` (the slow server's) right away under
    /// [`ROGUE_SENDER`], with the same shape and timestamps and every value set to `value`:
    /// well-formed, fresh and wrong.
    pub fn features_republisher(attach: &Attach, key: &str, value: f32) -> Result<Self> {
        let session = attach.session()?;
        let sub = session
            .declare_subscriber(key.to_string())
            .wait()
            .map_err(transport("declare_subscriber (rogue)"))?;
        let publisher = session
            .declare_publisher(key.to_string())
            .wait()
            .map_err(transport("declare_publisher (rogue)"))?;
        Ok(Self::spawn(move |stop, sent| {
            while !stop.load(Ordering::Acquire) {
                let Ok(Some(sample)) = sub.recv_timeout(Duration::from_millis(20)) else {
                    continue;
                };
                let Ok(f) = wire::decode_features(&sample.payload().to_bytes()) else {
                    continue;
                };
                if f.sender == ROGUE_SENDER {
                    continue;
                }
                let data = vec![value; f.data.len()];
                let fake = wire::encode_features(
                    ROGUE_SENDER,
                    f.seq,
                    f.t_capture,
                    f.t_sent,
                    f.tokens,
                    f.dim,
                    &data,
                );
                if publisher.put(fake).wait().is_ok() {
                    sent.fetch_add(1, Ordering::SeqCst);
                }
            }
            drop((sub, publisher));
            let _ = session.close().wait();
        }))
    }

    fn spawn(f: impl FnOnce(Arc<AtomicBool>, Arc<AtomicU64>) + Send + 'static) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let sent = Arc::new(AtomicU64::new(0));
        let (s, n) = (stop.clone(), sent.clone());
        Self {
            stop,
            sent,
            handle: Some(std::thread::spawn(move || f(s, n))),
        }
    }

    /// Replies or frames sent so far.
    pub fn sent(&self) -> u64 {
        self.sent.load(Ordering::SeqCst)
    }
}

impl Drop for Rogue {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}
