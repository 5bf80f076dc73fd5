//! `pir2 serve policy|slow` (feature `remote`); the robot side of `pir2 eval --remote` and
//! the TLS options are [`crate::remote`]'s.
//!
//! Transport, wire format, clock sync and fault handling are `pir2_runtime::remote`'s (Zenoh
//! peers with multicast and gossip scouting off: they meet only through the given
//! endpoints). This module chooses the models:
//!
//! - `serve policy --checkpoint DIR`: a candle checkpoint (e.g. `pir2 train`'s `best/`)
//!   answers one-NFE requests; `pir2 eval --remote ENDPOINT` sends the ball-plate
//!   evaluation's action-head calls there ([`crate::remote::RemotePolicy::models`] is a model factory for
//!   the study pipeline's one closed loop) (the lock-step eval is deterministic, so the result
//!   equals the local eval's, outages included: a call is retried until the server answers or
//!   `max_failed_calls` timeouts in a row stop the run);
//! - `serve slow`: a camera + backbone publishing features with capture times, either the
//!   GR00T ONNX backbone (`--gr00t-checkpoint DIR --task …`, needs feature `gr00t`, synthetic
//!   camera) or a stub (`--stub DIM`: a counter camera and a pass-through encoder), for
//!   `pir2 run gr00t-xarm-xhand --remote-slow ENDPOINT`.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::Result;

use crate::remote::TlsOptions;
#[cfg(not(feature = "remote"))]
use crate::remote::NO_REMOTE;

/// What `pir2 serve …` runs.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum ServeOptions {
    /// Answer action-head (one-NFE) requests until Ctrl-C: a candle checkpoint
    /// (`--checkpoint`, for `pir2 eval --remote`) or a GR00T export's ONNX action head
    /// (`--gr00t-checkpoint --task`, for `pir2 run … --remote-policy`).
    Policy {
        /// Candle checkpoint directory (config.json, stats.json, model.safetensors), e.g. the
        /// `best/` directory `pir2 train` writes.
        #[arg(
            long,
            required_unless_present = "gr00t_checkpoint",
            conflicts_with = "gr00t_checkpoint"
        )]
        checkpoint: Option<PathBuf>,
        /// With --checkpoint: the policy the checkpoint must have been trained as (refused
        /// by name if its `identity.json` records another). The server announces the
        /// checkpoint's identity (policy, weights SHA-256) to `pir2 eval --remote`, which
        /// refuses a server running another policy or other weights.
        #[arg(long, requires = "checkpoint", value_parser = crate::tasks::policy_parser())]
        policy: Option<pir2_runtime::Policy>,
        /// A GR00T export (docs/gr00t-contract.md): its action head (four ONNX graphs + side
        /// weights + statistics) is served; feature `gr00t`.
        #[arg(long, requires = "task")]
        gr00t_checkpoint: Option<PathBuf>,
        /// With --gr00t-checkpoint: the task (key or prompt) whose prompt layout (image and
        /// text token masks) the DiT is fed; must be the robot's `--task`.
        #[arg(long)]
        task: Option<String>,
        /// Hold every reply this many ms: a stand-in for a slow network (tests, measuring how
        /// `d` follows the round trip). Zero in deployment.
        #[arg(long, default_value_t = 0)]
        inject_delay_ms: u64,
        /// Zenoh endpoint to listen on.
        #[arg(long, default_value = "tcp/127.0.0.1:7447")]
        listen: String,
        /// Key the requests arrive on.
        #[arg(long, default_value = "pir2/policy")]
        key: String,
        /// Mutual TLS and `--insecure`.
        #[command(flatten)]
        tls: TlsOptions,
        /// Where ONNX Runtime runs the GR00T action head.
        #[command(flatten)]
        ep: crate::ep::EpOptions,
    },
    /// Publish slow-channel features (camera → backbone) with capture times until Ctrl-C.
    Slow {
        /// Zenoh endpoint to listen on.
        #[arg(long, default_value = "tcp/127.0.0.1:7448")]
        listen: String,
        /// Key the features are published on (clock pings on `<key>/clock`).
        #[arg(long, default_value = "pir2/slow")]
        key: String,
        /// The GR00T ONNX backbone of this checkpoint (feature `gr00t`) on a synthetic camera.
        #[arg(long, required_unless_present = "stub", conflicts_with = "stub")]
        gr00t_checkpoint: Option<PathBuf>,
        /// Task (key or prompt) whose prompt the GR00T backbone encodes.
        #[arg(long, requires = "gr00t_checkpoint")]
        task: Option<String>,
        /// A stub: a counter camera of this many values and a pass-through encoder.
        #[arg(long)]
        stub: Option<usize>,
        /// Camera frame period, ms.
        #[arg(long, default_value_t = 60)]
        frame_ms: u64,
        /// Mutual TLS and `--insecure`.
        #[command(flatten)]
        tls: TlsOptions,
        /// Where ONNX Runtime runs the GR00T backbone.
        #[command(flatten)]
        ep: crate::ep::EpOptions,
    },
}

