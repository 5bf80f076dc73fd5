//! πR² fine-tuning of GR00T N1.7's action head ([`Gr00tN17Head`]) with candle, on the
//! head's device (the CPU; a GPU with the `cuda` / `metal` features, see
//! [`crate::candle::device`]).
//!
//! Two files, by what they are: this one is the trainer (the run's spec, the sample, the
//! step, the run's identity); `features.rs` is the frozen backbone's tokens it reads
//! ([`VlFeatures`]: precomputed, or cached per frame).
//!
//! The network is the inference head itself, loaded with [`Gr00tN17Head::load_trainable`]:
//! its projectors, position embedding, DiT and decoder are candle `Var`s, the backbone
//! post-processing (`vlln`, VL self-attention) stays frozen with the backbone, and a
//! zero-initialised delay table `e(d_vis)` is added to the action tokens. The draws and the
//! resumable machinery are the trainer's own ([`crate::train::Trainer`]): the same [`TrainConfig`]
//! (AdamW, cosine LR with warm-up, grad-norm clip, seed), the same batch sampler, step
//! checkpoints with the full training state, `interrupted-*` states, bit-identical resume.
//!
//! Each sample (the paper's robot recipe on GR00T's data pipeline): a frame `t` uniformly
//! over the frames whose whole chunk lies inside their episode (`t ≤ len − H`, as GR00T's
//! `ShardedSingleStepDataset` samples; an episode shorter than `H` gives none); the state
//! history ending at `t` (clamped at the episode start); the action chunk `a_{t..t+H}`
//! (encoded per sample by an [`ActionTargets`] when the targets depend on the sample, as
//! relative actions do); `τ`/mask from the schedule's draw (πR²: staircase with a clean,
//! masked front of `d ~ U{1..d_max}`, or the warm-up branch); `d_vis ~ U{0..d_vis_max}` per sample, the VL
//! tokens of frame `max(0, t − d_vis)` and `e(d_vis)` on the action tokens. GR00T's discrete
//! timesteps are [`timestep_bucket`]`(τ_p)` per action token and `state_timestep` for the
//! state token (per-token AdaLN, as deployed). Actions are padded with zeros to `A_max`; the
//! loss is the trainer's masked MSE over the robot's `A` action dimensions only.
//!
//! The backbone is frozen, so its tokens are computed once per frame: a [`VlCache`] holds
//! them (after `vlln` and the VL self-attention, which are frozen too) in one file keyed by
//! a digest of everything they depend on ([`vl_cache_key`]); another input gets another
//! file, never a stale one. [`PrecomputedFeatures`] reads backbone outputs a user computed
//! with the real backbone.
//!
//! The training forward is [`Gr00tN17Head::velocity_train`]: GR00T's dropout in the DiT
//! blocks at the checkpoint's rate (`diffusion_model_cfg.dropout`, `final_dropout`; see
//! [`DitDropout`]), masks keyed by the run's seed and the step index, so a resumed run is
//! bit-identical to an uninterrupted one. [`Gr00tTrainer::dropout`]`(false)` trains without
//! it. Whether it is on, its rate, and whether its masks are built on the device (off the
//! CPU) are part of the run's identity ([`RUN_FILE`]): a run resumes on the kind of device it
//! began on.
//!
//! A step stays on the head's device (`load_trainable(.., device)`): the batch's tensors
//! are uploaded once, then the forward, the backward, the grad-norm clip (only the squared
//! norm of each parameter tensor, one `f32` each, comes back to the host for the global
//! norm), the AdamW moments and update (tensor ops, in place on the `Var`s) and, off the
//! CPU, the dropout masks ([`MaskSource::Device`](crate::gr00t::n17::MaskSource::Device))
//! run there. The host's copies of the weights and the optimiser state (the checkpoint's
//! form, files unchanged) are read from the device only when a checkpoint is written and
//! written to it only when a run resumes; between checkpoints they are stale. On the CPU the
//! device-side AdamW
//! writes the host AdamW's bits and the masks are the host-built ones, so CPU runs are
//! unchanged. Only the CPU has been run: the CUDA and Metal paths use the same candle ops
//! (`u32` and `f32` elementwise kernels, no `affine`) but have not been compiled or run here.
//!
//! Not done here: EMA, self-rollout and validation hooks of [`crate::train::Trainer`] are refused
//! by name.

use candle_core::{DType, Var};

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use candle_core::Tensor;

