//! [`Gr00tActionHead`]: GR00T N1.7's action head as four ONNX graphs, one NFE per call.
//!
//! One call (`velocity`) on `x [B,H,A]`, `τ [B,H]`, proprioception `[B,n_obs,45]`, backbone
//! tokens `[B,T,D_vl]` and `d_vis [B]`:
//!
//! ```text
//! state   = pad(normalise(obs), max_state_dim) per history step → [B, 1, S_in]
//! s       = state_encoder(state, embodiment_id)                  → [B, 1, D_in]
//! t_p     = min(floor(clamp(τ_p, 0, 1)·buckets), buckets − 1)     (per position, int64)
//! a       = action_encoder(pad(x, A_max), t [B,H], embodiment_id) → [B, H, D_in]
//! a      += position_embedding[0..H]           (if the side file has one; GR00T adds it outside ONNX)
//! a      += delay_embedding[min(d_vis, d_vis_max)]   (πR²: broadcast over the H action tokens)
//! y       = DiT(sa_embs = [s; a], vl_embs, timestep = [t_state, t_0..t_{H-1}], masks) → [B, 1+H, D_hid]
//! v       = action_decoder(y, embodiment_id)[:, 1:, :A]           → [B, H, A]
//! ```
//!
//! The velocity is in GR00T's normalised action space (`x_τ = (1−τ)·ε + τ·a`, `v = a − ε`,
//! the same convention as pir2); the runtime's output map denormalises the executed actions
//! ([`super::Normalizer::action_output_map`]).
//!
//! **Recording.** [`Gr00tActionHead::record_nfe`] writes what the four graphs were fed and
//! what the head returned, for the first calls, one safetensors file per call
//! ([`NfeRecorder`]): a diagnostic to compare the deployed head with the framework it was
//! trained in.
//!
//! The slow input may be [`SlowInput::Tokens`] (`dim = D_vl`) or, as the runtime's action head
//! passes it, a flat [`SlowInput::Vector`] of `T·D_vl` values that is read as `[T, D_vl]`.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use pir2_runtime::{ModelInput, SlowInput, VelocityModel};

use super::config::{CheckpointFiles, EmbodimentConfig, Normalizer};
use super::contract::{feed, Bindings, Graph, ACTION_DECODER, ACTION_ENCODER, DIT, STATE_ENCODER};
pub use super::prompt::VlLayout;
use super::weights::SideWeights;
use crate::error::{Error, Result};
use crate::ort::OrtOptions;

/// `want == got`, else an input error naming `what`.
pub(super) fn expect_size(what: &str, want: usize, got: usize) -> Result<()> {
    if want == got {
        Ok(())
    } else {
        Err(Error::input(what, want, got))
    }
}

/// The sizes every GR00T head checks on a call (`dims`: `H`, `A`, `n_obs`, proprioception
/// width; `out`: the output's length), each error naming what differs.
pub(super) fn check_call(
    input: &ModelInput<'_>,
    (h, a, n_obs, state_dim): (usize, usize, usize, usize),
    out: usize,
) -> Result<()> {
    let chk = expect_size;
    chk("horizon H", h, input.horizon)?;
    chk("action width A", a, input.action_dim)?;
    chk("history n_obs", n_obs, input.n_obs)?;
    chk("proprioception width", state_dim, input.fast_dim)?;
    chk("out [B,H,A]", input.batch * h * a, out)
}

/// Sizes read from the ONNX files and the side weights.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeadDims {
    /// Chunk length `H`.
    pub horizon: usize,
    /// Robot action width `A`.
    pub action_dim: usize,
    /// Padded action width of the model.
    pub max_action_dim: usize,
    /// Robot state width.
    pub state_dim: usize,
    /// State width the model sees per history step (`state_dim` with the sin/cos encoded
    /// groups counted twice).
    pub encoded_state_dim: usize,
    /// Padded state width per history step.
    pub max_state_dim: usize,
    /// History length.
    pub n_obs: usize,
    /// Token width of the state/action tokens.
    pub d_in: usize,
    /// Backbone token width.
    pub d_vl: usize,
    /// DiT output width.
    pub d_hid: usize,
    /// Rows of the delay table minus one.
    pub d_vis_max: usize,
    /// Backbone token count `T` if the DiT fixes it (GR00T's exporter leaves it dynamic).
    pub vl_tokens: Option<usize>,
}

