//! The trainer: AdamW, cosine LR with warm-up, grad-norm clipping, EMA, masked per-position
//! MSE on draws from the deployment's own schedule family, closed-loop checkpoint selection.
//!
//! Each sample: a frame `t` drawn uniformly over all frames; the fast history
//! `o_{t−n_obs+1..t}` (clamped at the episode start); the slow features of frame
//! `max(0, t − d_vis)` with `d_vis ~ U{0..d_vis_max}`; the action chunk `a_{t..t+H}` (the last
//! action repeats past the end), normalised; `τ`/mask from [`TrainSchedule::draw`] and the
//! input/target from [`Draw::build`]. The loss is `Σ_p mask_p·|v_p − target_p|² / (A·Σ_p mask_p)`.
//!
//! Checkpoints are chosen by the caller's closed-loop validation (docs/method.md §1): every
//! `checkpoint_every` steps and at the end, the trainer calls `validate(&mut model, step)` on
//! the evaluated weights (EMA if enabled); the highest score wins. Loss alone picks policies
//! that drift in closed loop.
//!
//! ```no_run
//! # use pir2_backends::{candle::CandleModel, train::*, config::*};
//! # fn demo(episodes: Vec<Episode>, cfg: Config) -> pir2_backends::Result<()> {
//! let stats = compute_stats(episodes.as_slice(), &cfg.spec)?;
//! let mut model = CandleModel::new(cfg, stats, 0)?;
//! let report = Trainer::new(TrainConfig { steps: 3000, ..TrainConfig::default() })
//!     .out_dir("runs/mlp")
//!     .validate(|m: &mut CandleModel, step| { let _ = (m, step); 0.0 /* closed-loop success */ })
//!     .on_progress(|p: &Progress| eprintln!("{} {:.4}", p.step, p.loss))
//!     .run(&mut model, episodes.as_slice())?;
//! # let _ = report; Ok(()) }
//! ```

use std::io::Write;
use std::path::{Path, PathBuf};

use candle_core::Tensor;
use pir2_runtime::model::{ModelInput, SlowInput};
use pir2_schedule::train::{Draw, PiR2Draws, TrainSchedule};
use pir2_schedule::Rng;
use serde::{Deserialize, Serialize};

use crate::candle::{kernels, CandleModel};
use crate::config::{Norm, SlowSpec, Spec, Stats};
use crate::error::{Error, Result};

mod batcher;
mod data;
mod optim;
mod run;
mod state;

pub(crate) use batcher::Batcher;
pub(crate) use data::check_dataset;
pub use data::{compute_stats, Dataset, Episode};
pub(crate) use optim::{clip_grad_store, clip_grads, AdamW, DeviceAdamW};
pub(crate) use run::{
    backward_to_host, finish, masked_mse, run_controls, step_dir, LossLog, RunControl,
};
pub(crate) use state::{latest_step_checkpoint, remove_interrupted, State, INTERRUPTED_PREFIX};

// ---------------------------------------------------------------- config

/// Train on buffers partly denoised by the model itself (docs/method.md §1: a fix worth measuring).
///
/// For a fraction `prob` of the samples, each non-front position with `τ_p ≤ 0.95` starts one
/// step earlier, at `max(0, τ_p − step)`, on the noised ground truth; the model (no gradient)
/// takes that Euler step to `τ_p`, and the target becomes the velocity that carries the
/// model's own state to the ground truth: `(a_p − x_p)/(1 − τ_p)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SelfRollout {
    /// Fraction of samples rolled by the model.
    pub prob: f32,
    /// The Euler step taken by the model (e.g. `1/n`).
    pub step: f32,
}