use crate::config::{SlowSpec, Spec, Stats};
use crate::error::{Error, Result};
use crate::gr00t::n17::{timestep_bucket, DitDropout, Gr00tN17Head, Timesteps, VlTokens};
use crate::train::*;

mod features;

pub use features::{
    head_fingerprint, tree_fingerprint, vl_cache_key, PrecomputedFeatures, VlCache, VlFeatures,
};

/// The embodiment as the trainer sees it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Gr00tTrainSpec {
    /// Chunk length `H`.
    pub horizon: usize,
    /// The robot's action width `A` (≤ the head's `max_action_dim`); the data's actions.
    pub action_dim: usize,
    /// Largest slow-feature age drawn (the delay table has `d_vis_max + 1` rows).
    pub d_vis_max: usize,
    /// The embodiment slot of the category-specific layers.
    pub embodiment_id: u32,
    /// GR00T timestep of the state token (deployment default: `buckets − 1`).
    pub state_timestep: u32,
}

/// How a sample's action chunk becomes the model's training target when the target depends
/// on the sample, not only on the frame: GR00T's relative action groups are `a − s`, with `s`
/// the newest raw state of the sample's observation window (frame `t` itself), normalised
/// with per-chunk-slot statistics. Without one, the trainer reads the data's actions as
/// already normalised.
pub trait ActionTargets {
    /// Encode in place `chunk` (`[H, A]`): the raw actions of episode `episode` from frame
    /// `frame` on (slot `p` holds frame `frame + p`; the trainer draws only chunks inside the
    /// episode), the sample's observation window ending at `frame`.
    fn encode(&self, episode: usize, frame: usize, chunk: &mut [f32]) -> Result<()>;
}

// ---------------------------------------------------------------- trainer

/// The head's trainable variables and host copies of their values (flattened).
fn trainable(head: &Gr00tN17Head) -> Result<(Vec<Var>, Vec<Vec<f32>>)> {
    let vars: Vec<Var> = head
        .trainable_vars()
        .iter()
        .map(|(_, v)| v.clone())
        .collect();
    let params = vars
        .iter()
        .map(|v| Ok(v.as_tensor().flatten_all()?.to_vec1::<f32>()?))
        .collect::<Result<Vec<_>>>()?;
    Ok((vars, params))
}

/// The host copies of the trained weights and the optimiser state, for a checkpoint.
fn to_host(st: &mut State, vars: &[Var], opt: &DeviceAdamW) -> Result<()> {
    for (p, v) in st.params.iter_mut().zip(vars) {
        *p = v.as_tensor().flatten_all()?.to_vec1::<f32>()?;
    }
    opt.to_host(&mut st.opt)
}

/// The host-side buffers of one training step's batch, allocated once per run.
struct StepBuffers {
    b: usize,
    h: usize,
    a: usize,
    a_max: usize,
    n_obs: usize,
    fast_dim: usize,
    t_vl: usize,
    d_vl: usize,
    buckets: usize,
    state_timestep: u32,
    /// First frame of each episode in the frames of all episodes in order.
    cum: Vec<usize>,
    emb: Vec<f32>,
    image: Vec<f32>,
    attn: Vec<f32>,
    x_pad: Vec<f32>,
    t_act: Vec<u32>,
    t_tok: Vec<u32>,
    ids: Tensor,
}

impl StepBuffers {
    fn new(
        head: &Gr00tN17Head,
        spec: &Spec,
        cfg: &TrainConfig,
        ts: &Gr00tTrainSpec,
        data: &[Episode],
        vl: &dyn VlFeatures,
    ) -> Result<Self> {
        let c = head.config();
        let (b, h) = (cfg.batch_size, spec.horizon);
        let (t_vl, d_vl) = (vl.tokens(), vl.dim());
        let cum = data
            .iter()
            .scan(0, |acc, e| {
                let start = *acc;
                *acc += e.len();
                Some(start)
            })
            .collect();
        Ok(Self {
            b,
            h,
            a: spec.action_dim,
            a_max: c.max_action_dim,
            n_obs: spec.n_obs,
            fast_dim: spec.fast_dim,
            t_vl,
            d_vl,
            buckets: c.num_timestep_buckets,
            state_timestep: ts.state_timestep,
            cum,
            emb: vec![0f32; b * t_vl * d_vl],
            image: vec![0f32; b * t_vl],
            attn: vec![0f32; b * t_vl],
            x_pad: vec![0f32; b * h * c.max_action_dim],
            t_act: vec![0u32; b * h],
            t_tok: vec![0u32; b * (1 + h)],
            ids: Tensor::from_vec(vec![ts.embodiment_id; b], b, head.device())?,
        })
    }
}