/// GR00T N1.7's action head with the πR² changes (see the module docs).
#[derive(Debug)]
pub struct Gr00tActionHead {
    dims: HeadDims,
    norm: Normalizer,
    embodiment_id: i64,
    buckets: i64,
    state_timestep: i64,
    state_encoder: Graph,
    action_encoder: Graph,
    dit: Graph,
    action_decoder: Graph,
    delay: Vec<f32>,
    position: Option<Vec<f32>>,
    layout: Option<VlLayout>,
    d_vis_counts: Vec<u64>,
    // scratch
    state: Vec<f32>,
    actions: Vec<f32>,
    t_act: Vec<i64>,
    t_all: Vec<i64>,
    emb_id: Vec<i64>,
    s_feat: Vec<f32>,
    a_feat: Vec<f32>,
    sa: Vec<f32>,
    y: Vec<f32>,
    dec: Vec<f32>,
    img_mask: Vec<bool>,
    att_mask: Vec<bool>,
    recorder: Option<NfeRecorder>,
}

/// Records the first calls of a [`Gr00tActionHead`]: for call `k` (from 0) of the first
/// `calls` successful ones, `DIR/nfe-{k:04}.safetensors` (written to a temporary name in `DIR`
/// and renamed) with what the four graphs were fed and what the head returned:
///
/// | tensor | dtype | shape | what |
/// |--------|-------|-------|------|
/// | `state` | f32 | `[B, 1, n_obs·max_state_dim]` | the state encoder's input: normalised, padded |
/// | `embodiment_id` | i64 | `[B]` | the projector slot (every graph) |
/// | `actions` | f32 | `[B, H, A_max]` | the action encoder's input: the noisy actions, padded |
/// | `timesteps` | i64 | `[B, H]` | the action encoder's timesteps `min(⌊τ·buckets⌋, buckets − 1)` |
/// | `sa_embs` | f32 | `[B, 1 + H, D_in]` | the DiT's tokens, after the position and delay embeddings |
/// | `timestep` | i64 | `[B, 1 + H]` | the DiT's timesteps (state token first) |
/// | `vl_embs` | f32 | `[B, T, D_vl]` | the backbone tokens as fed to the DiT (the backbone applied `vlln` and `vl_self_attention`) |
/// | `image_mask`, `backbone_attention_mask` | u8 | `[B, T]` | when the DiT takes them |
/// | `d_vis` | i64 | `[B]` | the slow features' age, ticks (before clamping to `d_vis_max`) |
/// | `tau` | f32 | `[B, H]` | pir2's per-position flow time |
/// | `x` | f32 | `[B, H, A]` | the noisy actions, robot width |
/// | `velocity` | f32 | `[B, H, A]` | the head's output |
///
/// The file's metadata: `pir2_version`, `embodiment_id`, `state_timestep`, `buckets`.
#[derive(Debug, Clone)]
pub struct NfeRecorder {
    dir: PathBuf,
    calls: usize,
    written: usize,
}

impl NfeRecorder {
    /// The directory written to.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Calls recorded so far.
    pub fn written(&self) -> usize {
        self.written
    }

    /// The file of call `k`.
    pub fn file(dir: &Path, k: usize) -> PathBuf {
        dir.join(format!("nfe-{k:04}.safetensors"))
    }
}

/// One recorded tensor: dtype, shape, little-endian bytes.
type Recorded = (safetensors::Dtype, Vec<usize>, Vec<u8>);