/// Trainer hyper-parameters (defaults: the Leap-cube recipe of docs/method.md §4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrainConfig {
    /// Optimiser steps.
    pub steps: usize,
    /// Samples per step.
    pub batch_size: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Final learning rate of the cosine decay.
    pub min_lr: f64,
    /// Linear warm-up steps.
    pub warmup: usize,
    /// AdamW `(β1, β2)`.
    pub betas: (f64, f64),
    /// AdamW `ε`.
    pub eps: f64,
    /// Decoupled weight decay.
    pub weight_decay: f64,
    /// Global grad-norm clip (`None`: no clipping).
    pub grad_clip: Option<f64>,
    /// EMA decay of the evaluated weights (`None`: evaluate the raw weights).
    pub ema: Option<f64>,
    /// Seed of every random draw of the trainer (frames, delays, noise, schedule draws).
    pub seed: u64,
    /// The schedule family (use the deployment's family and `n`).
    pub schedule: TrainSchedule,
    /// Validate/checkpoint every this many steps (and always at the end).
    pub checkpoint_every: Option<usize>,
    /// Optional training on self-rolled buffers.
    pub self_rollout: Option<SelfRollout>,
    /// Write a loss-log line every this many steps.
    pub log_every: usize,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            steps: 3000,
            batch_size: 256,
            lr: 1e-4,
            min_lr: 0.0,
            warmup: 500,
            betas: (0.95, 0.999),
            eps: 1e-8,
            weight_decay: 1e-6,
            grad_clip: Some(1.0),
            ema: None,
            seed: 0,
            schedule: TrainSchedule::PiR2(PiR2Draws {
                n: Some(2),
                ..PiR2Draws::default()
            }),
            checkpoint_every: None,
            self_rollout: None,
            log_every: 10,
        }
    }
}

impl TrainConfig {
    /// Learning rate at `step` (0-based): linear warm-up to `lr`, cosine down to `min_lr`.
    pub fn lr_at(&self, step: usize) -> f64 {
        if step < self.warmup {
            return self.lr * (step + 1) as f64 / self.warmup as f64;
        }
        let span = self.steps.saturating_sub(self.warmup).max(1) as f64;
        let p = ((step - self.warmup) as f64 / span).min(1.0);
        self.min_lr + 0.5 * (self.lr - self.min_lr) * (1.0 + (std::f64::consts::PI * p).cos())
    }

    pub(crate) fn validate(&self, h: usize) -> Result<()> {
        if self.steps == 0 || self.batch_size == 0 {
            return Err(Error::config("train.steps/batch_size", "must be >= 1"));
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            return Err(Error::config(
                "train.lr",
                format!("must be > 0, got {}", self.lr),
            ));
        }
        if let Some(e) = self.ema {
            if !(0.0..1.0).contains(&e) {
                return Err(Error::config(
                    "train.ema",
                    format!("must be in [0,1), got {e}"),
                ));
            }
        }
        if let Some(r) = self.self_rollout {
            if !((0.0..=1.0).contains(&r.prob) && r.step > 0.0 && r.step <= 1.0) {
                return Err(Error::config(
                    "train.self_rollout",
                    "prob in [0,1], step in (0,1]",
                ));
            }
        }
        self.schedule.validate(h)?;
        Ok(())
    }
}

// ---------------------------------------------------------------- hooks and report

/// Progress of one step (for a progress bar).
#[derive(Debug, Clone, Copy)]
pub struct Progress {
    /// Steps done (1-based).
    pub step: usize,
    /// Total steps.
    pub steps: usize,
    /// This step's loss.
    pub loss: f32,
    /// This step's learning rate.
    pub lr: f64,
    /// Global grad norm before clipping.
    pub grad_norm: f32,
}

/// One evaluated checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointRecord {
    /// Step.
    pub step: usize,
    /// Validation score (higher is better), if a validator was given.
    pub score: Option<f64>,
    /// Directory, if an output directory was given.
    pub dir: Option<PathBuf>,
}

/// What a training run did.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TrainReport {
    /// `(step, loss)` of every step.
    pub losses: Vec<(usize, f32)>,
    /// Every evaluated checkpoint.
    pub checkpoints: Vec<CheckpointRecord>,
    /// The best checkpoint by validation score (the model holds these weights on return).
    pub best: Option<CheckpointRecord>,
}

pub(crate) type ProgressFn<'a> = Box<dyn FnMut(&Progress) + 'a>;
type ValidateFn<'a> = Box<dyn FnMut(&mut CandleModel, usize) -> f64 + 'a>;