/// What one training step reads besides the head, the batcher and the optimiser.
struct StepInputs<'s, 'a> {
    data: &'s [Episode],
    vl: &'s mut dyn VlFeatures,
    targets: Option<&'a dyn ActionTargets>,
    dropout: bool,
    cfg: &'s TrainConfig,
    step: usize,
    lr: f64,
}

/// ONE training step, the trainer's own (also what [`Gr00tTrainer::time_steps`] times): the
/// batch drawn by `batcher` (targets encoded by `targets`), its VL tokens read from `vl`, the
/// tensors uploaded to the head's device, the forward (`velocity_train` with GR00T's dropout
/// keyed by the seed and `step`, or `velocity`), the masked MSE, the backward, the grad-norm
/// clip and the AdamW update at `lr`. Returns the loss and the gradient norm before the clip.
fn train_step(
    head: &Gr00tN17Head,
    inp: StepInputs<'_, '_>,
    batcher: &mut Batcher,
    buf: &mut StepBuffers,
    vars: &[Var],
    opt: &mut DeviceAdamW,
) -> Result<(f32, f32)> {
    let StepInputs {
        data,
        vl,
        targets,
        dropout,
        cfg,
        step,
        lr,
    } = inp;
    let dev = head.device();
    let c = head.config();
    let StepBuffers {
        b,
        h,
        a,
        a_max,
        n_obs,
        fast_dim,
        t_vl,
        d_vl,
        buckets,
        state_timestep,
        ..
    } = *buf;
    match targets {
        Some(tg) => {
            let mut f = |e: usize, t: usize, c: &mut [f32]| tg.encode(e, t, c);
            batcher.fill_encoded(data, Some(&mut f))?
        }
        None => batcher.fill(data)?,
    }
    for i in 0..b {
        let (e, t) = batcher.slow_frame[i];
        vl.read(
            buf.cum[e] + t,
            &mut buf.emb[i * t_vl * d_vl..(i + 1) * t_vl * d_vl],
            &mut buf.image[i * t_vl..(i + 1) * t_vl],
            &mut buf.attn[i * t_vl..(i + 1) * t_vl],
        )?;
        buf.t_tok[i * (1 + h)] = state_timestep;
        for p in 0..h {
            let q = i * h + p;
            let tb = timestep_bucket(batcher.tau[q], buckets);
            buf.t_act[q] = tb;
            buf.t_tok[i * (1 + h) + 1 + p] = tb;
            buf.x_pad[q * a_max..q * a_max + a].copy_from_slice(&batcher.x[q * a..(q + 1) * a]);
        }
    }
    let state = Tensor::from_slice(&batcher.fast, (b, n_obs, fast_dim), dev)?;
    let x = Tensor::from_slice(&buf.x_pad, (b, h, a_max), dev)?;
    let ta = Tensor::from_slice(&buf.t_act, (b, h), dev)?;
    let tt = Tensor::from_slice(&buf.t_tok, (b, 1 + h), dev)?;
    let vl_emb = Tensor::from_slice(&buf.emb, (b, t_vl, d_vl), dev)?;
    let im = Tensor::from_slice(&buf.image, (b, t_vl), dev)?;
    let am = Tensor::from_slice(&buf.attn, (b, t_vl), dev)?;
    let dv = Tensor::from_slice(&batcher.dvis, b, dev)?;
    let tokens = VlTokens {
        embeddings: &vl_emb,
        attention_mask: Some(&am),
        image_mask: Some(&im),
        d_vis: Some(&dv),
    };
    let ids = &buf.ids;
    let s = head.encode_state(&state, ids)?;
    let ts = Timesteps::PerPosition {
        actions: &ta,
        tokens: &tt,
    };
    let v = if dropout {
        let d = DitDropout::from_config(&c.dit, cfg.seed, step as u64);
        head.velocity_train(&s, &x, ts, &tokens, ids, &d)?
    } else {
        head.velocity(&s, &x, ts, &tokens, ids)?
    };
    let loss = masked_mse(v.narrow(2, 0, a)?, &batcher.target, &batcher.mask)?;
    let loss_v = loss.to_dtype(DType::F32)?.to_scalar::<f32>()?;
    if !loss_v.is_finite() {
        return Err(Error::Diverged {
            step: step + 1,
            loss: loss_v,
        });
    }
    let mut grads = loss.backward()?;
    let gn = clip_grad_store(&mut grads, vars, cfg.grad_clip)?;
    opt.step(vars, &grads, lr)?;
    Ok((loss_v, gn))
}