fn f32s(shape: &[usize], v: &[f32]) -> Recorded {
    let bytes = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    (safetensors::Dtype::F32, shape.to_vec(), bytes)
}

fn i64s(shape: &[usize], v: &[i64]) -> Recorded {
    let bytes = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    (safetensors::Dtype::I64, shape.to_vec(), bytes)
}

fn u8s(shape: &[usize], v: &[bool]) -> Recorded {
    (
        safetensors::Dtype::U8,
        shape.to_vec(),
        v.iter().map(|&b| u8::from(b)).collect(),
    )
}

/// Write `tensors` with `meta` to `path` through a temporary file in the same directory.
fn write_record(
    path: &Path,
    tensors: Vec<(&'static str, Recorded)>,
    meta: HashMap<String, String>,
) -> Result<()> {
    let fail = |message: String| Error::NfeRecord {
        path: path.to_path_buf(),
        message,
    };
    let mut views = Vec::with_capacity(tensors.len());
    for (name, (dtype, shape, bytes)) in &tensors {
        let v = safetensors::tensor::TensorView::new(*dtype, shape.clone(), bytes)
            .map_err(|e| fail(format!("tensor `{name}`: {e}")))?;
        views.push((*name, v));
    }
    let bytes =
        safetensors::tensor::serialize(views, Some(meta)).map_err(|e| fail(e.to_string()))?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    let written = std::fs::write(&tmp, &bytes).and_then(|()| std::fs::rename(&tmp, path));
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(fail(e.to_string()));
    }
    Ok(())
}

impl Gr00tActionHead {
    /// Load the four graphs and the side weights of `files`, checking every file against the
    /// contract and against `cfg` (horizon, state and action widths, delay-table rows).
    pub fn load(
        files: &CheckpointFiles,
        cfg: &EmbodimentConfig,
        norm: Normalizer,
        embodiment_id: i64,
        opts: &OrtOptions,
    ) -> Result<Self> {
        cfg.validate()?;
        let mut b = Bindings::default();
        let src = Path::new("<embodiment config: horizon>");
        b.bind("H", cfg.horizon, src);
        b.bind("SA", cfg.horizon + 1, src);
        let state_encoder = Graph::load(&files.state_encoder, STATE_ENCODER, opts, &mut b)?;
        let action_encoder = Graph::load(&files.action_encoder, ACTION_ENCODER, opts, &mut b)?;
        let dit = Graph::load(&files.dit, DIT, opts, &mut b)?;
        let action_decoder = Graph::load(&files.action_decoder, ACTION_DECODER, opts, &mut b)?;
        let need = |n: &str| b.get(n).expect("bound by the contract check");
        let (s_in, a_max) = (need("S_in"), need("A_max"));
        let contract_err = |path: &Path, tensor: &str, problem: String| Error::Gr00tContract {
            path: path.to_path_buf(),
            tensor: tensor.to_string(),
            problem,
        };
        if s_in % cfg.n_obs != 0 || s_in / cfg.n_obs < cfg.encoded_state_dim() {
            return Err(contract_err(
                &files.state_encoder,
                "state",
                format!(
                    "last dimension {s_in} must be n_obs ({}) × max_state_dim with max_state_dim >= {} (the state width{})",
                    cfg.n_obs,
                    cfg.encoded_state_dim(),
                    if cfg.encoded_state_dim() != cfg.state_dim() {
                        format!(" after sin/cos encoding; {} raw", cfg.state_dim())
                    } else {
                        String::new()
                    }
                ),
            ));
        }
        if a_max < cfg.action_dim() {
            return Err(contract_err(
                &files.action_encoder,
                "actions",
                format!(
                    "max_action_dim {a_max} is smaller than the action width {}",
                    cfg.action_dim()
                ),
            ));
        }
        let dims = HeadDims {
            horizon: cfg.horizon,
            action_dim: cfg.action_dim(),
            max_action_dim: a_max,
            state_dim: cfg.state_dim(),
            encoded_state_dim: cfg.encoded_state_dim(),
            max_state_dim: s_in / cfg.n_obs,
            n_obs: cfg.n_obs,
            d_in: need("D_in"),
            d_vl: need("D_vl"),
            d_hid: need("D_hid"),
            d_vis_max: cfg.d_vis_max,
            vl_tokens: b.get("T"),
        };
        if norm.state_dim() != dims.state_dim || norm.encoded_state_dim() != dims.encoded_state_dim
        {
            return Err(Error::Gr00tConfig(format!(
                "normaliser has {} state dims ({} encoded), the embodiment {} ({})",
                norm.state_dim(),
                norm.encoded_state_dim(),
                dims.state_dim,
                dims.encoded_state_dim
            )));
        }
        let side = SideWeights::load(&files.weights)?;
        let delay = side.delay_embedding(cfg.d_vis_max, dims.d_in)?;
        let position = side.position_embedding(cfg.horizon, dims.d_in)?;
        Ok(Gr00tActionHead {
            dims,
            norm,
            embodiment_id,
            buckets: cfg.num_timestep_buckets,
            state_timestep: cfg.state_timestep(),
            state_encoder,
            action_encoder,
            dit,
            action_decoder,
            delay,
            position,
            layout: None,
            d_vis_counts: vec![0; cfg.d_vis_max + 1],
            state: Vec::new(),
            actions: Vec::new(),
            t_act: Vec::new(),
            t_all: Vec::new(),
            emb_id: Vec::new(),
            s_feat: Vec::new(),
            a_feat: Vec::new(),
            sa: Vec::new(),
            y: Vec::new(),
            dec: Vec::new(),
            img_mask: Vec::new(),
            att_mask: Vec::new(),
            recorder: None,
        })
    }

