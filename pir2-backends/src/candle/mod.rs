//! The candle backend: pure-Rust models that train and run on the CPU.
//!
//! [`CandleModel`] wraps one architecture ([`crate::config::ModelConfig`]) together with its
//! normalisation [`Stats`]. It implements [`VelocityModel`] in **normalised action space**
//! (see [`crate::config`]); observations are passed raw and normalised inside.
//!
//! One file on purpose (the architectures, layers and kernels are submodules): a
//! [`CandleModel`]'s weights live twice, as candle `Var`s and as host copies for the batch-1
//! fast paths, and every method that changes one (training, restoring, loading) marks or
//! refreshes the other; loading, saving, encoding and both forward paths stay beside the
//! fields they keep in step.
//!
//! ```
//! use pir2_backends::candle::CandleModel;
//! use pir2_backends::config::{Config, ModelConfig, MlpConfig, Spec, SlowSpec, Stats};
//! use pir2_runtime::model::{ModelInput, SlowInput, VelocityModel};
//! let spec = Spec { horizon: 4, action_dim: 2, n_obs: 2, fast_dim: 3, slow: SlowSpec::None, d_vis_max: 0 };
//! let cfg = Config { spec, model: ModelConfig::Mlp(MlpConfig { width: 32, depth: 2, ..Default::default() }) };
//! let mut m = CandleModel::new(cfg, Stats::identity(&spec), 0).unwrap();
//! let (x, tau, obs) = (vec![0.0; 8], vec![0.5; 4], vec![0.0; 6]);
//! let input = ModelInput { batch: 1, horizon: 4, action_dim: 2, x: &x, tau: &tau, obs_fast: &obs,
//!     n_obs: 2, fast_dim: 3, slow: SlowInput::None, d_vis: &[0] };
//! let mut v = vec![0.0; 8];
//! m.velocity(&input, &mut v).unwrap();
//! ```

mod device;
pub(crate) mod dit;
pub mod export;
pub(crate) mod kernels;
pub(crate) mod layers;
pub(crate) mod mlp;
pub(crate) mod unet;
pub(crate) mod unet_fast;

use std::path::Path;

use candle_core::{Device, Tensor, Var};
use pir2_runtime::model::{ModelInput, SlowInput, VelocityModel};

pub use device::device;

use crate::checkpoint::{self, Checkpoint};
use crate::config::{Config, ModelConfig, SlowSpec, Spec, Stats};
use crate::error::{Error, Result};
use layers::{CResult, ParamStore};

/// Run `f` with the candle kernels on a rayon pool of its own, as many threads as the global
/// pool has (the cores, or `RAYON_NUM_THREADS`).
///
/// The training and batched-inference kernels split their work over the pool they run in,
/// and how a run's numbers round depends on that pool's thread count, so the count is kept:
/// a job gets the same bits here as on the global pool. What changes is that jobs running
/// side by side on their own OS threads no longer queue on one shared pool: two
/// [64, 128, 256] U-Net trainings on two cores ran at about 1.0 step/s each sharing the
/// global pool of one process, and at 1.28-1.38 each with a pool each (separate processes).
pub fn with_kernel_pool<R: Send>(f: impl FnOnce() -> R + Send) -> Result<R> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(rayon::current_num_threads())
        .build()
        .map_err(|e| Error::config("threads", format!("cannot start a kernel thread pool: {e}")))?;
    Ok(pool.install(f))
}

/// Threads the candle kernels of a batched call split their work over (the rayon pool the
/// call runs in: the cores, or `RAYON_NUM_THREADS`). A batch-1 inference call runs on one
/// thread; a batched one's bits depend on this count.
pub fn kernel_threads() -> usize {
    rayon::current_num_threads()
}