/// Wall-clock times of training steps ([`Gr00tTrainer::time_steps`]).
#[derive(Debug, Clone, PartialEq)]
pub struct StepTimes {
    /// Seconds of each timed step, in order (the device synchronised after each).
    pub seconds: Vec<f64>,
    /// Trained parameters (elements of the head's trainable tensors).
    pub parameters: usize,
    /// The last step's loss.
    pub last_loss: f32,
}

/// The run's identity file in the output directory: a resumed run must match it.
pub const RUN_FILE: &str = "gr00t_run.json";
/// The head's weights in every step checkpoint (GR00T's names, with the delay table).
pub const WEIGHTS_FILE: &str = "model.safetensors";

/// Builder and runner of one πR² fine-tuning run of a [`Gr00tN17Head`].
pub struct Gr00tTrainer<'a> {
    cfg: TrainConfig,
    spec: Gr00tTrainSpec,
    out_dir: PathBuf,
    ctl: RunControl<'a>,
    identity: serde_json::Value,
    extra_files: Vec<(String, Vec<u8>)>,
    targets: Option<&'a dyn ActionTargets>,
    dropout: bool,
}

impl std::fmt::Debug for Gr00tTrainer<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gr00tTrainer")
            .field("cfg", &self.cfg)
            .field("spec", &self.spec)
            .field("out_dir", &self.out_dir)
            .field("resume", &self.ctl.resume)
            .field("dropout", &self.dropout)
            .finish_non_exhaustive()
    }
}

impl<'a> Gr00tTrainer<'a> {
    /// A run with hyper-parameters `cfg` for `spec`, writing to `out_dir` (step checkpoints
    /// `step-NNNNNN/`, `loss.jsonl`, [`RUN_FILE`]).
    pub fn new(cfg: TrainConfig, spec: Gr00tTrainSpec, out_dir: impl AsRef<Path>) -> Self {
        Self {
            cfg,
            spec,
            out_dir: out_dir.as_ref().to_path_buf(),
            ctl: RunControl::default(),
            identity: serde_json::Value::Null,
            extra_files: Vec::new(),
            targets: None,
            dropout: true,
        }
    }
    /// Apply GR00T's DiT dropout at the checkpoint's rate in the training forward (on by
    /// default; see [`DitDropout`]).
    pub fn dropout(mut self, on: bool) -> Self {
        self.dropout = on;
        self
    }
    /// Encode every sample's chunk with `targets` (the data then holds raw actions); without
    /// it the data's actions are the normalised targets themselves.
    pub fn action_targets(mut self, targets: &'a dyn ActionTargets) -> Self {
        self.targets = Some(targets);
        self
    }
    run_controls!();
    /// What the run is made of (inputs' digests, embodiment…), written to [`RUN_FILE`] with
    /// the spec; a resumed run whose identity differs is refused, naming the file.
    pub fn identity(mut self, id: serde_json::Value) -> Self {
        self.identity = id;
        self
    }
    /// A file written into every step checkpoint next to the weights (e.g. `config.json`).
    pub fn checkpoint_file(mut self, name: &str, bytes: Vec<u8>) -> Self {
        self.extra_files.push((name.to_string(), bytes));
        self
    }