    /// Record the first `calls` successful calls of [`Self::forward`] into `dir` (see
    /// [`NfeRecorder`] for the files). `dir` is created if missing; it must be empty (a
    /// record is never mixed with another), else [`Error::NfeRecord`] naming it. Each
    /// recorded call costs one file write: a diagnostic, not for latency measurements. A
    /// write that fails is that call's error.
    pub fn record_nfe(&mut self, dir: &Path, calls: usize) -> Result<()> {
        prepare_record_dir(dir)?;
        self.recorder = Some(NfeRecorder {
            dir: dir.to_path_buf(),
            calls,
            written: 0,
        });
        Ok(())
    }

    /// The recorder, if [`Self::record_nfe`] set one.
    pub fn recorder(&self) -> Option<&NfeRecorder> {
        self.recorder.as_ref()
    }

    /// The sizes.
    pub fn dims(&self) -> &HeadDims {
        &self.dims
    }

    /// Set the token layout of the backbone features (required when the DiT declares masks).
    pub fn set_vl_layout(&mut self, layout: VlLayout) {
        self.layout = Some(layout);
    }

    /// The token layout of the backbone features, once set.
    pub fn vl_layout(&self) -> Option<&VlLayout> {
        self.layout.as_ref()
    }

    /// How many calls saw each `d_vis` (after clamping to `d_vis_max`).
    pub fn d_vis_counts(&self) -> &[u64] {
        &self.d_vis_counts
    }

    /// Overwrite one row of the delay table (tests, ablations).
    pub fn set_delay_row(&mut self, d_vis: usize, row: &[f32]) -> Result<()> {
        if d_vis > self.dims.d_vis_max || row.len() != self.dims.d_in {
            return Err(Error::input(
                "delay row",
                format!(
                    "d_vis <= {} and {} values",
                    self.dims.d_vis_max, self.dims.d_in
                ),
                format!("d_vis {d_vis}, {} values", row.len()),
            ));
        }
        let d = self.dims.d_in;
        self.delay[d_vis * d..(d_vis + 1) * d].copy_from_slice(row);
        Ok(())
    }