/// Files the trainer adds to every step checkpoint so a run can continue from it
/// ([`Trainer::resume`]).
pub const TRAIN_STATE_FILE: &str = "train_state.json";
/// Raw weights, AdamW moments, EMA and best weights of a step checkpoint.
pub const TRAIN_TENSORS_FILE: &str = "train_state.safetensors";

/// Builder and runner of one training run.
pub struct Trainer<'a> {
    cfg: TrainConfig,
    ctl: RunControl<'a>,
    validate: Option<ValidateFn<'a>>,
    out_dir: Option<PathBuf>,
    log: Option<Box<dyn Write + 'a>>,
    fused: bool,
    later_ties: bool,
}

impl std::fmt::Debug for Trainer<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Trainer")
            .field("cfg", &self.cfg)
            .field("out_dir", &self.out_dir)
            .field("resume", &self.ctl.resume)
            .field("fused", &self.fused)
            .finish_non_exhaustive()
    }
}

impl<'a> Trainer<'a> {
    /// A trainer with the given hyper-parameters.
    pub fn new(cfg: TrainConfig) -> Self {
        Self {
            cfg,
            ctl: RunControl::default(),
            validate: None,
            out_dir: None,
            log: None,
            fused: true,
            later_ties: false,
        }
    }
    run_controls!();
    /// Closed-loop validation: returns a score, higher is better (e.g. success rate).
    pub fn validate(mut self, f: impl FnMut(&mut CandleModel, usize) -> f64 + 'a) -> Self {
        self.validate = Some(Box::new(f));
        self
    }
    /// How a validation score equal to the best so far is treated: `false` (default) keeps
    /// the earlier checkpoint, `true` moves the pick to the later one. With a noisy score
    /// (few closed-loop episodes, coarse success rates) ties are common, and keeping the
    /// first tie tends to deploy under-trained weights; the later checkpoint has seen more
    /// data for the same measured quality.
    pub fn later_ties(mut self, on: bool) -> Self {
        self.later_ties = on;
        self
    }
    /// Save checkpoints to `dir/step-NNNNNN/`, the loss log to `dir/loss.jsonl`, and the
    /// best pick to `dir/best.json`. `run` fails at once if `dir` already holds `step-*`
    /// checkpoints, unless [`Trainer::resume`] is on.
    pub fn out_dir(mut self, dir: impl AsRef<Path>) -> Self {
        self.out_dir = Some(dir.as_ref().to_owned());
        self
    }
    /// Also write the JSON-lines loss log to `w`.
    pub fn log_to(mut self, w: impl Write + 'a) -> Self {
        self.log = Some(Box::new(w));
        self
    }
    /// Train a U-Net with the hand-written host kernels (default `true`; see
    /// [`CandleModel::set_fused`]); `false` uses candle's autograd graph. Other architectures
    /// always use candle's autograd.
    pub fn fused(mut self, on: bool) -> Self {
        self.fused = on;
        self
    }