    fn check(&self, head: &Gr00tN17Head, data: &[Episode], vl: &dyn VlFeatures) -> Result<Spec> {
        let cfg = &self.cfg;
        let s = &self.spec;
        let c = head.config();
        if cfg.ema.is_some() || cfg.self_rollout.is_some() {
            return Err(Error::config(
                "train.ema/self_rollout",
                "not supported by the GR00T trainer",
            ));
        }
        if head.trainable_vars().is_empty() {
            return Err(Error::config(
                "gr00t head",
                "loaded for inference; use Gr00tN17Head::load_trainable",
            ));
        }
        match head.delay_embedding().map(|t| t.dim(0)).transpose()? {
            Some(rows) if rows == s.d_vis_max + 1 => {}
            other => {
                return Err(Error::config(
                    "gr00t d_vis_max",
                    format!(
                        "the head's delay table has {other:?} rows, d_vis_max = {} needs {}",
                        s.d_vis_max,
                        s.d_vis_max + 1
                    ),
                ))
            }
        }
        if s.action_dim == 0 || s.action_dim > c.max_action_dim {
            return Err(Error::config(
                "gr00t action_dim",
                format!(
                    "{} must be in 1..={} (max_action_dim)",
                    s.action_dim, c.max_action_dim
                ),
            ));
        }
        if c.add_pos_embed && s.horizon > c.max_seq_len {
            return Err(Error::config(
                "gr00t horizon",
                format!(
                    "{} is above the position embedding's {} rows",
                    s.horizon, c.max_seq_len
                ),
            ));
        }
        if s.embodiment_id as usize >= c.max_num_embodiments {
            return Err(Error::config(
                "gr00t embodiment_id",
                format!(
                    "{} is not a slot in 0..{}",
                    s.embodiment_id, c.max_num_embodiments
                ),
            ));
        }
        if s.state_timestep as usize >= c.num_timestep_buckets {
            return Err(Error::config(
                "gr00t state_timestep",
                format!("{} outside 0..{}", s.state_timestep, c.num_timestep_buckets),
            ));
        }
        let frames: usize = data.iter().map(Episode::len).sum();
        let full: usize = data
            .iter()
            .map(|e| (e.len() + 1).saturating_sub(s.horizon))
            .sum();
        if full == 0 {
            let longest = data.iter().map(Episode::len).max().unwrap_or(0);
            return Err(Error::Dataset(format!(
                "no episode holds one whole action chunk of H = {} frames (the longest has \
                 {longest}); GR00T trains only on chunks inside an episode",
                s.horizon
            )));
        }
        if vl.frames() != frames || vl.dim() != c.backbone_embedding_dim {
            return Err(Error::Dataset(format!(
                "the VL features hold {} frames of width {}, the dataset has {frames} frames and \
                 the head wants width {}",
                vl.frames(),
                vl.dim(),
                c.backbone_embedding_dim
            )));
        }
        let spec = Spec {
            horizon: s.horizon,
            action_dim: s.action_dim,
            n_obs: c.state_history_length,
            fast_dim: c.max_state_dim,
            slow: SlowSpec::None,
            d_vis_max: s.d_vis_max,
        };
        spec.validate()?;
        cfg.validate(spec.horizon)?;
        check_dataset(data, &spec)?;
        Ok(spec)
    }

