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

use candle_core::{Device, Tensor};
use pir2_runtime::model::{ModelInput, SlowInput};
use pir2_schedule::train::{Draw, PiR2Draws, TrainSchedule};
use pir2_schedule::Rng;
use serde::{Deserialize, Serialize};

use crate::candle::{kernels, CandleModel};
use crate::config::{Norm, SlowSpec, Spec, Stats};
use crate::error::{Error, Result};

// ---------------------------------------------------------------- dataset

/// Frame-indexed demonstrations. Frames of one episode are consecutive control ticks.
pub trait Dataset {
    /// Number of episodes.
    fn num_episodes(&self) -> usize;
    /// Frames in episode `e` (≥ 1).
    fn episode_len(&self, e: usize) -> usize;
    /// Fast observation of frame `t` (`F` values).
    fn fast(&self, e: usize, t: usize) -> &[f32];
    /// Slow features of frame `t` (`S` or `T·D` values; empty without a slow channel).
    fn slow(&self, e: usize, t: usize) -> &[f32];
    /// Action of frame `t` (`A` values, raw units).
    fn action(&self, e: usize, t: usize) -> &[f32];
}

/// One in-memory episode: row-major per-frame fast obs, slow features and actions.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Episode {
    /// Fast observation width `F`.
    pub fast_dim: usize,
    /// Slow values per frame (`S` or `T·D`, 0 for none).
    pub slow_len: usize,
    /// Action width `A`.
    pub action_dim: usize,
    /// `[len, F]`.
    pub fast: Vec<f32>,
    /// `[len, slow_len]`.
    pub slow: Vec<f32>,
    /// `[len, A]`.
    pub action: Vec<f32>,
}

impl Episode {
    /// An empty episode with the given widths.
    pub fn new(fast_dim: usize, slow_len: usize, action_dim: usize) -> Self {
        Self {
            fast_dim,
            slow_len,
            action_dim,
            ..Default::default()
        }
    }
    /// Append one frame.
    pub fn push(&mut self, fast: &[f32], slow: &[f32], action: &[f32]) {
        debug_assert_eq!(fast.len(), self.fast_dim);
        debug_assert_eq!(slow.len(), self.slow_len);
        debug_assert_eq!(action.len(), self.action_dim);
        self.fast.extend_from_slice(fast);
        self.slow.extend_from_slice(slow);
        self.action.extend_from_slice(action);
    }
    /// Frames.
    pub fn len(&self) -> usize {
        self.action.len().checked_div(self.action_dim).unwrap_or(0)
    }
    /// Whether the episode has no frames.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl Dataset for [Episode] {
    fn num_episodes(&self) -> usize {
        self.len()
    }
    fn episode_len(&self, e: usize) -> usize {
        self[e].len()
    }
    fn fast(&self, e: usize, t: usize) -> &[f32] {
        let f = self[e].fast_dim;
        &self[e].fast[t * f..(t + 1) * f]
    }
    fn slow(&self, e: usize, t: usize) -> &[f32] {
        let s = self[e].slow_len;
        &self[e].slow[t * s..(t + 1) * s]
    }
    fn action(&self, e: usize, t: usize) -> &[f32] {
        let a = self[e].action_dim;
        &self[e].action[t * a..(t + 1) * a]
    }
}

fn check_dataset<D: Dataset + ?Sized>(data: &D, spec: &Spec) -> Result<()> {
    if data.num_episodes() == 0 {
        return Err(Error::Dataset("no episodes".into()));
    }
    for e in 0..data.num_episodes() {
        if data.episode_len(e) == 0 {
            return Err(Error::Dataset(format!("episode {e} is empty")));
        }
        let (f, s, a) = (
            data.fast(e, 0).len(),
            data.slow(e, 0).len(),
            data.action(e, 0).len(),
        );
        if f != spec.fast_dim || s != spec.slow.len() || a != spec.action_dim {
            return Err(Error::Dataset(format!(
                "episode {e}: frame widths fast/slow/action = {f}/{s}/{a}, the spec wants {}/{}/{}",
                spec.fast_dim,
                spec.slow.len(),
                spec.action_dim
            )));
        }
    }
    Ok(())
}