    /// Train `model` on `data`. On return the model holds the best validated weights (EMA
    /// weights if EMA is on), or the final (EMA) weights without a validator.
    pub fn run<D: Dataset + ?Sized>(
        mut self,
        model: &mut CandleModel,
        data: &D,
    ) -> Result<TrainReport> {
        let spec = *model.spec();
        let cfg = self.cfg.clone();
        cfg.validate(spec.horizon)?;
        check_dataset(data, &spec)?;
        if self.ctl.resume && self.out_dir.is_none() {
            return Err(Error::config(
                "train.resume",
                "needs an output directory (Trainer::out_dir)",
            ));
        }
        let out_dir = self.out_dir.clone();
        let resume_from = match &out_dir {
            Some(d) => self.ctl.prepare(d)?,
            None => None,
        };
        let mut log = LossLog::open(out_dir.as_deref(), self.log.take())?;

        let names: Vec<String> = model.vars().iter().map(|(n, _)| n.clone()).collect();
        let params = model.host_params()?;
        let mut st = State {
            step: 0,
            opt: AdamW::new(&cfg, &params),
            ema: cfg.ema.map(|_| params.clone()),
            params,
            best: None,
            report: TrainReport::default(),
        };
        let mut batcher = Batcher::new(data, &spec, model.stats(), &cfg);
        if let Some(dir) = &resume_from {
            let rng = st.load(dir, &cfg, &names)?;
            batcher.rng = rng;
            // A finished run resumed: leave the model as the run left it (best, else EMA).
            let done = st.step >= cfg.steps;
            match (&st.best, &st.ema) {
                (Some((_, w)), _) if done => model.set_host_params(w)?,
                (None, Some(e)) if done => model.set_host_params(e)?,
                _ => model.set_host_params(&st.params)?,
            }
        }
        let mut grads: Vec<Vec<f32>> = st.params.iter().map(|p| vec![0.0; p.len()]).collect();
        let mut fused_net = if self.fused { model.fast_unet()? } else { None };
        let par = kernels::parallelism(rayon::current_num_threads());
        let mut dv = Vec::new();
        // The model's variables lag `st.params` (fused path only).
        let mut stale = false;
        let vars: Vec<_> = model.vars().iter().map(|(_, v)| v.clone()).collect();

        for step in st.step..cfg.steps {
            let stop = self
                .ctl
                .stop_before(step, out_dir.as_deref(), &mut log, |p| {
                    if stale {
                        model.set_host_params(&st.params)?;
                    }
                    st.save_step(
                        |dir| model.write_files(dir),
                        p,
                        batcher.rng.state(),
                        &names,
                        &cfg,
                    )
                })?;
            if stop {
                break;
            }
            let lr = cfg.lr_at(step);
            batcher.fill(data)?;
            if let Some(r) = cfg.self_rollout {
                if stale {
                    model.set_host_params(&st.params)?;
                    stale = false;
                }
                batcher.self_roll(model, r)?;
            }
            for g in grads.iter_mut() {
                g.fill(0.0);
            }
            let a = spec.action_dim;
            let mut gn = None;
            let msum: f32 = batcher.mask.iter().sum();
            let denom = msum.max(1.0) * a as f32;
            let loss_v = match fused_net.as_mut() {
                Some(net) => {
                    let input = batcher.input();
                    let hb = model.host_batch(&input)?;
                    let v = net.forward(par, &st.params, &hb);
                    dv.resize(v.len(), 0.0);
                    let mut loss = 0.0f64;
                    for (i, ((d, &vi), &t)) in dv.iter_mut().zip(v).zip(&batcher.target).enumerate()
                    {
                        let m = batcher.mask[i / a];
                        let e = vi - t;
                        loss += (m * e * e) as f64;
                        *d = 2.0 * m * e / denom;
                    }
                    net.backward(par, &st.params, &mut grads, &dv);
                    (loss / denom as f64) as f32
                }
                None => {
                    let v = model.forward_input(&batcher.input())?;
                    let loss = masked_mse(v, &batcher.target, &batcher.mask)?;
                    let lv = loss.to_scalar::<f32>()?;
                    if lv.is_finite() {
                        // Clip in candle as before the host optimiser existed: same bits.
                        gn = Some(backward_to_host(&loss, &vars, cfg.grad_clip, &mut grads)?);
                    }
                    lv
                }
            };
            if !loss_v.is_finite() {
                return Err(Error::Diverged {
                    step: step + 1,
                    loss: loss_v,
                });
            }
            let gn = match gn {
                Some(gn) => gn,
                None => clip_grads(&mut grads, cfg.grad_clip),
            };
            st.opt.step(&mut st.params, &grads, lr);
            if fused_net.is_some() {
                // The host kernels read `st.params`; the model's variables catch up when needed.
                stale = true;
            } else {
                model.set_host_params(&st.params)?;
            }
            if let (Some(e), Some(decay)) = (st.ema.as_mut(), cfg.ema) {
                let d = decay.min((1 + step) as f64 / (10 + step) as f64);
                let (df, cf) = (d as f32, (1.0 - d) as f32);
                for (m, p) in e.iter_mut().zip(&st.params) {
                    for (mi, &pi) in m.iter_mut().zip(p) {
                        *mi = *mi * df + pi * cf;
                    }
                }
            }
            let done = step + 1;
            let at_ckpt = self.ctl.after_step(
                &cfg,
                &mut st,
                &mut log,
                Progress {
                    step: done,
                    steps: cfg.steps,
                    loss: loss_v,
                    lr,
                    grad_norm: gn,
                },
            )?;
            if !at_ckpt || (self.validate.is_none() && self.out_dir.is_none() && done != cfg.steps)
            {
                continue;
            }
            // Evaluate the EMA weights (swap in, evaluate, swap back).
            match &st.ema {
                Some(e) => model.set_host_params(e)?,
                None if stale => model.set_host_params(&st.params)?,
                None => {}
            }
            stale = false;
            let score = self.validate.as_mut().map(|f| f(model, done));
            let step_dir = out_dir.as_deref().map(|d| step_dir(d, done));
            if let Some(s) = score {
                log.line(&format!(r#"{{"step":{done},"val":{s}}}"#))?;
                let later_ties = self.later_ties;
                if st
                    .best
                    .as_ref()
                    .is_none_or(|(b, _)| s > *b || (later_ties && s == *b))
                {
                    st.best = Some((s, st.ema.as_ref().unwrap_or(&st.params).clone()));
                    st.report.best = Some(CheckpointRecord {
                        step: done,
                        score,
                        dir: step_dir.clone(),
                    });
                }
            }
            st.report.checkpoints.push(CheckpointRecord {
                step: done,
                score,
                dir: step_dir.clone(),
            });
            if let (Some(d), Some(p)) = (out_dir.as_deref(), &step_dir) {
                // Flush the log first: a resumed run appends after what is on disk.
                log.flush()?;
                st.save_step(
                    |dir| model.write_files(dir),
                    p,
                    batcher.rng.state(),
                    &names,
                    &cfg,
                )?;
                if score.is_some() && st.report.best.as_ref().is_some_and(|b| b.step == done) {
                    let path = d.join("best.json");
                    let text = serde_json::to_string_pretty(&st.report.best).map_err(|e| {
                        Error::Format {
                            path: path.clone(),
                            message: e.to_string(),
                        }
                    })?;
                    crate::checkpoint::write_durable(&path, text.as_bytes())?;
                }
            }
            if done == cfg.steps {
                // Leave the evaluated (EMA) weights in the model, then the best if validated.
                if let Some((_, w)) = &st.best {
                    model.set_host_params(w)?;
                }
            } else if st.ema.is_some() {
                model.set_host_params(&st.params)?;
            }
        }
        if stale {
            model.set_host_params(&st.params)?;
        }
        finish(out_dir.as_deref(), &mut log, st, &cfg)
    }
}

/// Mean flow-matching loss of `model` on `data` (e.g. held-out episodes) under `schedule`:
/// `batches` batches of `batch_size` samples drawn exactly as in training (frames, `d_vis`,
/// noise, schedule draws) from `seed`, the loss of each as the trainer's masked per-position
/// MSE, averaged over batches. No gradient, no update. The same arguments draw the same
/// samples, so checkpoints of one run are compared on identical draws.
pub fn held_out_loss<D: Dataset + ?Sized>(
    model: &mut CandleModel,
    data: &D,
    schedule: TrainSchedule,
    batch_size: usize,
    batches: usize,
    seed: u64,
) -> Result<f64> {
    let spec = *model.spec();
    check_dataset(data, &spec)?;
    let cfg = TrainConfig {
        batch_size: batch_size.max(1),
        seed,
        schedule,
        ..TrainConfig::default()
    };
    cfg.schedule.validate(spec.horizon)?;
    let mut batcher = Batcher::new(data, &spec, model.stats(), &cfg);
    let a = spec.action_dim;
    let mut v = vec![0.0f32; cfg.batch_size * spec.horizon * a];
    let mut total = 0.0f64;
    for _ in 0..batches.max(1) {
        batcher.fill(data)?;
        model.velocity_into(&batcher.input(), &mut v)?;
        let msum: f32 = batcher.mask.iter().sum();
        let mut loss = 0.0f64;
        for (i, (&vi, &t)) in v.iter().zip(&batcher.target).enumerate() {
            let e = (vi - t) as f64;
            loss += batcher.mask[i / a] as f64 * e * e;
        }
        total += loss / (msum.max(1.0) as f64 * a as f64);
    }
    Ok(total / batches.max(1) as f64)
}