/// Encoded, normalised inputs of one batch (shared by inference and training).
#[derive(Debug)]
pub(crate) struct Inputs {
    pub(crate) b: usize,
    /// `[B, H, A]` (normalised action space).
    pub(crate) x: Tensor,
    /// Raw per-position `τ`, `[B·H]` (may hold `HIDDEN_FRONT_TAU`).
    pub(crate) tau: Vec<f32>,
    /// Encoded fast history `[B, n_obs·F]`.
    pub(crate) fast: Tensor,
    /// Normalised slow features `[B, T, D]` (a vector is one token).
    pub(crate) slow: Option<Tensor>,
    /// Clamped slow ages `[B]` (u32).
    pub(crate) dvis: Tensor,
}

#[derive(Debug)]
enum Arch {
    Mlp(mlp::Mlp),
    UNet(Box<unet::UNet>),
    Dit(dit::Dit),
}

impl Arch {
    fn forward(&self, inp: &Inputs) -> CResult<Tensor> {
        match self {
            Arch::Mlp(m) => m.forward(inp),
            Arch::UNet(m) => m.forward(inp),
            Arch::Dit(m) => m.forward(inp),
        }
    }
}

/// Reusable host buffers for encoding.
#[derive(Debug, Default)]
struct Scratch {
    fast: Vec<f32>,
    slow: Vec<f32>,
    dvis: Vec<u32>,
    /// Host copy of the MLP weights for batch-1 calls; `None` = stale, rebuilt on demand.
    mlp_fast: Option<mlp::MlpFast>,
    /// The hand-written U-Net and a host copy of the weights (see [`CandleModel::set_fused`]).
    unet: Option<UNetHost>,
}

/// The U-Net's host kernels with the weights they run on.
#[derive(Debug)]
struct UNetHost {
    net: unet_fast::FastUNet,
    params: Vec<Vec<f32>>,
    /// The weights changed since `params` was copied.
    stale: bool,
}

/// A candle velocity model (MLP, U-Net or DiT) with its normalisation statistics.
#[derive(Debug)]
pub struct CandleModel {
    config: Config,
    stats: Stats,
    vars: Vec<(String, Var)>,
    net: Arch,
    scratch: Scratch,
    fused: bool,
    /// The policy the weights are trained as (recorded in the checkpoint's `identity.json`).
    policy: Option<pir2_runtime::Policy>,
    /// SHA-256 of the `model.safetensors` the weights were loaded from, until they change.
    loaded_sha256: Option<String>,
}

impl CandleModel {
    /// Build a freshly initialised model (deterministic in `seed`).
    pub fn new(config: Config, stats: Stats, seed: u64) -> Result<Self> {
        Self::build(config, stats, ParamStore::new(seed))
    }

    fn build(config: Config, stats: Stats, mut ps: ParamStore) -> Result<Self> {
        config.validate()?;
        stats.validate(&config.spec)?;
        let spec = config.spec;
        let net = match &config.model {
            ModelConfig::Mlp(c) => Arch::Mlp(mlp::Mlp::new(&mut ps, &spec, c)?),
            ModelConfig::UNet(c) => Arch::UNet(Box::new(unet::UNet::new(&mut ps, &spec, c)?)),
            ModelConfig::Dit(c) => Arch::Dit(dit::Dit::new(&mut ps, &spec, c)?),
        };
        Ok(Self {
            config,
            stats,
            vars: ps.vars,
            net,
            scratch: Scratch::default(),
            fused: true,
            policy: None,
            loaded_sha256: None,
        })
    }

    /// The policy (training schedule) the weights are trained as: what a loaded checkpoint's
    /// `identity.json` records (`None`: unrecorded, e.g. a checkpoint written before
    /// checkpoints recorded it), or what [`CandleModel::set_policy`] set.
    pub fn policy(&self) -> Option<pir2_runtime::Policy> {
        self.policy
    }

    /// Record the policy the model is trained as; [`CandleModel::save`] (and every step
    /// checkpoint of the trainer) writes it to `identity.json`.
    pub fn set_policy(&mut self, policy: Option<pir2_runtime::Policy>) {
        self.policy = policy;
    }