    fn bucket(&self, tau: f32) -> i64 {
        // Hidden-front slots carry τ < 0: they are fed as noise-level 0.
        let t = if tau.is_finite() {
            tau.clamp(0.0, 1.0)
        } else {
            0.0
        };
        ((t * self.buckets as f32).floor() as i64).min(self.buckets - 1)
    }

    fn tokens<'a>(&self, slow: &SlowInput<'a>, batch: usize) -> Result<(&'a [f32], usize)> {
        let d_vl = self.dims.d_vl;
        let (data, t) = match *slow {
            SlowInput::Tokens { data, tokens, dim } => {
                if dim != d_vl {
                    return Err(Error::input("backbone token width", d_vl, dim));
                }
                (data, tokens)
            }
            SlowInput::Vector { data, dim } => {
                if dim == 0 || dim % d_vl != 0 {
                    return Err(Error::input(
                        "backbone features (flat T·D_vl)",
                        format!("a multiple of D_vl = {d_vl}"),
                        dim,
                    ));
                }
                (data, dim / d_vl)
            }
            SlowInput::None => {
                return Err(Error::input(
                    "backbone features",
                    format!("[B, T, {d_vl}] tokens"),
                    "none",
                ))
            }
        };
        if data.len() != batch * t * d_vl {
            return Err(Error::input(
                "backbone features [B,T,D_vl]",
                batch * t * d_vl,
                data.len(),
            ));
        }
        Ok((data, t))
    }

    /// One NFE (see the module docs); `out` is `[B, H, A]`.
    pub fn forward(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        input.validate()?;
        let HeadDims {
            horizon: h,
            action_dim: a,
            max_action_dim: a_max,
            state_dim: sd,
            encoded_state_dim: esd,
            max_state_dim: msd,
            n_obs,
            d_in,
            d_vl: _,
            d_hid,
            d_vis_max,
            vl_tokens: _,
        } = self.dims;
        let b = input.batch;
        check_call(input, (h, a, n_obs, sd), out.len())?;
        let chk = expect_size;
        for g in [
            &self.state_encoder,
            &self.action_encoder,
            &self.dit,
            &self.action_decoder,
        ] {
            if let Some(fb) = g.declared.batch {
                if fb != b {
                    return Err(Error::input(
                        format!("batch (fixed in `{}`)", g.path().display()),
                        fb,
                        b,
                    ));
                }
            }
        }
        let (vl, t) = self.tokens(&input.slow, b)?;

        // 1. state tokens
        self.state.clear();
        self.state.resize(b * n_obs * msd, 0.0);
        for bi in 0..b {
            for k in 0..n_obs {
                let src = &input.obs_fast[(bi * n_obs + k) * sd..(bi * n_obs + k + 1) * sd];
                let at = (bi * n_obs + k) * msd;
                let dst = &mut self.state[at..at + esd];
                self.norm.normalize_state(src, dst);
            }
        }
        self.emb_id.clear();
        self.emb_id.resize(b, self.embodiment_id);
        let mut s_feat = std::mem::take(&mut self.s_feat);
        self.state_encoder.run_into(
            vec![
                feed("state", &[b, 1, n_obs * msd], &self.state)?,
                feed("embodiment_id", &[b], &self.emb_id)?,
            ],
            "output",
            &mut s_feat,
        )?;
        self.s_feat = s_feat;
        chk(
            "state encoder output [B,1,D_in]",
            b * d_in,
            self.s_feat.len(),
        )?;

        // 2. action tokens with per-position timesteps
        self.actions.clear();
        self.actions.resize(b * h * a_max, 0.0);
        self.t_act.clear();
        for bi in 0..b {
            for p in 0..h {
                let src = &input.x[(bi * h + p) * a..(bi * h + p + 1) * a];
                self.actions[(bi * h + p) * a_max..(bi * h + p) * a_max + a].copy_from_slice(src);
                let tb = self.bucket(input.tau[bi * h + p]);
                self.t_act.push(tb);
            }
        }
        let mut a_feat = std::mem::take(&mut self.a_feat);
        self.action_encoder.run_into(
            vec![
                feed("actions", &[b, h, a_max], &self.actions)?,
                feed("timesteps", &[b, h], &self.t_act)?,
                feed("embodiment_id", &[b], &self.emb_id)?,
            ],
            "output",
            &mut a_feat,
        )?;
        self.a_feat = a_feat;
        chk(
            "action encoder output [B,H,D_in]",
            b * h * d_in,
            self.a_feat.len(),
        )?;

        // 3. position and delay embeddings, then [state; actions]
        self.sa.clear();
        self.sa.reserve(b * (1 + h) * d_in);
        self.t_all.clear();
        for bi in 0..b {
            let dv = (input.d_vis[bi] as usize).min(d_vis_max);
            self.d_vis_counts[dv] += 1;
            let row = &self.delay[dv * d_in..(dv + 1) * d_in];
            self.sa
                .extend_from_slice(&self.s_feat[bi * d_in..(bi + 1) * d_in]);
            self.t_all.push(self.state_timestep);
            for p in 0..h {
                let tok = &self.a_feat[(bi * h + p) * d_in..(bi * h + p + 1) * d_in];
                for j in 0..d_in {
                    let pos = self.position.as_ref().map_or(0.0, |pe| pe[p * d_in + j]);
                    self.sa.push(tok[j] + pos + row[j]);
                }
                self.t_all.push(self.t_act[bi * h + p]);
            }
        }

        // 4. DiT
        let mut feeds = vec![
            feed("sa_embs", &[b, 1 + h, d_in], &self.sa)?,
            feed("vl_embs", &[b, t, self.dims.d_vl], vl)?,
            feed("timestep", &[b, 1 + h], &self.t_all)?,
        ];
        let wants_img = self.dit.declared.has("image_mask");
        let wants_att = self.dit.declared.has("backbone_attention_mask");
        if wants_img || wants_att {
            let layout = self.layout.as_ref().ok_or_else(|| {
                Error::Gr00tConfig(format!(
                    "`{}` declares the VL masks but no token layout was set (Gr00tActionHead::set_vl_layout)",
                    self.dit.path().display()
                ))
            })?;
            if layout.image_mask.len() != t || layout.attention_mask.len() != t {
                return Err(Error::input(
                    "VL layout masks (length T)",
                    t,
                    layout.image_mask.len(),
                ));
            }
            self.img_mask.clear();
            self.att_mask.clear();
            for _ in 0..b {
                self.img_mask.extend_from_slice(&layout.image_mask);
                self.att_mask.extend_from_slice(&layout.attention_mask);
            }
            if wants_img {
                feeds.push(feed("image_mask", &[b, t], &self.img_mask)?);
            }
            if wants_att {
                feeds.push(feed("backbone_attention_mask", &[b, t], &self.att_mask)?);
            }
        }
        let mut y = std::mem::take(&mut self.y);
        let r = self.dit.run_into(feeds, "output", &mut y);
        self.y = y;
        r?;
        chk(
            "DiT output [B,1+H,D_hid]",
            b * (1 + h) * d_hid,
            self.y.len(),
        )?;

        // 5. decoder, drop the state token and the padding
        let mut dec = std::mem::take(&mut self.dec);
        self.action_decoder.run_into(
            vec![
                feed("model_output", &[b, 1 + h, d_hid], &self.y)?,
                feed("embodiment_id", &[b], &self.emb_id)?,
            ],
            "output",
            &mut dec,
        )?;
        self.dec = dec;
        chk(
            "action decoder output [B,1+H,A_max]",
            b * (1 + h) * a_max,
            self.dec.len(),
        )?;
        for bi in 0..b {
            for p in 0..h {
                let src = (bi * (1 + h) + 1 + p) * a_max;
                out[(bi * h + p) * a..(bi * h + p + 1) * a]
                    .copy_from_slice(&self.dec[src..src + a]);
            }
        }
        ensure_finite(out)?;
        if self.recorder.as_ref().is_some_and(|r| r.written < r.calls) {
            self.record(input, vl, t, (wants_img, wants_att), out)?;
        }
        Ok(())
    }

    /// Write the call just made ([`NfeRecorder`]).
    fn record(
        &mut self,
        input: &ModelInput<'_>,
        vl: &[f32],
        t: usize,
        (img, att): (bool, bool),
        out: &[f32],
    ) -> Result<()> {
        let Some(rec) = self.recorder.as_mut() else {
            return Ok(());
        };
        let HeadDims {
            horizon: h,
            action_dim: a,
            max_action_dim: a_max,
            max_state_dim: msd,
            n_obs,
            d_in,
            d_vl,
            ..
        } = self.dims;
        let b = input.batch;
        let d_vis: Vec<i64> = input.d_vis.iter().map(|&d| d as i64).collect();
        let mut tensors = vec![
            ("state", f32s(&[b, 1, n_obs * msd], &self.state)),
            ("embodiment_id", i64s(&[b], &self.emb_id)),
            ("actions", f32s(&[b, h, a_max], &self.actions)),
            ("timesteps", i64s(&[b, h], &self.t_act)),
            ("sa_embs", f32s(&[b, 1 + h, d_in], &self.sa)),
            ("timestep", i64s(&[b, 1 + h], &self.t_all)),
            ("vl_embs", f32s(&[b, t, d_vl], vl)),
            ("d_vis", i64s(&[b], &d_vis)),
            ("tau", f32s(&[b, h], input.tau)),
            ("x", f32s(&[b, h, a], input.x)),
            ("velocity", f32s(&[b, h, a], out)),
        ];
        if img {
            tensors.push(("image_mask", u8s(&[b, t], &self.img_mask)));
        }
        if att {
            tensors.push(("backbone_attention_mask", u8s(&[b, t], &self.att_mask)));
        }
        let meta = HashMap::from([
            (
                "pir2_version".to_string(),
                env!("CARGO_PKG_VERSION").to_string(),
            ),
            ("embodiment_id".to_string(), self.embodiment_id.to_string()),
            (
                "state_timestep".to_string(),
                self.state_timestep.to_string(),
            ),
            ("buckets".to_string(), self.buckets.to_string()),
        ]);
        write_record(&NfeRecorder::file(&rec.dir, rec.written), tensors, meta)?;
        rec.written += 1;
        Ok(())
    }
}