    /// Train `head` (loaded with [`Gr00tN17Head::load_trainable`]) on `data` (per frame the
    /// normalised state padded to `max_state_dim` as the fast row, the normalised action of
    /// width `A`, or the raw one with [`action_targets`](Self::action_targets)) with the VL tokens of `vl` (frame `i` = the `i`-th frame over the episodes in
    /// order). On return the head holds the last step's weights.
    pub fn run(
        mut self,
        head: &Gr00tN17Head,
        data: &[Episode],
        vl: &mut dyn VlFeatures,
    ) -> Result<TrainReport> {
        let spec = self.check(head, data, vl)?;
        let cfg = self.cfg.clone();
        let out = self.out_dir.clone();
        // The run's identity: written once, checked on resume.
        let dit = &head.config().dit;
        let dropout = (self.dropout && dit.dropout > 0.0).then(|| {
            let mut d =
                serde_json::json!({ "rate": dit.dropout, "final_dropout": dit.final_dropout });
            // Device-built masks have other bits than the host-built ones CPU runs draw: a
            // run resumed on another kind of device would not continue its masks, so it is
            // refused. (Absent for host masks, so runs logged before keep their identity.)
            if crate::gr00t::n17::MaskSource::for_device(head.device())
                == crate::gr00t::n17::MaskSource::Device
            {
                d["masks"] = "device".into();
            }
            d
        });
        let id = serde_json::json!({
            "spec": self.spec,
            "identity": self.identity,
            "dropout": dropout,
        });
        let id_path = out.join(RUN_FILE);
        let resume_from = self.ctl.prepare(&out)?;
        if resume_from.is_some() {
            let text = std::fs::read_to_string(&id_path).map_err(|e| Error::io(&id_path, e))?;
            let old: serde_json::Value =
                serde_json::from_str(&text).map_err(|e| Error::Format {
                    path: id_path.clone(),
                    message: e.to_string(),
                })?;
            if old != id {
                return Err(Error::config(
                    "train.resume",
                    format!(
                        "{} records another run ({old}); this one is {id}",
                        id_path.display()
                    ),
                ));
            }
        } else {
            let text = serde_json::to_string_pretty(&id).map_err(|e| Error::Format {
                path: id_path.clone(),
                message: e.to_string(),
            })?;
            let tmp = out.join(format!(".{RUN_FILE}.tmp"));
            crate::checkpoint::write_durable(&tmp, text.as_bytes())?;
            std::fs::rename(&tmp, &id_path).map_err(|e| Error::io(&id_path, e))?;
        }
        let mut log = LossLog::open(Some(&out), None)?;

        // The head's device: every per-step tensor lives there, the AdamW moments and
        // update too ([`DeviceAdamW`]). The host holds the state only to save or restore it.
        let dev = head.device().clone();
        let names: Vec<String> = head
            .trainable_vars()
            .iter()
            .map(|(n, _)| n.clone())
            .collect();
        let (vars, params) = trainable(head)?;
        let mut st = State {
            step: 0,
            opt: AdamW::new(&cfg, &params),
            ema: None,
            params,
            best: None,
            report: TrainReport::default(),
        };
        let stats = Stats::identity(&spec);
        let mut batcher = Batcher::new(data, &spec, &stats, &cfg);
        batcher.full_chunks_only(data);
        if let Some(dir) = &resume_from {
            batcher.rng = st.load(dir, &cfg, &names)?;
            for (v, p) in vars.iter().zip(&st.params) {
                v.set(&Tensor::from_slice(p, v.dims(), &dev)?)?;
            }
        }
        let mut opt = DeviceAdamW::from_host(&st.opt, &vars)?;
        let extra = std::mem::take(&mut self.extra_files);
        let write_model = |dir: &Path| -> Result<()> {
            head.save_weights(&dir.join(WEIGHTS_FILE))?;
            for (name, bytes) in &extra {
                crate::checkpoint::write_durable(&dir.join(name), bytes)?;
            }
            Ok(())
        };
        let mut buf = StepBuffers::new(head, &spec, &cfg, &self.spec, data, &*vl)?;
        let dropout = dropout.is_some();

        for step in st.step..cfg.steps {
            if self.ctl.stop_before(step, Some(&out), &mut log, |p| {
                to_host(&mut st, &vars, &opt)?;
                st.save_step(write_model, p, batcher.rng.state(), &names, &cfg)
            })? {
                break;
            }
            let lr = cfg.lr_at(step);
            let (loss_v, gn) = train_step(
                head,
                StepInputs {
                    data,
                    vl,
                    targets: self.targets,
                    dropout,
                    cfg: &cfg,
                    step,
                    lr,
                },
                &mut batcher,
                &mut buf,
                &vars,
                &mut opt,
            )?;
            let done = step + 1;
            let progress = Progress {
                step: done,
                steps: cfg.steps,
                loss: loss_v,
                lr,
                grad_norm: gn,
            };
            if self.ctl.after_step(&cfg, &mut st, &mut log, progress)? {
                let dir = step_dir(&out, done);
                st.report.checkpoints.push(CheckpointRecord {
                    step: done,
                    score: None,
                    dir: Some(dir.clone()),
                });
                log.flush()?;
                to_host(&mut st, &vars, &opt)?;
                st.save_step(write_model, &dir, batcher.rng.state(), &names, &cfg)?;
            }
        }
        finish(Some(&out), &mut log, st, &cfg)
    }