/// Normalisation statistics of a dataset (std floored at 1e-4): fast obs, successive fast
/// differences within episodes, slow features (per token width), actions.
pub fn compute_stats<D: Dataset + ?Sized>(data: &D, spec: &Spec) -> Result<Stats> {
    spec.validate()?;
    check_dataset(data, spec)?;
    let f = spec.fast_dim;
    let (mut fast, mut diff) = (Norm::accumulator(f), Norm::accumulator(f));
    let mut slow = Norm::accumulator(spec.slow.width());
    let mut act = Norm::accumulator(spec.action_dim);
    let mut d = vec![0.0f32; f];
    for e in 0..data.num_episodes() {
        for t in 0..data.episode_len(e) {
            let o = data.fast(e, t);
            fast.push(o);
            if t > 0 {
                for ((dj, &a), &b) in d.iter_mut().zip(o).zip(data.fast(e, t - 1)) {
                    *dj = a - b;
                }
                diff.push(&d);
            }
            if spec.slow.width() > 0 {
                for row in data.slow(e, t).chunks(spec.slow.width()) {
                    slow.push(row);
                }
            }
            act.push(data.action(e, t));
        }
    }
    let floor = 1e-4;
    Ok(Stats {
        fast: fast.finish(floor),
        fast_diff: diff.finish(floor),
        slow: slow.finish(floor),
        action: act.finish(floor),
    })
}

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

    fn validate(&self, h: usize) -> Result<()> {
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

type ProgressFn<'a> = Box<dyn FnMut(&Progress) + 'a>;
type ValidateFn<'a> = Box<dyn FnMut(&mut CandleModel, usize) -> f64 + 'a>;

/// Files the trainer adds to every step checkpoint so a run can continue from it
/// ([`Trainer::resume`]).
pub const TRAIN_STATE_FILE: &str = "train_state.json";
/// Raw weights, AdamW moments, EMA and best weights of a step checkpoint.
pub const TRAIN_TENSORS_FILE: &str = "train_state.safetensors";

/// Builder and runner of one training run.
pub struct Trainer<'a> {
    cfg: TrainConfig,
    progress: Option<ProgressFn<'a>>,
    validate: Option<ValidateFn<'a>>,
    out_dir: Option<PathBuf>,
    log: Option<Box<dyn Write + 'a>>,
    resume: bool,
    fused: bool,
    stop_after: Option<usize>,
    later_ties: bool,
}

impl std::fmt::Debug for Trainer<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Trainer")
            .field("cfg", &self.cfg)
            .field("out_dir", &self.out_dir)
            .field("resume", &self.resume)
            .field("fused", &self.fused)
            .finish_non_exhaustive()
    }
}

