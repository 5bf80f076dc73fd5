//! What a training run does around its steps, whatever it trains: the output directory
//! (refusing earlier checkpoints unless resuming), the loss log, stopping (`stop_after`,
//! `stop_on` and the `interrupted-*` state), the book-keeping after a step (loss history,
//! log line, progress hook), the loss and gradient of the candle autograd path, and the end
//! of the run. [`Trainer`] and the crate's other trainers build their steps on these.

use std::fs::File;
use std::io::BufWriter;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use candle_core::Var;

use super::*;

/// The run controls of a trainer's builder (set by the methods of [`run_controls!`]).
#[derive(Default)]
pub(crate) struct RunControl<'a> {
    pub(crate) resume: bool,
    pub(crate) stop_after: Option<usize>,
    pub(crate) stop: Option<Arc<AtomicBool>>,
    pub(crate) progress: Option<ProgressFn<'a>>,
}

/// The builder methods of [`RunControl`], for a builder with a field `ctl: RunControl`.
macro_rules! run_controls {
    () => {
        /// Continue from the last step checkpoint in the output directory (default off).
        ///
        /// Every step checkpoint carries the full training state
        /// ([`TRAIN_STATE_FILE`](crate::train::TRAIN_STATE_FILE),
        /// [`TRAIN_TENSORS_FILE`](crate::train::TRAIN_TENSORS_FILE): raw weights, AdamW
        /// moments and step count, EMA, the best pick so far, the batch generator's random
        /// state, the loss history), so a resumed run continues **bit-identically** to an
        /// uninterrupted one with the same configuration, data and thread count on the same
        /// kind of CPU. The matrix kernels are chosen at run time by instruction set (AVX2 or
        /// AVX-512, say), so on another kind of CPU a resumed run continues correctly but is
        /// not promised to continue bit for bit (measured: an AVX2 AMD EPYC and an AVX-512
        /// Intel Xeon gave the same bits for the study's U-Net). The model's own weights are
        /// replaced by the checkpoint's. With no step checkpoint in the directory the run
        /// starts from scratch; a checkpoint written with a different
        /// [`TrainConfig`](crate::train::TrainConfig) or model is an error naming the
        /// difference. Steps after the checkpoint that an interrupted run had logged appear
        /// twice in `loss.jsonl`.
        pub fn resume(mut self, on: bool) -> Self {
            self.ctl.resume = on;
            self
        }
        /// Return once `steps` steps are done (counted from step 0, not from a resume point),
        /// as if the run had been interrupted there: no extra validation or checkpoint is
        /// made, the model holds the raw weights of that step, and a later run with `resume`
        /// continues from the last step checkpoint written. For time-sliced training and tests.
        pub fn stop_after(mut self, steps: usize) -> Self {
            self.ctl.stop_after = Some(steps);
            self
        }
        /// Stop at the next step once `flag` is set (e.g. by Ctrl-C): with an output directory
        /// the full training state is written first as `interrupted-NNNNNN/` (unless a step
        /// checkpoint of that step exists), then the run returns
        /// [`Error::Interrupted`](crate::Error::Interrupted). A run with `resume` continues
        /// from the latest of the step checkpoints and that state, bit-identically;
        /// `interrupted-*` directories are removed when the run finishes. They are not step
        /// checkpoints: nothing picks or evaluates them.
        pub fn stop_on(mut self, flag: std::sync::Arc<std::sync::atomic::AtomicBool>) -> Self {
            self.ctl.stop = Some(flag);
            self
        }
        /// Called after every step.
        pub fn on_progress(mut self, f: impl FnMut(&crate::train::Progress) + 'a) -> Self {
            self.ctl.progress = Some(Box::new(f));
            self
        }
    };
}
pub(crate) use run_controls;

/// The step checkpoint directory of step `step` in `out`.
pub(crate) fn step_dir(out: &Path, step: usize) -> PathBuf {
    out.join(format!("step-{step:06}"))
}