/// Run a server until `stop` (Ctrl-C).
#[cfg(feature = "remote")]
pub fn serve(cmd: &ServeOptions, stop: Arc<AtomicBool>) -> Result<()> {
    imp::serve(cmd, stop)
}

/// Without feature `remote` there is no transport.
#[cfg(not(feature = "remote"))]
pub fn serve(_cmd: &ServeOptions, _stop: Arc<AtomicBool>) -> Result<()> {
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

    use super::ServeOptions;

    pub(super) fn serve(cmd: &ServeOptions, stop: Arc<AtomicBool>) -> Result<()> {
        match cmd {
            ServeOptions::Policy {
                checkpoint,
                policy,
                gr00t_checkpoint,
                task,
                inject_delay_ms,
                listen,
                key,
                tls,
                ep,
            } => {
                let mut cfg = PolicyServerConfig {
                    link: tls.apply(Link::listen(listen.clone()))?,
                    key: key.clone(),
                    reply_delay: Duration::from_millis(*inject_delay_ms),
                    ..Default::default()
                };
                let delay = if *inject_delay_ms > 0 {
                    format!(", every reply held {inject_delay_ms} ms")
                } else {
                    String::new()
                };
                let ctx = || format!("serving the policy on {listen}");
                match (checkpoint, gr00t_checkpoint) {
                    (Some(ck), _) => {
                        let model = CandleModel::load(ck)
                            .with_context(|| format!("loading checkpoint {}", ck.display()))?;
                        if let Some(p) = policy {
                            crate::identity::expect_policy(&model, ck, *p, "--policy")?;
                        }
                        cfg.identity = crate::identity::announce(&model);
                        eprintln!(
                            "serving {} ({}) on {listen}, key {key}{delay} (Ctrl-C to stop)",
                            ck.display(),
                            model.backend()
                        );
                        serve_counted(Announce::new(model), &cfg, stop).with_context(ctx)
                    }
                    (None, Some(dir)) => {
                        let task = task
                            .as_deref()
                            .context("--task is required with --gr00t-checkpoint")?;
                        let (model, what) = gr00t_head(dir, task, ep)?;
                        eprintln!("serving {what} on {listen}, key {key}{delay} (Ctrl-C to stop)");
                        serve_counted(Announce::new(model), &cfg, stop).with_context(ctx)
                    }
                    (None, None) => {
                        anyhow::bail!("give --checkpoint DIR or --gr00t-checkpoint DIR --task T")
                    }
                }
            }
            ServeOptions::Slow {
                listen,
                key,
                gr00t_checkpoint,
                task,
                stub,
                frame_ms,
                tls,
                ep,
            } => {
                let link = tls.apply(Link::listen(listen.clone()))?;
                let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
                let period = Duration::from_millis(*frame_ms);
                let (source, encoder, what): (Box<dyn SlowSource>, Box<dyn SlowEncoder>, String) =
                    match (gr00t_checkpoint, stub) {
                        (Some(dir), _) => gr00t_backbone(dir, task.as_deref(), &clock, period, ep)?,
                        (None, Some(dim)) => (
                            Box::new(CameraStub::new(clock.clone(), period, *dim)),
                            Box::new(PassThroughEncoder {
                                latency: Duration::ZERO,
                            }),
                            format!("stub camera ({dim} values) + pass-through encoder"),
                        ),
                        (None, None) => anyhow::bail!("give --gr00t-checkpoint DIR or --stub DIM"),
                    };
                let cfg = SlowServerConfig {
                    link,
                    key: key.clone(),
                };
                eprintln!(
                    "serving slow features ({what}, one frame per {frame_ms} ms) on {listen}, \
                     key {key} (Ctrl-C to stop)"
                );
                serve_slow(source, encoder, clock, &cfg, stop)
                    .with_context(|| format!("serving slow features on {listen}"))
            }
        }
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
        anyhow::bail!("--gr00t-checkpoint needs a pir2 built with feature `gr00t`")
    }

    type SlowPair = (Box<dyn SlowSource>, Box<dyn SlowEncoder>, String);

    #[cfg(feature = "gr00t")]
    fn gr00t_backbone(
        dir: &std::path::Path,
        task: Option<&str>,
        clock: &Arc<dyn Clock>,
        period: Duration,
        ep: &crate::ep::EpOptions,
    ) -> Result<SlowPair> {
        use pir2_backends::gr00t::testing::SyntheticCamera;
        use pir2_backends::gr00t::Gr00tBackbone;
        let task = task.context("--task is required with --gr00t-checkpoint")?;
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
        _: Option<&str>,
        _: &Arc<dyn Clock>,
        _: Duration,
        _: &crate::ep::EpOptions,
    ) -> Result<SlowPair> {
        anyhow::bail!("--gr00t-checkpoint needs a pir2 built with feature `gr00t`")
    }
}