    /// SHA-256 (lowercase hex) of the `model.safetensors` this model was loaded from
    /// ([`crate::checkpoint::weights_sha256`]), while its weights are unchanged since.
    pub fn weights_sha256(&self) -> Option<&str> {
        self.loaded_sha256.as_deref()
    }

    /// The configuration.
    pub fn config(&self) -> &Config {
        &self.config
    }
    /// The input/output spec.
    pub fn spec(&self) -> &Spec {
        &self.config.spec
    }
    /// The normalisation statistics (use [`Stats::normalize_action`] /
    /// [`Stats::denormalize_action`] around the runtime's action buffer).
    pub fn stats(&self) -> &Stats {
        &self.stats
    }
    /// Trainable variables in creation order, with their checkpoint names.
    pub fn vars(&self) -> &[(String, Var)] {
        &self.vars
    }
    /// Tell the model its weights were changed through [`CandleModel::vars`] (drops the
    /// host copy the batch-1 MLP path keeps). The trainer and [`CandleModel::restore`] call it.
    pub fn weights_changed(&mut self) {
        self.loaded_sha256 = None;
        self.scratch.mlp_fast = None;
        if let Some(u) = self.scratch.unet.as_mut() {
            u.stale = true;
        }
    }

    /// Use the hand-written host kernels for the U-Net (default `true`): inference through
    /// [`VelocityModel::velocity`] at any batch size, and training in [`crate::train`]. They
    /// compute the same function as the candle graph ([`CandleModel::forward_input`], which
    /// always uses candle) up to float rounding; `false` selects the candle graph everywhere
    /// (the reference, e.g. for benchmarks). No effect on the MLP and DiT.
    pub fn set_fused(&mut self, on: bool) {
        self.fused = on;
    }

    /// Whether the hand-written kernels are used for this model (a U-Net with
    /// [`CandleModel::set_fused`] on).
    pub fn fused(&self) -> bool {
        self.fused && matches!(self.net, Arch::UNet(_))
    }

    /// A fresh instance of the U-Net host kernels (own buffers), if the model is a U-Net.
    pub(crate) fn fast_unet(&self) -> Result<Option<unet_fast::FastUNet>> {
        let ModelConfig::UNet(c) = &self.config.model else {
            return Ok(None);
        };
        let names: Vec<&str> = self.vars.iter().map(|(n, _)| n.as_str()).collect();
        Ok(Some(unet_fast::FastUNet::new(
            &self.config.spec,
            c,
            &names,
        )?))
    }

    /// Host copies of every weight (same order as [`CandleModel::vars`]).
    pub(crate) fn host_params(&self) -> Result<Vec<Vec<f32>>> {
        Ok(self
            .vars
            .iter()
            .map(|(_, v)| v.flatten_all()?.to_vec1::<f32>())
            .collect::<CResult<Vec<_>>>()?)
    }

    /// Overwrite every weight from host copies (same order as [`CandleModel::vars`]).
    pub(crate) fn set_host_params(&mut self, params: &[Vec<f32>]) -> Result<()> {
        if params.len() != self.vars.len() {
            return Err(Error::shape("weights", self.vars.len(), params.len()));
        }
        for ((_, v), p) in self.vars.iter().zip(params) {
            v.set(&Tensor::from_slice(p, v.shape(), &Device::Cpu)?)?;
        }
        self.weights_changed();
        Ok(())
    }

