//! `pir2 serve policy|slow` and `pir2 gr00t serve policy|slow` (feature `remote`); the robot
//! side of `pir2 eval --remote` and the TLS options are [`crate::remote`]'s.
//!
//! Transport, wire format, clock sync and fault handling are `pir2_runtime::remote`'s (Zenoh
//! peers with multicast and gossip scouting off: they meet only through the given
//! endpoints). This module chooses the models:
//!
//! - `serve policy --checkpoint DIR`: a candle checkpoint (e.g. `pir2 train`'s `best/`)
//!   answers one-NFE requests; `pir2 eval --remote ENDPOINT` sends the ball-plate
//!   evaluation's action-head calls there ([`crate::remote::RemotePolicy::models`] is a model
//!   factory for the study pipeline's one closed loop) (the lock-step eval is deterministic,
//!   so the result equals the local eval's, outages included: a call is retried until the
//!   server answers or `max_failed_calls` timeouts in a row stop the run);
//! - `serve slow --stub DIM`: a counter camera and a pass-through encoder publishing
//!   features with capture times;
//! - `gr00t serve policy --checkpoint DIR --task …` (needs feature `gr00t`): a GR00T export's
//!   ONNX action head, for `pir2 gr00t run … --remote-policy ENDPOINT`;
//! - `gr00t serve slow --checkpoint DIR --task …` (needs feature `gr00t`): the GR00T ONNX
//!   backbone on a synthetic camera, for `pir2 gr00t run … --remote-slow ENDPOINT`.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::Result;

use crate::remote::TlsOptions;
#[cfg(not(feature = "remote"))]
use crate::remote::NO_REMOTE;

/// What `pir2 serve …` runs (the GR00T servers are `pir2 gr00t serve`'s, [`Gr00tServeCmd`]).
#[derive(Debug, Clone, clap::Subcommand)]
pub enum ServeOptions {
    /// Answer a candle checkpoint's action-head (one-NFE) requests until Ctrl-C, for
    /// `pir2 eval --remote` (a GR00T export's head: `pir2 gr00t serve policy`).
    Policy(PolicyServeOptions),
    /// Publish stub slow-channel features (a counter camera and a pass-through encoder) with
    /// capture times until Ctrl-C (the GR00T backbone: `pir2 gr00t serve slow`).
    Slow(SlowServeOptions),
}

/// Where a policy server listens and how it answers: the flags `pir2 serve policy` and
/// `pir2 gr00t serve policy` share.
#[derive(Debug, Clone, clap::Args)]
pub struct PolicyEndpointOptions {
    /// Hold every reply this many ms: a stand-in for a slow network (tests, measuring how
    /// `d` follows the round trip). Zero in deployment.
    #[arg(long, default_value_t = 0)]
    pub inject_delay_ms: u64,
    /// Zenoh endpoint to listen on.
    #[arg(long, default_value = "tcp/127.0.0.1:7447")]
    pub listen: String,
    /// Key the requests arrive on.
    #[arg(long, default_value = "pir2/policy")]
    pub key: String,
    /// Mutual TLS and `--insecure`.
    #[command(flatten)]
    pub tls: TlsOptions,
}

/// How often, where and on which key a slow-channel server publishes: the flags `pir2 serve
/// slow` and `pir2 gr00t serve slow` share.
#[derive(Debug, Clone, clap::Args)]
pub struct SlowEndpointOptions {
    /// Camera frame period, ms.
    #[arg(long, default_value_t = 60)]
    pub frame_ms: u64,
    /// Zenoh endpoint to listen on.
    #[arg(long, default_value = "tcp/127.0.0.1:7448")]
    pub listen: String,
    /// Key the features are published on (clock pings on `<key>/clock`).
    #[arg(long, default_value = "pir2/slow")]
    pub key: String,
    /// Mutual TLS and `--insecure`.
    #[command(flatten)]
    pub tls: TlsOptions,
}

/// Options of `pir2 serve policy`.
#[derive(Debug, Clone, clap::Args)]
pub struct PolicyServeOptions {
    /// Candle checkpoint directory (config.json, stats.json, model.safetensors), e.g. the
    /// `best/` directory `pir2 train` writes.
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// The policy the checkpoint must have been trained as (refused by name if its
    /// `identity.json` records another). The server announces the checkpoint's identity
    /// (policy, weights SHA-256) to `pir2 eval --remote`, which refuses a server running
    /// another policy or other weights.
    #[arg(long, value_parser = crate::tasks::policy_parser())]
    pub policy: Option<pir2_runtime::Policy>,
    /// Where the server listens and how it answers.
    #[command(flatten)]
    pub endpoint: PolicyEndpointOptions,
}