impl<'a> Trainer<'a> {
    /// A trainer with the given hyper-parameters.
    pub fn new(cfg: TrainConfig) -> Self {
        Self {
            cfg,
            progress: None,
            validate: None,
            out_dir: None,
            log: None,
            resume: false,
            fused: true,
            stop_after: None,
            later_ties: false,
        }
    }
    /// Called after every step.
    pub fn on_progress(mut self, f: impl FnMut(&Progress) + 'a) -> Self {
        self.progress = Some(Box::new(f));
        self
    }
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
    /// Continue from the last step checkpoint in [`Trainer::out_dir`] (default off).
    ///
    /// Every step checkpoint carries the full training state ([`TRAIN_STATE_FILE`],
    /// [`TRAIN_TENSORS_FILE`]: raw weights, AdamW moments and step count, EMA, the best pick
    /// so far, the batch generator's random state, the loss history), so a resumed run
    /// continues **bit-identically** to an uninterrupted one with the same configuration,
    /// data and thread count. The model's own weights are replaced by the checkpoint's. With
    /// no step checkpoint in the directory the run starts from scratch; a checkpoint written
    /// with a different [`TrainConfig`] or model is an error naming the difference. Steps
    /// after the checkpoint that an interrupted run had logged appear twice in `loss.jsonl`.
    pub fn resume(mut self, on: bool) -> Self {
        self.resume = on;
        self
    }
    /// Return once `steps` steps are done (counted from step 0, not from a resume point), as
    /// if the run had been interrupted there: no extra validation or checkpoint is made, the
    /// model holds the raw weights of that step, and a later run with [`Trainer::resume`]
    /// continues from the last step checkpoint written. For time-sliced training and tests.
    pub fn stop_after(mut self, steps: usize) -> Self {
        self.stop_after = Some(steps);
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
        if self.resume && self.out_dir.is_none() {
            return Err(Error::config(
                "train.resume",
                "needs an output directory (Trainer::out_dir)",
            ));
        }
        let resume_from = match (&self.out_dir, self.resume) {
            (Some(d), true) => latest_step_checkpoint(d)?,
            _ => None,
        };
        let mut file_log = match &self.out_dir {
            Some(d) => {
                // Fail now, not after hours of training, if earlier checkpoints are in the way.
                if !self.resume {
                    if let Ok(rd) = std::fs::read_dir(d) {
                        for e in rd.flatten() {
                            if e.file_name().to_string_lossy().starts_with("step-") {
                                return Err(Error::CheckpointExists(e.path()));
                            }
                        }
                    }
                }
                std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
                let p = d.join("loss.jsonl");
                Some(std::io::BufWriter::new(
                    std::fs::OpenOptions::new()
                        .create(true)
                        .append(true)
                        .open(&p)
                        .map_err(|e| Error::io(&p, e))?,
                ))
            }
            None => None,
        };
        // `None` flushes the file log.
        let mut log_line = |line: Option<String>, this: &mut Self| -> Result<()> {
            let Some(line) = line else {
                if let Some(w) = file_log.as_mut() {
                    w.flush().map_err(|e| Error::io("loss.jsonl", e))?;
                }
                return Ok(());
            };
            if let Some(w) = file_log.as_mut() {
                writeln!(w, "{line}").map_err(|e| Error::io("loss.jsonl", e))?;
            }
            if let Some(w) = this.log.as_mut() {
                writeln!(w, "{line}").map_err(|e| Error::io("loss log", e))?;
            }
            Ok(())
        };

        let out_dir = self.out_dir.clone();
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
            if self.stop_after.is_some_and(|s| step >= s) {
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
                    let (v, target, mask) = {
                        let bt = &batcher;
                        let input = bt.input();
                        let v = model.forward_input(&input)?;
                        let dev = Device::Cpu;
                        let b = cfg.batch_size;
                        let target = Tensor::from_slice(&bt.target, (b, spec.horizon, a), &dev)?;
                        let mask = Tensor::from_slice(&bt.mask, (b, spec.horizon, 1), &dev)?;
                        (v, target, mask)
                    };
                    let err = (v - target)?.sqr()?.broadcast_mul(&mask)?;
                    let loss = (err.sum_all()? / (msum.max(1.0) as f64 * a as f64))?;
                    let lv = loss.to_scalar::<f32>()?;
                    if lv.is_finite() {
                        let mut gs = loss.backward()?;
                        // Clip in candle as before the host optimiser existed: same bits.
                        gn = Some(clip_grad_store(&mut gs, &vars, cfg.grad_clip)?);
                        for (g, v) in grads.iter_mut().zip(&vars) {
                            if let Some(t) = gs.get(v.as_tensor()) {
                                g.copy_from_slice(&t.flatten_all()?.to_vec1::<f32>()?);
                            }
                        }
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
            st.step = done;
            st.report.losses.push((done, loss_v));
            if done % cfg.log_every.max(1) == 0 || done == cfg.steps {
                log_line(
                    Some(format!(
                        r#"{{"step":{done},"loss":{loss_v},"lr":{lr},"grad_norm":{gn}}}"#
                    )),
                    &mut self,
                )?;
            }
            if let Some(p) = self.progress.as_mut() {
                p(&Progress {
                    step: done,
                    steps: cfg.steps,
                    loss: loss_v,
                    lr,
                    grad_norm: gn,
                });
            }
            let at_ckpt =
                cfg.checkpoint_every.is_some_and(|k| k > 0 && done % k == 0) || done == cfg.steps;
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
            let step_dir = self
                .out_dir
                .as_ref()
                .map(|d| d.join(format!("step-{done:06}")));
            if let Some(s) = score {
                log_line(Some(format!(r#"{{"step":{done},"val":{s}}}"#)), &mut self)?;
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
                log_line(None, &mut self)?;
                st.save_step(model, d, p, batcher.rng.state(), &names, &cfg)?;
                if score.is_some() && st.report.best.as_ref().is_some_and(|b| b.step == done) {
                    let path = d.join("best.json");
                    let text = serde_json::to_string_pretty(&st.report.best).map_err(|e| {
                        Error::Format {
                            path: path.clone(),
                            message: e.to_string(),
                        }
                    })?;
                    write_durable(&path, text.as_bytes())?;
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
        log_line(None, &mut self)?;
        Ok(st.report)
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

/// Global grad norm of candle gradients; scales them in place when it exceeds `clip`.
fn clip_grad_store(
    grads: &mut candle_core::backprop::GradStore,
    vars: &[candle_core::Var],
    clip: Option<f64>,
) -> Result<f32> {
    let mut sq = 0.0f64;
    for v in vars {
        if let Some(g) = grads.get(v.as_tensor()) {
            sq += g.sqr()?.sum_all()?.to_scalar::<f32>()? as f64;
        }
    }
    let norm = sq.sqrt();
    if let Some(c) = clip {
        if norm > c && norm.is_finite() {
            let s = c / (norm + 1e-6);
            for v in vars {
                if let Some(g) = grads.remove(v.as_tensor()) {
                    grads.insert(v.as_tensor(), (g * s)?);
                }
            }
        }
    }
    Ok(norm as f32)
}

/// Global grad norm (f64 accumulation); scales the gradients in place when it exceeds `clip`.
fn clip_grads(grads: &mut [Vec<f32>], clip: Option<f64>) -> f32 {
    let sq: f64 = grads
        .iter()
        .map(|g| g.iter().map(|&v| (v as f64) * (v as f64)).sum::<f64>())
        .sum();
    let norm = sq.sqrt();
    if let Some(c) = clip {
        if norm > c && norm.is_finite() {
            let s = (c / (norm + 1e-6)) as f32;
            for g in grads.iter_mut() {
                for v in g.iter_mut() {
                    *v *= s;
                }
            }
        }
    }
    norm as f32
}

// ---------------------------------------------------------------- optimiser and state

/// AdamW on host buffers, the same update as `candle_nn::AdamW` (decoupled weight decay,
/// bias-corrected moments), with state that can be saved and restored.
#[derive(Debug, Clone)]
struct AdamW {
    beta1: f64,
    beta2: f64,
    eps: f64,
    weight_decay: f64,
    t: u64,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
}

impl AdamW {
    fn new(cfg: &TrainConfig, params: &[Vec<f32>]) -> Self {
        Self {
            beta1: cfg.betas.0,
            beta2: cfg.betas.1,
            eps: cfg.eps,
            weight_decay: cfg.weight_decay,
            t: 0,
            m: params.iter().map(|p| vec![0.0; p.len()]).collect(),
            v: params.iter().map(|p| vec![0.0; p.len()]).collect(),
        }
    }

    fn step(&mut self, params: &mut [Vec<f32>], grads: &[Vec<f32>], lr: f64) {
        self.t += 1;
        let (b1, b2) = (self.beta1, self.beta2);
        let scale_m = (1.0 / (1.0 - b1.powi(self.t as i32))) as f32;
        let scale_v = (1.0 / (1.0 - b2.powi(self.t as i32))) as f32;
        let decay = (1.0 - lr * self.weight_decay) as f32;
        let (b1f, c1) = (b1 as f32, (1.0 - b1) as f32);
        let (b2f, c2) = (b2 as f32, (1.0 - b2) as f32);
        let (eps, lrf) = (self.eps as f32, lr as f32);
        for (((p, g), m), v) in params
            .iter_mut()
            .zip(grads)
            .zip(self.m.iter_mut())
            .zip(self.v.iter_mut())
        {
            for (((pi, &gi), mi), vi) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                *mi = *mi * b1f + gi * c1;
                *vi = *vi * b2f + gi * gi * c2;
                let mh = *mi * scale_m;
                let vh = *vi * scale_v;
                *pi = *pi * decay - (mh / (vh.sqrt() + eps)) * lrf;
            }
        }
    }
}

/// Everything a run carries from one step to the next.
struct State {
    /// Steps done.
    step: usize,
    /// Raw (trained) weights, in [`CandleModel::vars`] order.
    params: Vec<Vec<f32>>,
    opt: AdamW,
    ema: Option<Vec<Vec<f32>>>,
    best: Option<(f64, Vec<Vec<f32>>)>,
    report: TrainReport,
}

/// The JSON part of a step checkpoint's training state.
#[derive(Debug, Serialize, Deserialize)]
struct StateMeta {
    step: usize,
    adam_t: u64,
    rng: [u64; 4],
    best_score: Option<f64>,
    config: TrainConfig,
    report: TrainReport,
}

impl State {
    /// Write the step checkpoint `dir` (model weights as evaluated + training state): into a
    /// uniquely named temp directory, every file fsynced, then renamed into place.
    fn save_step(
        &self,
        model: &CandleModel,
        out: &Path,
        dir: &Path,
        rng: [u64; 4],
        names: &[String],
        cfg: &TrainConfig,
    ) -> Result<()> {
        if dir.exists() {
            return Err(Error::CheckpointExists(dir.to_owned()));
        }
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        let leaf = dir
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_default();
        let tmp = out.join(format!(".{leaf}.tmp-{}-{nanos}", std::process::id()));
        model.save(&tmp)?;
        let meta = StateMeta {
            step: self.step,
            adam_t: self.opt.t,
            rng,
            best_score: self.best.as_ref().map(|b| b.0),
            config: cfg.clone(),
            report: self.report.clone(),
        };
        let path = tmp.join(TRAIN_STATE_FILE);
        let text = serde_json::to_string(&meta).map_err(|e| Error::Format {
            path: path.clone(),
            message: e.to_string(),
        })?;
        write_durable(&path, text.as_bytes())?;
        let mut tensors: Vec<(String, &[f32])> = Vec::new();
        for (i, n) in names.iter().enumerate() {
            tensors.push((format!("param/{n}"), &self.params[i]));
            tensors.push((format!("adam_m/{n}"), &self.opt.m[i]));
            tensors.push((format!("adam_v/{n}"), &self.opt.v[i]));
            if let Some(e) = &self.ema {
                tensors.push((format!("ema/{n}"), &e[i]));
            }
            if let Some((_, b)) = &self.best {
                tensors.push((format!("best/{n}"), &b[i]));
            }
        }
        let tpath = tmp.join(TRAIN_TENSORS_FILE);
        let st_err = |e: safetensors::SafeTensorError| Error::Safetensors {
            path: tpath.clone(),
            message: e.to_string(),
        };
        let bytes: Vec<(String, Vec<u8>)> = tensors
            .iter()
            .map(|(n, d)| (n.clone(), d.iter().flat_map(|v| v.to_le_bytes()).collect()))
            .collect();
        let mut views = Vec::with_capacity(bytes.len());
        for ((n, b), (_, d)) in bytes.iter().zip(&tensors) {
            views.push((
                n.clone(),
                safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![d.len()], b)
                    .map_err(st_err)?,
            ));
        }
        let data = safetensors::serialize(views, None).map_err(st_err)?;
        write_durable(&tpath, &data)?;
        // The model's own files (written by `CandleModel::save`), then the directories.
        for f in std::fs::read_dir(&tmp)
            .map_err(|e| Error::io(&tmp, e))?
            .flatten()
        {
            sync_path(&f.path())?;
        }
        sync_path(&tmp)?;
        std::fs::rename(&tmp, dir).map_err(|e| Error::io(dir, e))?;
        sync_path(out)
    }

    /// Read the training state of the step checkpoint `dir`; returns the batch generator.
    fn load(&mut self, dir: &Path, cfg: &TrainConfig, names: &[String]) -> Result<Rng> {
        let path = dir.join(TRAIN_STATE_FILE);
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let meta: StateMeta = serde_json::from_str(&text).map_err(|e| Error::Format {
            path: path.clone(),
            message: e.to_string(),
        })?;
        if meta.config != *cfg {
            return Err(Error::config(
                "train.resume",
                format!(
                    "{} was written with another training configuration ({:?}); resume needs the same",
                    path.display(),
                    meta.config
                ),
            ));
        }
        let tpath = dir.join(TRAIN_TENSORS_FILE);
        let bytes = std::fs::read(&tpath).map_err(|e| Error::io(&tpath, e))?;
        let st = safetensors::SafeTensors::deserialize(&bytes).map_err(|e| Error::Safetensors {
            path: tpath.clone(),
            message: e.to_string(),
        })?;
        let read = |key: String, want: usize| -> Result<Vec<f32>> {
            let v = st.tensor(&key).map_err(|e| Error::Safetensors {
                path: tpath.clone(),
                message: format!("`{key}`: {e}"),
            })?;
            let d: Vec<f32> = v
                .data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            if d.len() != want || v.dtype() != safetensors::Dtype::F32 {
                return Err(Error::shape("train state tensor", want, d.len()));
            }
            Ok(d)
        };
        for (i, n) in names.iter().enumerate() {
            let len = self.params[i].len();
            self.params[i] = read(format!("param/{n}"), len)?;
            self.opt.m[i] = read(format!("adam_m/{n}"), len)?;
            self.opt.v[i] = read(format!("adam_v/{n}"), len)?;
            if let Some(e) = self.ema.as_mut() {
                e[i] = read(format!("ema/{n}"), len)?;
            }
        }
        self.best = match meta.best_score {
            Some(s) => Some((
                s,
                names
                    .iter()
                    .zip(&self.params)
                    .map(|(n, p)| read(format!("best/{n}"), p.len()))
                    .collect::<Result<Vec<_>>>()?,
            )),
            None => None,
        };
        self.step = meta.step;
        self.opt.t = meta.adam_t;
        self.report = meta.report;
        Rng::from_state(meta.rng).ok_or_else(|| Error::Format {
            path,
            message: "all-zero random state".into(),
        })
    }
}

/// Write `bytes` to `path` and fsync it.
fn write_durable(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut f = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    f.write_all(bytes).map_err(|e| Error::io(path, e))?;
    f.sync_all().map_err(|e| Error::io(path, e))
}

/// fsync a file or a directory.
fn sync_path(path: &Path) -> Result<()> {
    std::fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(|e| Error::io(path, e))
}

/// The step checkpoint with the highest step that carries a training state, if any.
fn latest_step_checkpoint(out: &Path) -> Result<Option<PathBuf>> {
    let rd = match std::fs::read_dir(out) {
        Ok(rd) => rd,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(Error::io(out, e)),
    };
    let mut best: Option<(usize, PathBuf)> = None;
    let mut without_state = None;
    for e in rd.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(n) = name
            .strip_prefix("step-")
            .and_then(|s| s.parse::<usize>().ok())
        else {
            continue;
        };
        if !e.path().join(TRAIN_STATE_FILE).is_file() {
            without_state = Some(e.path());
            continue;
        }
        if best.as_ref().is_none_or(|(b, _)| n > *b) {
            best = Some((n, e.path()));
        }
    }
    match (best, without_state) {
        (Some((_, p)), _) => Ok(Some(p)),
        (None, Some(p)) => Err(Error::config(
            "train.resume",
            format!("{} has no training state to resume from", p.display()),
        )),
        (None, None) => Ok(None),
    }
}

// ---------------------------------------------------------------- batches

/// Builds training batches into reusable host buffers.
struct Batcher {
    spec: Spec,
    stats: Stats,
    schedule: TrainSchedule,
    b: usize,
    rng: Rng,
    /// Cumulative frame counts per episode.
    cum: Vec<usize>,
    draw: Draw,
    act: Vec<f32>,
    eps: Vec<f32>,
    x: Vec<f32>,
    tau: Vec<f32>,
    target: Vec<f32>,
    mask: Vec<f32>,
    /// Normalised ground-truth chunks (for self-rollout).
    gt: Vec<f32>,
    epsb: Vec<f32>,
    fast: Vec<f32>,
    slow: Vec<f32>,
    dvis: Vec<u32>,
}

impl Batcher {
    fn new<D: Dataset + ?Sized>(data: &D, spec: &Spec, stats: &Stats, cfg: &TrainConfig) -> Self {
        let (h, a, b) = (spec.horizon, spec.action_dim, cfg.batch_size);
        let mut cum = Vec::with_capacity(data.num_episodes());
        let mut total = 0;
        for e in 0..data.num_episodes() {
            total += data.episode_len(e);
            cum.push(total);
        }
        Self {
            spec: *spec,
            stats: stats.clone(),
            schedule: cfg.schedule,
            b,
            rng: Rng::derive(cfg.seed, 0x0074_7261_696e),
            cum,
            draw: Draw::new(h),
            act: vec![0.0; h * a],
            eps: vec![0.0; h * a],
            x: vec![0.0; b * h * a],
            tau: vec![0.0; b * h],
            target: vec![0.0; b * h * a],
            mask: vec![0.0; b * h],
            gt: vec![0.0; b * h * a],
            epsb: vec![0.0; b * h * a],
            fast: vec![0.0; b * spec.n_obs * spec.fast_dim],
            slow: vec![0.0; b * spec.slow.len()],
            dvis: vec![0; b],
        }
    }

    fn fill<D: Dataset + ?Sized>(&mut self, data: &D) -> Result<()> {
        let Spec {
            horizon: h,
            action_dim: a,
            n_obs,
            fast_dim: f,
            d_vis_max,
            ..
        } = self.spec;
        let sl = self.spec.slow.len();
        let total = *self.cum.last().unwrap_or(&0) as u64;
        for i in 0..self.b {
            let k = self.rng.below(total) as usize;
            let e = self.cum.partition_point(|&c| c <= k);
            let t = k - if e == 0 { 0 } else { self.cum[e - 1] };
            let len = data.episode_len(e);
            for j in 0..n_obs {
                let tt = (t + j + 1).saturating_sub(n_obs);
                self.fast[(i * n_obs + j) * f..(i * n_obs + j + 1) * f]
                    .copy_from_slice(data.fast(e, tt));
            }
            let dv = self.rng.below(d_vis_max as u64 + 1) as usize;
            self.dvis[i] = dv as u32;
            if sl > 0 {
                self.slow[i * sl..(i + 1) * sl].copy_from_slice(data.slow(e, t.saturating_sub(dv)));
            }
            for p in 0..h {
                self.act[p * a..(p + 1) * a].copy_from_slice(data.action(e, (t + p).min(len - 1)));
            }
            self.stats.normalize_action(&mut self.act);
            self.rng.fill_normal(&mut self.eps);
            self.schedule.draw(&mut self.rng, &mut self.draw)?;
            let r = i * h * a..(i + 1) * h * a;
            self.draw.build(
                &self.act,
                &self.eps,
                a,
                &mut self.x[r.clone()],
                &mut self.tau[i * h..(i + 1) * h],
                &mut self.target[r.clone()],
            )?;
            self.mask[i * h..(i + 1) * h].copy_from_slice(&self.draw.mask);
            self.gt[r.clone()].copy_from_slice(&self.act);
            self.epsb[r].copy_from_slice(&self.eps);
        }
        Ok(())
    }

    fn input(&self) -> ModelInput<'_> {
        let slow = match self.spec.slow {
            SlowSpec::None => SlowInput::None,
            SlowSpec::Vector { dim } => SlowInput::Vector {
                data: &self.slow,
                dim,
            },
            SlowSpec::Tokens { tokens, dim } => SlowInput::Tokens {
                data: &self.slow,
                tokens,
                dim,
            },
        };
        ModelInput {
            batch: self.b,
            horizon: self.spec.horizon,
            action_dim: self.spec.action_dim,
            x: &self.x,
            tau: &self.tau,
            obs_fast: &self.fast,
            n_obs: self.spec.n_obs,
            fast_dim: self.spec.fast_dim,
            slow,
            d_vis: &self.dvis,
        }
    }

    /// Replace a fraction of the samples by states the model reached itself (see [`SelfRollout`]).
    fn self_roll(&mut self, model: &mut CandleModel, r: SelfRollout) -> Result<()> {
        let (h, a) = (self.spec.horizon, self.spec.action_dim);
        let rows: Vec<bool> = (0..self.b).map(|_| self.rng.uniform() < r.prob).collect();
        if !rows.iter().any(|&s| s) {
            return Ok(());
        }
        // Start states: one step earlier on the noised ground truth (front and τ > 0.95 unchanged).
        let (x_final, tau_final) = (self.x.clone(), self.tau.clone());
        let mut tau_start = self.tau.clone();
        for (i, &row) in rows.iter().enumerate() {
            for p in 0..h {
                let q = i * h + p;
                let t = self.tau[q];
                if !row || self.mask[q] == 0.0 || !(0.0..=0.95).contains(&t) {
                    continue;
                }
                let ts = (t - r.step).max(0.0);
                tau_start[q] = ts;
                for j in q * a..(q + 1) * a {
                    self.x[j] = (1.0 - ts) * self.epsb[j] + ts * self.gt[j];
                }
            }
        }
        self.tau.copy_from_slice(&tau_start);
        let v = {
            let input = self.input();
            let mut v = vec![0.0f32; self.b * h * a];
            model.velocity_into(&input, &mut v)?;
            v
        };
        self.tau.copy_from_slice(&tau_final);
        for i in 0..self.b {
            for p in 0..h {
                let q = i * h + p;
                let (t, ts) = (tau_final[q], tau_start[q]);
                let r = q * a..(q + 1) * a;
                if ts == t {
                    self.x[r.clone()].copy_from_slice(&x_final[r]);
                    continue;
                }
                for ((x, tg), (&g, &vj)) in self.x[r.clone()]
                    .iter_mut()
                    .zip(&mut self.target[r.clone()])
                    .zip(self.gt[r.clone()].iter().zip(&v[r]))
                {
                    *x += (t - ts) * vj;
                    *tg = (g - *x) / (1.0 - t);
                }
            }
        }
        Ok(())
    }
}
