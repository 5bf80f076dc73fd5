//! The velocity-model trait every backend implements.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// The slow-channel input of a model call.
#[derive(Debug, Clone, Copy)]
pub enum SlowInput<'a> {
    /// The model takes no slow input.
    None,
    /// A feature vector per sample: `data` is `[B, dim]`.
    Vector {
        /// Flat `[B, dim]` data.
        data: &'a [f32],
        /// Feature width.
        dim: usize,
    },
    /// Tokens per sample: `data` is `[B, tokens, dim]`.
    Tokens {
        /// Flat `[B, tokens, dim]` data.
        data: &'a [f32],
        /// Tokens per sample.
        tokens: usize,
        /// Token width.
        dim: usize,
    },
}

/// The slow-channel layout a model expects: the shape side of [`SlowInput`], shared by the
/// model configurations, the ONNX contract and the checkpoints.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SlowSpec {
    /// No slow input.
    #[default]
    None,
    /// One feature vector of width `dim` per sample (`[B, S]`).
    Vector {
        /// Feature width `S`.
        dim: usize,
    },
    /// `tokens` tokens of width `dim` per sample (`[B, T, D]`).
    Tokens {
        /// Tokens `T`.
        tokens: usize,
        /// Token width `D`.
        dim: usize,
    },
}

impl SlowSpec {
    /// Values per sample (`S` or `T·D`).
    pub fn len(&self) -> usize {
        match *self {
            SlowSpec::None => 0,
            SlowSpec::Vector { dim } => dim,
            SlowSpec::Tokens { tokens, dim } => tokens * dim,
        }
    }

    /// Whether there is no slow input.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Width of one slow feature (the normalisation width): `S` or `D`.
    pub fn width(&self) -> usize {
        match *self {
            SlowSpec::None => 0,
            SlowSpec::Vector { dim } | SlowSpec::Tokens { dim, .. } => dim,
        }
    }

    /// Number of tokens (1 for a vector, 0 for none).
    pub fn tokens(&self) -> usize {
        match *self {
            SlowSpec::None => 0,
            SlowSpec::Vector { .. } => 1,
            SlowSpec::Tokens { tokens, .. } => tokens,
        }
    }

    /// Does a call's slow input match this spec?
    pub fn matches(&self, slow: &SlowInput<'_>) -> bool {
        match (self, slow) {
            (SlowSpec::None, SlowInput::None) => true,
            (SlowSpec::Vector { dim }, SlowInput::Vector { dim: d, .. }) => dim == d,
            (
                SlowSpec::Tokens { tokens, dim },
                SlowInput::Tokens {
                    tokens: t, dim: d, ..
                },
            ) => tokens == t && dim == d,
            _ => false,
        }
    }

    /// Human-readable shape, e.g. `[B, 9]`.
    pub fn describe(&self) -> String {
        match self {
            SlowSpec::None => "none".to_string(),
            SlowSpec::Vector { dim } => format!("[B, {dim}]"),
            SlowSpec::Tokens { tokens, dim } => format!("[B, {tokens}, {dim}]"),
        }
    }
}

/// One batched model call. All tensors are flat, row-major, `f32`.
#[derive(Debug, Clone, Copy)]
pub struct ModelInput<'a> {
    /// Batch size `B`.
    pub batch: usize,
    /// Chunk length `H`.
    pub horizon: usize,
    /// Action dimension `A`.
    pub action_dim: usize,
    /// Noisy chunk `x`: `[B, H, A]`.
    pub x: &'a [f32],
    /// Per-position noise level `τ`: `[B, H]` (0 = noise, 1 = clean;
    /// [`pir2_schedule::HIDDEN_FRONT_TAU`] marks a hidden front slot).
    pub tau: &'a [f32],
    /// Fast observation history: `[B, n_obs, fast_dim]`, oldest first.
    pub obs_fast: &'a [f32],
    /// History length `n_obs`.
    pub n_obs: usize,
    /// Fast observation width.
    pub fast_dim: usize,
    /// Slow features.
    pub slow: SlowInput<'a>,
    /// Age of the slow features in control ticks: `[B]`.
    pub d_vis: &'a [u32],
}

impl ModelInput<'_> {
    /// Check every length against the declared sizes; one error naming the tensor.
    pub fn validate(&self) -> Result<()> {
        let b = self.batch;
        let chk = |what: &str, got: usize, want: usize| -> Result<()> {
            if got != want {
                Err(Error::shape(what, want, got))
            } else {
                Ok(())
            }
        };
        chk(
            "x [B,H,A]",
            self.x.len(),
            b * self.horizon * self.action_dim,
        )?;
        chk("tau [B,H]", self.tau.len(), b * self.horizon)?;
        chk(
            "obs_fast [B,n_obs,F]",
            self.obs_fast.len(),
            b * self.n_obs * self.fast_dim,
        )?;
        chk("d_vis [B]", self.d_vis.len(), b)?;
        match self.slow {
            SlowInput::None => Ok(()),
            SlowInput::Vector { data, dim } => chk("obs_slow [B,S]", data.len(), b * dim),
            SlowInput::Tokens { data, tokens, dim } => {
                chk("obs_slow [B,T,D]", data.len(), b * tokens * dim)
            }
        }
    }
}

/// Raised by the real-time driver when a run stops (the robot is stopped first), so a model
/// whose call can block for long (a remote head retrying a server that is gone) gives the
/// call up instead of holding the run's exit; see [`VelocityModel::watch_stop`].
#[derive(Debug, Clone, Default)]
pub struct StopSignal(std::sync::Arc<std::sync::atomic::AtomicBool>);

impl StopSignal {
    /// A signal not raised yet.
    pub fn new() -> Self {
        Self::default()
    }
    /// Raise it (every clone sees it).
    pub fn raise(&self) {
        self.0.store(true, std::sync::atomic::Ordering::SeqCst);
    }
    /// Whether it was raised.
    pub fn is_raised(&self) -> bool {
        self.0.load(std::sync::atomic::Ordering::SeqCst)
    }
}

/// A flow-matching velocity model `v(x, τ, obs_fast, obs_slow, d_vis)`.
///
/// `velocity` writes `[B, H, A]` into `out`. Backends keep their scratch memory inside
/// `self`, hence `&mut self`. Optional capabilities are default methods that return
/// [`Error::Unsupported`].
pub trait VelocityModel: Send {
    /// The backend's name (e.g. "candle", "onnxruntime", "libtorch").
    fn backend(&self) -> &'static str;
    /// Evaluate one NFE.
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()>;
    /// Export to an ONNX file (optional capability).
    fn export_onnx(&self, _path: &std::path::Path) -> Result<()> {
        Err(Error::Unsupported {
            capability: "ONNX export",
            backend: self.backend(),
        })
    }
    /// Called by the real-time driver before the first call with the run's [`StopSignal`].
    /// A model whose call can block for long should, once it is raised, end the call with
    /// [`Error::Abandoned`] (the driver then ignores it: the run is already stopping).
    /// Default: nothing (a local model's call is short).
    fn watch_stop(&mut self, _stop: StopSignal) {}
}

impl<M: VelocityModel + ?Sized> VelocityModel for Box<M> {
    fn backend(&self) -> &'static str {
        (**self).backend()
    }
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        (**self).velocity(input, out)
    }
    fn export_onnx(&self, path: &std::path::Path) -> Result<()> {
        (**self).export_onnx(path)
    }
    fn watch_stop(&mut self, stop: StopSignal) {
        (**self).watch_stop(stop)
    }
}