/// Options of `pir2 serve slow`.
#[derive(Debug, Clone, clap::Args)]
pub struct SlowServeOptions {
    /// The stub's counter camera: this many values per frame.
    #[arg(long)]
    pub stub: usize,
    /// How often, where and on which key the features are published.
    #[command(flatten)]
    pub endpoint: SlowEndpointOptions,
}

/// What `pir2 gr00t serve …` runs.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum Gr00tServeCmd {
    /// Answer a GR00T export's action-head (one-NFE) requests until Ctrl-C, for
    /// `pir2 gr00t run … --remote-policy`.
    Policy(Gr00tPolicyServeOptions),
    /// Publish a GR00T export's backbone features (synthetic camera → ONNX backbone) with
    /// capture times until Ctrl-C, for `pir2 gr00t run … --remote-slow`.
    Slow(Gr00tSlowServeOptions),
}

/// Options of `pir2 gr00t serve policy`.
#[derive(Debug, Clone, clap::Args)]
pub struct Gr00tPolicyServeOptions {
    /// A GR00T export (docs/gr00t-contract.md): its action head (four ONNX graphs + side
    /// weights + statistics) is served.
    #[arg(long, alias = "gr00t-checkpoint")]
    pub checkpoint: PathBuf,
    /// The task (key or prompt) whose prompt layout (image and text token masks) the DiT is
    /// fed; must be the robot's `--task`.
    #[arg(long)]
    pub task: String,
    /// Where the server listens and how it answers.
    #[command(flatten)]
    pub endpoint: PolicyEndpointOptions,
    /// Where ONNX Runtime runs the action head.
    #[command(flatten)]
    pub ep: crate::ep::EpOptions,
}

/// Options of `pir2 gr00t serve slow`.
#[derive(Debug, Clone, clap::Args)]
pub struct Gr00tSlowServeOptions {
    /// A GR00T export (docs/gr00t-contract.md) whose ONNX backbone encodes a synthetic
    /// camera.
    #[arg(long, alias = "gr00t-checkpoint")]
    pub checkpoint: PathBuf,
    /// Task (key or prompt) whose prompt the backbone encodes.
    #[arg(long)]
    pub task: String,
    /// How often, where and on which key the features are published.
    #[command(flatten)]
    pub endpoint: SlowEndpointOptions,
    /// Where ONNX Runtime runs the backbone.
    #[command(flatten)]
    pub ep: crate::ep::EpOptions,
}

/// Run a server until `stop` (Ctrl-C).
#[cfg(feature = "remote")]
pub fn serve(cmd: &ServeOptions, stop: Arc<AtomicBool>) -> Result<()> {
    match cmd {
        ServeOptions::Policy(o) => imp::policy(o, stop),
        ServeOptions::Slow(o) => imp::slow(o, stop),
    }
}

/// Run a GR00T server until `stop` (Ctrl-C).
#[cfg(feature = "remote")]
pub fn serve_gr00t(cmd: &Gr00tServeCmd, stop: Arc<AtomicBool>) -> Result<()> {
    match cmd {
        Gr00tServeCmd::Policy(o) => imp::gr00t_policy(o, stop),
        Gr00tServeCmd::Slow(o) => imp::gr00t_slow(o, stop),
    }
}

/// Without feature `remote` there is no transport.
#[cfg(not(feature = "remote"))]
pub fn serve(_cmd: &ServeOptions, _stop: Arc<AtomicBool>) -> Result<()> {
    anyhow::bail!("{NO_REMOTE}")
}

/// Without feature `remote` there is no transport.
#[cfg(not(feature = "remote"))]
pub fn serve_gr00t(_cmd: &Gr00tServeCmd, _stop: Arc<AtomicBool>) -> Result<()> {
    anyhow::bail!("{NO_REMOTE}")
}

#[cfg(feature = "remote")]
mod imp {
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;
    use std::time::Duration;

    use anyhow::{Context, Result};

    use pir2_backends::candle::CandleModel;
    use pir2_runtime::remote::{
        serve_policy_counted, serve_slow, Link, PolicyServerConfig, PolicyServerStats,
        SlowServerConfig,
    };
    use pir2_runtime::testing::{CameraStub, PassThroughEncoder};
    use pir2_runtime::{Clock, ModelInput, SlowEncoder, SlowSource, SystemClock, VelocityModel};