impl RunControl<'_> {
    /// Where a run writing to `out` starts: with `resume`, the checkpoint to continue from;
    /// without, an error if `out` already holds checkpoints (now, not after hours of
    /// training). Creates `out`.
    pub(crate) fn prepare(&self, out: &Path) -> Result<Option<PathBuf>> {
        let resume_from = if self.resume {
            latest_step_checkpoint(out)?
        } else {
            if let Ok(rd) = std::fs::read_dir(out) {
                for e in rd.flatten() {
                    let name = e.file_name().to_string_lossy().into_owned();
                    if name.starts_with("step-") || name.starts_with(INTERRUPTED_PREFIX) {
                        return Err(Error::CheckpointExists(e.path()));
                    }
                }
            }
            None
        };
        std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
        Ok(resume_from)
    }

    /// Whether the run ends before `step`: `Ok(true)` once `stop_after` steps are done,
    /// [`Error::Interrupted`] once the stop flag is set. With an output directory and a step
    /// done, the log is flushed and `save` writes the training state into
    /// `interrupted-NNNNNN/` first, unless the step checkpoint of `step` exists.
    pub(crate) fn stop_before(
        &self,
        step: usize,
        out: Option<&Path>,
        log: &mut LossLog<'_>,
        save: impl FnOnce(&Path) -> Result<()>,
    ) -> Result<bool> {
        if self.stop_after.is_some_and(|s| step >= s) {
            return Ok(true);
        }
        if !self.stop.as_ref().is_some_and(|f| f.load(Ordering::SeqCst)) {
            return Ok(false);
        }
        let mut resume_point = None;
        if let (Some(d), true) = (out, step > 0) {
            log.flush()?;
            let regular = step_dir(d, step);
            if regular.join(TRAIN_STATE_FILE).is_file() {
                resume_point = Some(regular);
            } else {
                let p = d.join(format!("{INTERRUPTED_PREFIX}{step:06}"));
                if !p.exists() {
                    save(&p)?;
                }
                resume_point = Some(p);
            }
        }
        Err(Error::Interrupted { step, resume_point })
    }

    /// The book-keeping after the step `p.step` (1-based): its loss in the report, a log line
    /// every `log_every` steps and at the last, the progress hook. Returns whether the step
    /// is a checkpoint step (every `checkpoint_every`, and the last).
    pub(crate) fn after_step(
        &mut self,
        cfg: &TrainConfig,
        st: &mut State,
        log: &mut LossLog<'_>,
        p: Progress,
    ) -> Result<bool> {
        let done = p.step;
        st.step = done;
        st.report.losses.push((done, p.loss));
        if done % cfg.log_every.max(1) == 0 || done == cfg.steps {
            let (loss, lr, gn) = (p.loss, p.lr, p.grad_norm);
            log.line(&format!(
                r#"{{"step":{done},"loss":{loss},"lr":{lr},"grad_norm":{gn}}}"#
            ))?;
        }
        if let Some(f) = self.progress.as_mut() {
            f(&p);
        }
        Ok(cfg.checkpoint_every.is_some_and(|k| k > 0 && done % k == 0) || done == cfg.steps)
    }
}

/// The end of a run: the log flushed and, once every step is done, the `interrupted-*`
/// states in `out` removed.
pub(crate) fn finish(
    out: Option<&Path>,
    log: &mut LossLog<'_>,
    st: State,
    cfg: &TrainConfig,
) -> Result<TrainReport> {
    log.flush()?;
    if let (Some(d), true) = (out, st.step >= cfg.steps) {
        remove_interrupted(d)?;
    }
    Ok(st.report)
}

/// The JSON-lines loss log: `loss.jsonl` in the output directory (appended to, so a resumed
/// run continues it) and a caller's writer.
pub(crate) struct LossLog<'a> {
    file: Option<(BufWriter<File>, PathBuf)>,
    extra: Option<Box<dyn Write + 'a>>,
}

impl<'a> LossLog<'a> {
    /// Open `out/loss.jsonl` (with an output directory) for appending.
    pub(crate) fn open(out: Option<&Path>, extra: Option<Box<dyn Write + 'a>>) -> Result<Self> {
        let file = match out {
            Some(d) => {
                let p = d.join("loss.jsonl");
                let f = std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(&p)
                    .map_err(|e| Error::io(&p, e))?;
                Some((BufWriter::new(f), p))
            }
            None => None,
        };
        Ok(Self { file, extra })
    }

    /// Write `line` to the file and the caller's writer.
    pub(crate) fn line(&mut self, line: &str) -> Result<()> {
        if let Some((w, p)) = self.file.as_mut() {
            writeln!(w, "{line}").map_err(|e| Error::io(&*p, e))?;
        }
        if let Some(w) = self.extra.as_mut() {
            writeln!(w, "{line}").map_err(|e| Error::io("loss log", e))?;
        }
        Ok(())
    }

    /// Flush the file (a resumed run appends after what is on disk).
    pub(crate) fn flush(&mut self) -> Result<()> {
        if let Some((w, p)) = self.file.as_mut() {
            w.flush().map_err(|e| Error::io(&*p, e))?;
        }
        Ok(())
    }
}

/// The trainer's loss of `v [B,H,A]`: `Σ_p mask_p·|v_p − target_p|² / (A·Σ_p mask_p)`, with
/// `target [B·H·A]` and `mask [B·H]` on `v`'s device.
pub(crate) fn masked_mse(v: Tensor, target: &[f32], mask: &[f32]) -> Result<Tensor> {
    let (b, h, a) = v.dims3()?;
    let dev = v.device().clone();
    let target = Tensor::from_slice(target, (b, h, a), &dev)?;
    let mask_t = Tensor::from_slice(mask, (b, h, 1), &dev)?;
    let msum: f32 = mask.iter().sum();
    let err = (v - target)?.sqr()?.broadcast_mul(&mask_t)?;
    Ok((err.sum_all()? / (msum.max(1.0) as f64 * a as f64))?)
}

/// Back-propagate `loss`, clip the gradients of `vars` in candle ([`clip_grad_store`]) and
/// copy them to the host `grads` (zeros for a variable without one). Returns the global
/// norm before clipping.
pub(crate) fn backward_to_host(
    loss: &Tensor,
    vars: &[Var],
    clip: Option<f64>,
    grads: &mut [Vec<f32>],
) -> Result<f32> {
    let mut gs = loss.backward()?;
    let gn = clip_grad_store(&mut gs, vars, clip)?;
    for (g, v) in grads.iter_mut().zip(vars) {
        match gs.get(v.as_tensor()) {
            Some(t) => g.copy_from_slice(&t.flatten_all()?.to_vec1::<f32>()?),
            None => g.fill(0.0),
        }
    }
    Ok(gn)
}