    /// Time training steps of `head` on `data` and `vl` (as [`run`](Self::run) takes them):
    /// `warmup` untimed steps, then `steps` timed ones, each the step [`run`](Self::run)
    /// takes (the same function: batch draw, upload, forward with the dropout, loss,
    /// backward, clip, AdamW) from a fresh optimiser state, at the learning rates of
    /// steps `0..warmup + steps` of the configured schedule. Nothing is written (no output
    /// directory, log or checkpoint; the spec's checks are the run's). The head keeps the
    /// weights of the last step. Each timed step ends with the device synchronised.
    pub fn time_steps(
        self,
        head: &Gr00tN17Head,
        data: &[Episode],
        vl: &mut dyn VlFeatures,
        warmup: usize,
        steps: usize,
    ) -> Result<StepTimes> {
        let spec = self.check(head, data, vl)?;
        let cfg = self.cfg.clone();
        let dropout = self.dropout && head.config().dit.dropout > 0.0;
        let dev = head.device().clone();
        let (vars, params) = trainable(head)?;
        let parameters = params.iter().map(Vec::len).sum();
        let mut opt = DeviceAdamW::from_host(&AdamW::new(&cfg, &params), &vars)?;
        drop(params);
        let stats = Stats::identity(&spec);
        let mut batcher = Batcher::new(data, &spec, &stats, &cfg);
        batcher.full_chunks_only(data);
        let mut buf = StepBuffers::new(head, &spec, &cfg, &self.spec, data, &*vl)?;
        let mut seconds = Vec::with_capacity(steps);
        let mut last_loss = f32::NAN;
        for step in 0..warmup + steps {
            let t0 = std::time::Instant::now();
            let (loss, _) = train_step(
                head,
                StepInputs {
                    data,
                    vl,
                    targets: self.targets,
                    dropout,
                    cfg: &cfg,
                    step,
                    lr: cfg.lr_at(step),
                },
                &mut batcher,
                &mut buf,
                &vars,
                &mut opt,
            )?;
            dev.synchronize()?;
            if step >= warmup {
                seconds.push(t0.elapsed().as_secs_f64());
            }
            last_loss = loss;
        }
        Ok(StepTimes {
            seconds,
            parameters,
            last_loss,
        })
    }
}

#[cfg(test)]
mod tests {
    use std::time::Instant;

    use candle_core::Device;

    use super::*;
    use crate::gr00t::n17::{DropoutSite, MaskSource};