    use super::{
        Gr00tPolicyServeOptions, Gr00tSlowServeOptions, PolicyServeOptions, SlowServeOptions,
    };

    impl super::PolicyEndpointOptions {
        /// The server's configuration and the "every reply held" note of its start line.
        fn config(&self) -> Result<(PolicyServerConfig, String)> {
            let cfg = PolicyServerConfig {
                link: self.tls.apply(Link::listen(self.listen.clone()))?,
                key: self.key.clone(),
                reply_delay: Duration::from_millis(self.inject_delay_ms),
                ..Default::default()
            };
            let delay = if self.inject_delay_ms > 0 {
                format!(", every reply held {} ms", self.inject_delay_ms)
            } else {
                String::new()
            };
            Ok((cfg, delay))
        }
    }

    pub(super) fn policy(o: &PolicyServeOptions, stop: Arc<AtomicBool>) -> Result<()> {
        let (listen, key, ck) = (&o.endpoint.listen, &o.endpoint.key, &o.checkpoint);
        let (mut cfg, delay) = o.endpoint.config()?;
        let model = CandleModel::load(ck)
            .with_context(|| format!("loading checkpoint {}", ck.display()))?;
        if let Some(p) = o.policy {
            crate::identity::expect_policy(&model, ck, p, "--policy")?;
        }
        cfg.identity = crate::identity::announce(&model);
        eprintln!(
            "serving {} ({}) on {listen}, key {key}{delay} (Ctrl-C to stop)",
            ck.display(),
            model.backend()
        );
        serve_counted(Announce::new(model), &cfg, stop)
            .with_context(|| format!("serving the policy on {listen}"))
    }

    pub(super) fn gr00t_policy(o: &Gr00tPolicyServeOptions, stop: Arc<AtomicBool>) -> Result<()> {
        let (listen, key) = (&o.endpoint.listen, &o.endpoint.key);
        let (cfg, delay) = o.endpoint.config()?;
        let (model, what) = gr00t_head(&o.checkpoint, &o.task, &o.ep)?;
        eprintln!("serving {what} on {listen}, key {key}{delay} (Ctrl-C to stop)");
        serve_counted(Announce::new(model), &cfg, stop)
            .with_context(|| format!("serving the policy on {listen}"))
    }

    pub(super) fn slow(o: &SlowServeOptions, stop: Arc<AtomicBool>) -> Result<()> {
        let link = o
            .endpoint
            .tls
            .apply(Link::listen(o.endpoint.listen.clone()))?;
        let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
        let period = Duration::from_millis(o.endpoint.frame_ms);
        let dim = o.stub;
        let pair: SlowPair = (
            Box::new(CameraStub::new(clock.clone(), period, dim)),
            Box::new(PassThroughEncoder {
                latency: Duration::ZERO,
            }),
            format!("stub camera ({dim} values) + pass-through encoder"),
        );
        publish(pair, clock, link, &o.endpoint, stop)
    }

    pub(super) fn gr00t_slow(o: &Gr00tSlowServeOptions, stop: Arc<AtomicBool>) -> Result<()> {
        let link = o
            .endpoint
            .tls
            .apply(Link::listen(o.endpoint.listen.clone()))?;
        let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
        let period = Duration::from_millis(o.endpoint.frame_ms);
        let pair = gr00t_backbone(&o.checkpoint, &o.task, &clock, period, &o.ep)?;
        publish(pair, clock, link, &o.endpoint, stop)
    }

    /// Publish the features of `source` → `encoder` on `link` (`listen`) until `stop`.
    fn publish(
        (source, encoder, what): SlowPair,
        clock: Arc<dyn Clock>,
        link: Link,
        endpoint: &super::SlowEndpointOptions,
        stop: Arc<AtomicBool>,
    ) -> Result<()> {
        let (listen, key, frame_ms) = (&endpoint.listen, &endpoint.key, endpoint.frame_ms);
        let cfg = SlowServerConfig {
            link,
            key: key.to_string(),
        };
        eprintln!(
            "serving slow features ({what}, one frame per {frame_ms} ms) on {listen}, \
             key {key} (Ctrl-C to stop)"
        );
        serve_slow(source, encoder, clock, &cfg, stop)
            .with_context(|| format!("serving slow features on {listen}"))
    }