/// Make `dir` ready for a record: created if missing, refused (naming it) if it is not an
/// empty directory or cannot be created. `pir2 gr00t run --record-nfe` calls it before the
/// run starts, so a bad directory fails while nothing moves.
pub fn prepare_record_dir(dir: &Path) -> Result<()> {
    let fail = |message: String| Error::NfeRecord {
        path: dir.to_path_buf(),
        message,
    };
    if dir.exists() {
        let mut entries = std::fs::read_dir(dir)
            .map_err(|e| fail(format!("is not a readable directory: {e}")))?;
        if entries.next().is_some() {
            return Err(fail(
                "exists and is not empty; choose a new directory (a record is never mixed \
                 with another)"
                    .into(),
            ));
        }
        return Ok(());
    }
    std::fs::create_dir_all(dir).map_err(|e| fail(format!("cannot be created: {e}")))
}

/// The velocity a head returns must be finite: the first bad index is one error.
pub(super) fn ensure_finite(out: &[f32]) -> Result<()> {
    match out.iter().position(|x| !x.is_finite()) {
        Some(index) => Err(Error::Runtime(pir2_runtime::Error::NonFinite { index })),
        None => Ok(()),
    }
}

impl VelocityModel for Gr00tActionHead {
    fn backend(&self) -> &'static str {
        "onnxruntime (GR00T N1.7 action head)"
    }

    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        self.forward(input, out).map_err(Into::into)
    }
}