    /// Validate and encode a runtime input into host buffers (normalised fast history, slow
    /// features, clamped ages) for the host kernels.
    pub(crate) fn host_batch<'a>(
        &'a mut self,
        input: &ModelInput<'a>,
    ) -> Result<unet_fast::HostBatch<'a>> {
        self.encode_host(input)?;
        let sc = &self.scratch;
        Ok(unet_fast::HostBatch {
            b: input.batch,
            x: input.x,
            tau: input.tau,
            fast: &sc.fast,
            slow: &sc.slow,
            dvis: &sc.dvis,
        })
    }

    /// Number of scalar parameters.
    pub fn num_params(&self) -> usize {
        self.vars.iter().map(|(_, v)| v.elem_count()).sum()
    }

    /// A copy of every weight (same order as [`CandleModel::vars`]).
    pub fn snapshot(&self) -> Result<Vec<Tensor>> {
        Ok(self
            .vars
            .iter()
            .map(|(_, v)| v.as_tensor().detach().copy())
            .collect::<CResult<Vec<_>>>()?)
    }

    /// Overwrite every weight from a [`CandleModel::snapshot`].
    pub fn restore(&mut self, weights: &[Tensor]) -> Result<()> {
        if weights.len() != self.vars.len() {
            return Err(Error::shape("weights", self.vars.len(), weights.len()));
        }
        for ((_, v), w) in self.vars.iter().zip(weights) {
            v.set(w)?;
        }
        self.weights_changed();
        Ok(())
    }

    /// Save into a new directory (`config.json`, `stats.json`, `model.safetensors`).
    /// Fails if `dir` exists.
    pub fn save(&self, dir: &Path) -> Result<()> {
        checkpoint::create_dir_durably(dir, |tmp| self.write_files(tmp))
    }

    /// The checkpoint's files (config, stats, weights) in the existing directory `dir`.
    pub(crate) fn write_files(&self, dir: &Path) -> Result<()> {
        let mut owned = Vec::with_capacity(self.vars.len());
        for (n, v) in &self.vars {
            owned.push((
                n.clone(),
                v.dims().to_vec(),
                v.flatten_all()?.to_vec1::<f32>()?,
            ));
        }
        checkpoint::write_files(
            dir,
            &self.config,
            &self.stats,
            self.policy,
            owned
                .iter()
                .map(|(n, s, d)| (n.clone(), s.clone(), d.as_slice())),
        )
    }

    /// Load a checkpoint directory; every tensor must be present with the right shape, and
    /// no extra tensors may be present (errors name the tensor).
    pub fn load(dir: &Path) -> Result<Self> {
        let mut ck = Checkpoint::load(dir)?;
        // Every tensor must match the file exactly (below), so a model needing far more
        // weights than the file holds is a bad config.json: refused before its layers are
        // allocated. The slack (4× the file, at least 2^24 values) lets a checkpoint that
        // merely lacks a tensor build and fail below with the tensor's name.
        let held = ck
            .tensors
            .values()
            .fold(0usize, |a, t| a.saturating_add(t.data.len()));
        let budget = held.saturating_mul(4).max(1 << 24);
        let model = Self::build(
            ck.config.clone(),
            ck.stats.clone(),
            ParamStore::with_budget(0, budget),
        )?;
        for (name, var) in &model.vars {
            let t = ck.take(name, var.dims())?;
            var.set(&Tensor::from_vec(t.data, t.shape, &Device::Cpu)?)?;
        }
        ck.expect_consumed()?;
        let mut model = model;
        model.weights_changed();
        model.policy = ck.identity.as_ref().and_then(|i| i.policy);
        model.loaded_sha256 = Some(ck.weights_sha256);
        Ok(model)
    }

    /// Start a finetune: a new model with `config` (same spec as the checkpoint) whose weights
    /// come from the checkpoint wherever it has them. Tensors the checkpoint lacks must be
    /// zero-initialised extensions (the ablation's `film_pos`, the `d_vis` / delay
    /// embeddings) or per-position modulation heads, which start as copies of the checkpoint's
    /// shared head of the same layer (`<layer>_heads.*` ← `<layer>.*`: the U-Net's
    /// `film_heads`, the DiT's `ada_heads`; the shared head is then consumed). So the new model computes exactly what the checkpoint did at a
    /// position-uniform `τ`: a shared-FiLM U-Net finetuned with heads starts position-uniform
    /// and its heads specialise in training. Any other missing tensor, a shape mismatch or a
    /// leftover tensor is an error naming it.
    pub fn init_from(dir: &Path, config: Config) -> Result<Self> {
        let mut ck = Checkpoint::load(dir)?;
        ck.config.spec.expect_eq(&config.spec)?;
        let mut model = Self::new(config, ck.stats.clone(), 0)?;
        let extension =
            |n: &str| n.contains("film_pos.") || n == "dvis_embed" || n == "delay_embed";
        for (name, var) in &model.vars {
            if extension(name) && !ck.tensors.contains_key(name) {
                continue;
            }
            let dims = var.dims();
            // `<layer>_heads.{weight,bias}` ← `<layer>.{weight,bias}` (U-Net `film_heads`,
            // DiT `ada_heads`).
            let shared = ["weight", "bias"]
                .iter()
                .find_map(|k| {
                    name.strip_suffix(&format!("_heads.{k}"))
                        .map(|layer| format!("{layer}.{k}"))
                })
                .filter(|s| !ck.tensors.contains_key(name) && ck.tensors.contains_key(s));
            let data = match shared {
                Some(s) => {
                    let t = ck.take(&s, &dims[1..])?;
                    let n: usize = dims.iter().product();
                    t.data.iter().copied().cycle().take(n).collect()
                }
                None => ck.take(name, dims)?.data,
            };
            var.set(&Tensor::from_vec(data, dims, &Device::Cpu)?)?;
        }
        ck.expect_consumed()?;
        model.weights_changed();
        Ok(model)
    }

    /// Load a checkpoint and check it was built for `spec` (error names the differing field).
    pub fn load_expect(dir: &Path, spec: &Spec) -> Result<Self> {
        let m = Self::load(dir)?;
        spec.expect_eq(m.spec())?;
        Ok(m)
    }

    /// Check the runtime input against the spec and encode it (normalise, build tensors).
    pub(crate) fn encode(&mut self, input: &ModelInput<'_>) -> Result<Inputs> {
        let slow_shape = self.encode_host(input)?;
        let spec = self.config.spec;
        let b = input.batch;
        let sc = &self.scratch;
        let slow = match slow_shape {
            None => None,
            Some((t, d)) => Some(Tensor::from_slice(&sc.slow, (b, t, d), &Device::Cpu)?),
        };
        Ok(Inputs {
            b,
            x: Tensor::from_slice(input.x, (b, spec.horizon, spec.action_dim), &Device::Cpu)?,
            tau: input.tau.to_vec(),
            fast: Tensor::from_slice(&sc.fast, (b, spec.fast_encoded_dim()), &Device::Cpu)?,
            slow,
            dvis: Tensor::from_slice(&sc.dvis, b, &Device::Cpu)?,
        })
    }

    /// Validate and normalise into the host scratch buffers; returns the slow `(T, D)`.
    fn encode_host(&mut self, input: &ModelInput<'_>) -> Result<Option<(usize, usize)>> {
        input
            .validate()
            .map_err(|e| Error::shape("model input", "consistent lengths", e.to_string()))?;
        let spec = self.config.spec;
        let eq = |what: &'static str, want: usize, got: usize| -> Result<()> {
            if want != got {
                Err(Error::shape(what, want, got))
            } else {
                Ok(())
            }
        };
        eq("horizon", spec.horizon, input.horizon)?;
        eq("action_dim", spec.action_dim, input.action_dim)?;
        eq("n_obs", spec.n_obs, input.n_obs)?;
        eq("fast_dim", spec.fast_dim, input.fast_dim)?;
        let b = input.batch;
        if b == 0 {
            return Err(Error::shape("batch", ">= 1", 0));
        }
        let sc = &mut self.scratch;
        let fe = spec.fast_encoded_dim();
        sc.fast.resize(b * fe, 0.0);
        let raw = spec.n_obs * spec.fast_dim;
        for i in 0..b {
            self.stats.encode_fast(
                &input.obs_fast[i * raw..(i + 1) * raw],
                spec.n_obs,
                &mut sc.fast[i * fe..(i + 1) * fe],
            );
        }
        let slow_data = match (spec.slow, input.slow) {
            (SlowSpec::None, SlowInput::None) => None,
            (SlowSpec::Vector { dim }, SlowInput::Vector { data, dim: d2 }) if dim == d2 => {
                Some((data, 1, dim))
            }
            (
                SlowSpec::Tokens { tokens, dim },
                SlowInput::Tokens {
                    data,
                    tokens: t2,
                    dim: d2,
                },
            ) if tokens == t2 && dim == d2 => Some((data, tokens, dim)),
            (want, got) => {
                return Err(Error::shape(
                    "obs_slow",
                    want,
                    format!("{got:?}").chars().take(80).collect::<String>(),
                ))
            }
        };
        let shape = match slow_data {
            None => {
                sc.slow.clear();
                None
            }
            Some((data, t, d)) => {
                sc.slow.resize(data.len(), 0.0);
                self.stats.encode_slow(data, &mut sc.slow);
                Some((t, d))
            }
        };
        sc.dvis.clear();
        sc.dvis
            .extend(input.d_vis.iter().map(|&d| d.min(spec.d_vis_max as u32)));
        Ok(shape)
    }

    /// Differentiable forward pass on encoded inputs: `[B, H, A]`.
    pub(crate) fn forward(&self, inp: &Inputs) -> Result<Tensor> {
        Ok(self.net.forward(inp)?)
    }

    /// Standard `K`-step Euler sampling from pure noise (shared `τ`), batch 1. Returns the
    /// chunk `[H, A]` in **raw** action units (denormalised).
    pub fn sample_euler(
        &mut self,
        obs_fast: &[f32],
        slow: SlowInput<'_>,
        d_vis: u32,
        steps: usize,
        rng: &mut pir2_schedule::Rng,
    ) -> Result<Vec<f32>> {
        let spec = self.config.spec;
        let (h, a) = (spec.horizon, spec.action_dim);
        let mut x = vec![0.0f32; h * a];
        rng.fill_normal(&mut x);
        let mut v = vec![0.0f32; h * a];
        let steps = steps.max(1);
        for k in 0..steps {
            let tau = vec![k as f32 / steps as f32; h];
            let input = ModelInput {
                batch: 1,
                horizon: h,
                action_dim: a,
                x: &x,
                tau: &tau,
                obs_fast,
                n_obs: spec.n_obs,
                fast_dim: spec.fast_dim,
                slow,
                d_vis: &[d_vis],
            };
            self.velocity_into(&input, &mut v)?;
            for (xi, vi) in x.iter_mut().zip(&v) {
                *xi += vi / steps as f32;
            }
        }
        self.stats.denormalize_action(&mut x);
        Ok(x)
    }

    /// One NFE into `out` (`[B, H, A]`), with this crate's error type.
    pub fn velocity_into(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        let want = input.batch * input.horizon * input.action_dim;
        if out.len() != want {
            return Err(Error::shape("out [B,H,A]", want, out.len()));
        }
        if input.batch == 1 && matches!(self.net, Arch::Mlp(_)) {
            // Batch-1 fast path: plain loops over a host copy of the weights.
            self.encode_host(input)?;
            if let Arch::Mlp(m) = &self.net {
                let sc = &mut self.scratch;
                if sc.mlp_fast.is_none() {
                    sc.mlp_fast = Some(mlp::MlpFast::from(m)?);
                }
                if let Some(fast) = sc.mlp_fast.as_mut() {
                    fast.forward(
                        m.freqs,
                        input.x,
                        input.tau,
                        (&sc.fast, &sc.slow, sc.dvis[0] as usize),
                        out,
                    );
                    return Ok(());
                }
            }
        }
        if self.fused() {
            return self.velocity_fused(input, out);
        }
        let v = self.forward_input(input)?;
        let v = v.flatten_all()?.to_vec1::<f32>()?;
        out.copy_from_slice(&v);
        Ok(())
    }

    /// The U-Net on the host kernels: single-threaded at batch 1 (no allocation once warm),
    /// on the rayon pool otherwise.
    fn velocity_fused(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        self.encode_host(input)?;
        if self.scratch.unet.is_none() {
            let net = self
                .fast_unet()?
                .ok_or_else(|| Error::shape("model", "U-Net", "another architecture"))?;
            self.scratch.unet = Some(UNetHost {
                net,
                params: Vec::new(),
                stale: true,
            });
        }
        let stale = self.scratch.unet.as_ref().is_some_and(|u| u.stale);
        if stale {
            let params = self.host_params()?;
            if let Some(u) = self.scratch.unet.as_mut() {
                u.params = params;
                u.stale = false;
            }
        }
        let par = if input.batch == 1 {
            kernels::parallelism(1)
        } else {
            kernels::parallelism(rayon::current_num_threads())
        };
        let sc = &mut self.scratch;
        let Some(u) = sc.unet.as_mut() else {
            return Err(Error::shape("model", "U-Net", "another architecture"));
        };
        let batch = unet_fast::HostBatch {
            b: input.batch,
            x: input.x,
            tau: input.tau,
            fast: &sc.fast,
            slow: &sc.slow,
            dvis: &sc.dvis,
        };
        out.copy_from_slice(u.net.forward(par, &u.params, &batch));
        Ok(())
    }

    /// Forward on a runtime input, returning the candle tensor (training, tests).
    pub fn forward_input(&mut self, input: &ModelInput<'_>) -> Result<Tensor> {
        let inp = self.encode(input)?;
        self.forward(&inp)
    }
}