    /// Serve, then say on stderr what was served and refused (also when serving failed).
    fn serve_counted<M: VelocityModel>(
        model: M,
        cfg: &PolicyServerConfig,
        stop: Arc<AtomicBool>,
    ) -> pir2_runtime::remote::Result<()> {
        let stats = Arc::new(PolicyServerStats::default());
        let r = serve_policy_counted(model, cfg, stop, stats.clone());
        let c = stats.counters();
        eprintln!(
            "policy server: {} requests, {} answered; refused: {} oversized, {} batch too large, \
             {} malformed, {} model errors, {} model panics, {} without a session (no handshake \
             with this server); {} replies not delivered",
            c.requests,
            c.answered,
            c.oversized,
            c.too_large_batch,
            c.malformed,
            c.model_errors,
            c.model_panics,
            c.no_session,
            c.reply_failures
        );
        r
    }

    /// Says on stderr when the first request was answered (a client is being served).
    struct Announce<M> {
        inner: M,
        calls: u64,
    }

    impl<M> Announce<M> {
        fn new(inner: M) -> Self {
            Announce { inner, calls: 0 }
        }
    }

    impl<M: VelocityModel> VelocityModel for Announce<M> {
        fn backend(&self) -> &'static str {
            self.inner.backend()
        }
        fn velocity(
            &mut self,
            input: &ModelInput<'_>,
            out: &mut [f32],
        ) -> pir2_runtime::Result<()> {
            let r = self.inner.velocity(input, out);
            self.calls += 1;
            if self.calls == 1 {
                eprintln!("answered the first request");
            }
            r
        }
    }

    /// The GR00T action head of a checkpoint, with the VL layout of `task`'s prompt.
    #[cfg(feature = "gr00t")]
    fn gr00t_head(
        dir: &std::path::Path,
        task: &str,
        ep: &crate::ep::EpOptions,
    ) -> Result<(Box<dyn VelocityModel>, String)> {
        let ort = ep.ort()?;
        let (head, prompt) = pir2_backends::gr00t::load_action_head(dir, task, &ort)
            .with_context(|| format!("loading the GR00T action head from {}", dir.display()))?;
        let d = *head.dims();
        Ok((
            Box::new(head),
            format!(
                "GR00T action head of {} (H {}, A {}, D_vl {}; prompt {prompt:?}) on {}",
                dir.display(),
                d.horizon,
                d.action_dim,
                d.d_vl,
                ort.provider.describe()
            ),
        ))
    }

    #[cfg(not(feature = "gr00t"))]
    fn gr00t_head(
        _: &std::path::Path,
        _: &str,
        _: &crate::ep::EpOptions,
    ) -> Result<(Box<dyn VelocityModel>, String)> {
        anyhow::bail!(
            "`pir2 gr00t serve policy` needs a pir2 built with feature `gr00t` \
             (--features gr00t,remote)"
        )
    }

    type SlowPair = (Box<dyn SlowSource>, Box<dyn SlowEncoder>, String);

    #[cfg(feature = "gr00t")]
    fn gr00t_backbone(
        dir: &std::path::Path,
        task: &str,
        clock: &Arc<dyn Clock>,
        period: Duration,
        ep: &crate::ep::EpOptions,
    ) -> Result<SlowPair> {
        use pir2_backends::gr00t::testing::SyntheticCamera;
        use pir2_backends::gr00t::Gr00tBackbone;
        let ort = ep.ort()?;
        let (bb, prompt) = Gr00tBackbone::for_checkpoint(dir, task, &ort)
            .with_context(|| format!("loading the GR00T backbone from {}", dir.display()))?;
        let (t, d) = bb.output_shape();
        let what = bb.describe();
        Ok((
            Box::new(SyntheticCamera::with_views(
                clock.clone(),
                period,
                bb.views(),
            )),
            Box::new(bb),
            format!(
                "GR00T backbone {} [{t}×{d}] of {} on {}, synthetic camera, prompt {prompt:?}",
                what,
                dir.display(),
                ort.provider.describe()
            ),
        ))
    }

    #[cfg(not(feature = "gr00t"))]
    fn gr00t_backbone(
        _: &std::path::Path,
        _: &str,
        _: &Arc<dyn Clock>,
        _: Duration,
        _: &crate::ep::EpOptions,
    ) -> Result<SlowPair> {
        anyhow::bail!(
            "`pir2 gr00t serve slow` needs a pir2 built with feature `gr00t` \
             (--features gr00t,remote)"
        )
    }
}