    /// Not a check but a measurement (it asserts only that both optimisers write the same
    /// bits): training steps of the reference fixture's tiny head on the CPU, the AdamW
    /// update on host copies (weights and gradients to `Vec<f32>`, back with `Var::set`, the
    /// trainer's former path) against [`DeviceAdamW`], in interleaved rounds; then a DiT
    /// dropout mask built on the host against one built with device ops. Prints the
    /// medians and their ratios:
    /// `cargo test -p pir2-backends --features gr00t --lib step_timing -- --ignored --nocapture`.
    #[test]
    #[ignore = "a measurement: prints timings"]
    fn host_and_device_adamw_step_timing() {
        let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/gr00t_n17_head");
        let dir = std::env::temp_dir().join(format!("pir2-adamw-timing-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::copy(
            fixtures.join("alt.weights.safetensors"),
            dir.join("model.safetensors"),
        )
        .unwrap();
        std::fs::copy(fixtures.join("alt.config.json"), dir.join("config.json")).unwrap();
        let dev = Device::Cpu;
        let heads = [
            Gr00tN17Head::load_trainable(&dir, 2, &dev).unwrap(),
            Gr00tN17Head::load_trainable(&dir, 2, &dev).unwrap(),
        ];
        let _ = std::fs::remove_dir_all(&dir);
        let io = candle_core::safetensors::load(fixtures.join("alt.io.safetensors"), &dev).unwrap();
        let get = |k: &str| &io[k];
        let vars: Vec<Vec<Var>> = heads
            .iter()
            .map(|h| h.trainable_vars().iter().map(|(_, v)| v.clone()).collect())
            .collect();
        let n_params: usize = vars[0].iter().map(|v| v.elem_count()).sum();
        let cfg = TrainConfig {
            weight_decay: 0.05,
            ..TrainConfig::default()
        };
        let host_params: Vec<Vec<f32>> = vars[0]
            .iter()
            .map(|v| {
                v.as_tensor()
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap()
            })
            .collect();
        let mut host = (AdamW::new(&cfg, &host_params), host_params);
        let mut grads: Vec<Vec<f32>> = host.1.iter().map(|p| vec![0.0; p.len()]).collect();
        let mut device = DeviceAdamW::from_host(&host.0, &vars[1]).unwrap();

        let b = get("in.actions").dim(0).unwrap();
        let d_vis = Tensor::zeros(b, DType::U32, &dev).unwrap();
        // One step of head `k`; returns (whole step, optimiser part) in seconds.
        let mut step = |k: usize, lr: f64| -> (f64, f64) {
            let t0 = Instant::now();
            let head = &heads[k];
            let ids = get("in.embodiment_id");
            let vl = head.process_backbone(get("in.backbone_features")).unwrap();
            let s = head.encode_state(get("in.state"), ids).unwrap();
            let tokens = VlTokens {
                embeddings: &vl,
                attention_mask: Some(get("in.backbone_attention_mask")),
                image_mask: Some(get("in.image_mask")),
                d_vis: Some(&d_vis),
            };
            let ts = Timesteps::Shared(get("in.timesteps"));
            let v = head
                .velocity(&s, get("in.actions"), ts, &tokens, ids)
                .unwrap();
            let loss = v.sqr().unwrap().mean_all().unwrap();
            let mut gs = loss.backward().unwrap();
            clip_grad_store(&mut gs, &vars[k], Some(1.0)).unwrap();
            let t1 = Instant::now();
            if k == 0 {
                for (g, v) in grads.iter_mut().zip(&vars[0]) {
                    match gs.get(v.as_tensor()) {
                        Some(t) => g.copy_from_slice(&t.flatten_all().unwrap().to_vec1().unwrap()),
                        None => g.fill(0.0),
                    }
                }
                host.0.step(&mut host.1, &grads, lr);
                for (v, p) in vars[0].iter().zip(&host.1) {
                    v.set(&Tensor::from_slice(p, v.dims(), &dev).unwrap())
                        .unwrap();
                }
            } else {
                device.step(&vars[1], &gs, lr).unwrap();
            }
            let t2 = Instant::now();
            ((t2 - t0).as_secs_f64(), (t2 - t1).as_secs_f64())
        };
        let (rounds, per) = (6, 10);
        let mut t = [Vec::new(), Vec::new()];
        for r in 0..rounds {
            for (k, tk) in t.iter_mut().enumerate() {
                for i in 0..per {
                    let lr = cfg.lr_at(r * per + i);
                    let x = step(k, lr);
                    if r > 0 {
                        tk.push(x);
                    }
                }
            }
        }
        let median = |xs: &mut Vec<f64>| {
            xs.sort_by(f64::total_cmp);
            xs[xs.len() / 2]
        };
        let [h, d] = t;
        let (mut hs, mut ho): (Vec<f64>, Vec<f64>) = h.into_iter().unzip();
        let (mut ds, mut dopt): (Vec<f64>, Vec<f64>) = d.into_iter().unzip();
        let (hs, ho, ds, dopt) = (
            median(&mut hs),
            median(&mut ho),
            median(&mut ds),
            median(&mut dopt),
        );
        println!(
            "tiny GR00T head, {n_params} parameters in {} tensors, batch {}:",
            vars[0].len(),
            get("in.actions").dim(0).unwrap()
        );
        println!(
            "  step: host AdamW {:.3} ms, device AdamW {:.3} ms, device/host {:.3}",
            hs * 1e3,
            ds * 1e3,
            ds / hs
        );
        println!(
            "  optimiser only: host {:.3} ms, device {:.3} ms, device/host {:.3}",
            ho * 1e3,
            dopt * 1e3,
            dopt / ho
        );
        for (a, b) in vars[0].iter().zip(&vars[1]) {
            let bits = |v: &Var| {
                let x = v
                    .as_tensor()
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap();
                x.iter().map(|f| f.to_bits()).collect::<Vec<_>>()
            };
            assert_eq!(bits(a), bits(b), "the two optimisers wrote other weights");
        }

        // One DiT dropout mask at the paper's batch (512) for this head's FF width.
        let c = heads[0].config();
        let d = DitDropout::from_config(&c.dit, 1, 2);
        let inner = heads[0]
            .trainable_vars()
            .iter()
            .find(|(n, _)| n.ends_with("ff.net.0.proj.weight"))
            .map(|(_, v)| v.dim(0).unwrap())
            .unwrap();
        let shape = (512, 1 + c.max_seq_len.min(17), inner);
        let time = |src: MaskSource| {
            let mut xs: Vec<f64> = (0..5)
                .map(|_| {
                    let t0 = Instant::now();
                    d.mask_tensor(DropoutSite::FeedForwardInner(0), shape, &dev, src)
                        .unwrap();
                    t0.elapsed().as_secs_f64()
                })
                .collect();
            median(&mut xs)
        };
        let (mh, md) = (time(MaskSource::Host), time(MaskSource::Device));
        println!(
            "  dropout mask {shape:?}: host-built {:.2} ms, device-built (CPU) {:.2} ms, ratio {:.2}",
            mh * 1e3,
            md * 1e3,
            md / mh
        );
    }
}