impl VelocityModel for CandleModel {
    fn backend(&self) -> &'static str {
        "candle"
    }

    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        Ok(self.velocity_into(input, out)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MlpConfig;

    #[test]
    fn mlp_batch1_fast_path_matches_the_tensor_path() {
        let spec = Spec {
            horizon: 6,
            action_dim: 3,
            n_obs: 2,
            fast_dim: 4,
            slow: SlowSpec::Vector { dim: 2 },
            d_vis_max: 3,
        };
        let cfg = Config {
            spec,
            model: ModelConfig::Mlp(MlpConfig {
                width: 40,
                depth: 3,
                tau_freqs: 2,
                dvis_dim: 4,
            }),
        };
        let mut st = Stats::identity(&spec);
        st.fast.mean = vec![0.5; 4];
        st.slow.std = vec![2.0; 2];
        let mut m = CandleModel::new(cfg, st, 4).unwrap();
        // Non-zero delay embedding so the lookup is exercised.
        for (n, v) in m.vars() {
            if n == "dvis_embed" {
                v.set(&(v.as_tensor().ones_like().unwrap() * 0.3).unwrap())
                    .unwrap();
            }
        }
        m.weights_changed();
        let x: Vec<f32> = (0..18).map(|i| (i as f32 * 0.7).sin()).collect();
        let tau = [-1.0, 1.0, 0.8, 0.5, 0.2, 0.0];
        let obs: Vec<f32> = (0..8).map(|i| i as f32 * 0.1).collect();
        let slow = [0.3, -0.2];
        let input = ModelInput {
            batch: 1,
            horizon: 6,
            action_dim: 3,
            x: &x,
            tau: &tau,
            obs_fast: &obs,
            n_obs: 2,
            fast_dim: 4,
            slow: SlowInput::Vector {
                data: &slow,
                dim: 2,
            },
            d_vis: &[7],
        };
        let mut fast = vec![0.0; 18];
        m.velocity_into(&input, &mut fast).unwrap();
        let slow_path = m
            .forward_input(&input)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        for (a, b) in fast.iter().zip(&slow_path) {
            assert!((a - b).abs() < 1e-4 * (1.0 + b.abs()), "{a} vs {b}");
        }
    }
}
