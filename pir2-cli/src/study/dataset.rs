//! The dataset task: train a policy on a user's own state-only LeRobotDataset v3.0, validated
//! without an environment (`pir2 train --data DATASET --task task.toml --out DIR`).
//!
//! A `task.toml` ([`DatasetTaskConfig`]) names the features (fast keys concatenated in
//! order, optional slow keys, the action key), the chunk horizon `H` and history `n_obs`, the
//! policy (its training schedule and deployment sampler come from [`Policy`]), the model, the
//! optimiser, the held-out episodes and the checkpoint count. Unknown fields anywhere in the
//! file are an error naming the field.
//!
//! Every checkpoint is scored on the held-out episodes, which are never trained on: the
//! flow-matching loss under the policy's training schedule (fixed draws, so checkpoints are
//! compared on identical samples) and the open-loop action error of the chunk the policy's
//! deployment sampler produces ([`super::open_loop`]). The checkpoint with the lowest
//! open-loop error in normalised units is kept: it measures the actions the deployed head
//! would send, which the loss on random schedule draws does not rank reliably (a few-NFE
//! sampler can get worse while the per-draw loss still falls).
//!
//! This task has no environment, so it does not implement [`super::Task`] (whose validation
//! and evaluation are closed-loop); it shares the trainer, the checkpoint layout and
//! `pir2 export` with the tasks that do. Output directory:
//!
//! ```text
//! DIR/task.toml         the task as read (checked again by --resume)
//! DIR/step-NNNNNN/      step checkpoints with the training state (--resume continues there)
//! DIR/loss.jsonl        training loss and validation score per checkpoint
//! DIR/best.json         the chosen step
//! DIR/validation.json   held-out episodes and every checkpoint's scores
//! DIR/best/             the chosen checkpoint (`pir2 export DIR/best --onnx model.onnx`)
//! ```

use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, MlpConfig, ModelConfig, SlowSpec, Spec};
use pir2_backends::train::{compute_stats, held_out_loss, Progress, TrainConfig, Trainer};
use pir2_runtime::{HeadSpec, Policy, Recipe};
use pir2_schedule::Rng;
use pir2_sim::dataset::{read_selected, Episode, FeatureSelection};

use super::open_loop::{open_loop_error, OpenLoop, OpenLoopError};
use super::pipeline::{log_line, output_map, prepare_out, write_atomically, Episodes};

/// A `task.toml`: which features to train on and how.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetTaskConfig {
    /// Fast observation: these float features concatenated in order.
    pub fast_keys: Vec<String>,
    /// Slow observation: these float features concatenated in order (default: none). Fed as
    /// the model's slow vector, `d_vis_max` ticks old at most in training.
    #[serde(default)]
    pub slow_keys: Vec<String>,
    /// The action feature (default `action`).
    #[serde(default = "default_action_key")]
    pub action_key: String,
    /// Chunk length `H`.
    pub horizon: usize,
    /// Fast observation history length (default 1).
    #[serde(default = "one")]
    pub n_obs: usize,
    /// Largest slow-feature age (in frames) drawn in training (default 0).
    #[serde(default)]
    pub d_vis_max: usize,
    /// The policy: `pi_r2`, `pi_r2_hidden`, `pi_r2_full`, `rtc`, `flow`, `pi_r2_zero_delay`.
    pub policy: Policy,
    /// The policy's knobs: `nfe`, `flow_steps`, `pir2_d_max`, `rtc_d_max`, `delays`, `jitter`, ...
    #[serde(default)]
    pub recipe: Recipe,
    /// The architecture (default: an MLP, width 256, depth 3).
    #[serde(default = "default_model")]
    pub model: ModelConfig,
    /// Optimiser settings.
    #[serde(default)]
    pub train: Optimiser,
    /// Held-out episodes and checkpoint validation.
    #[serde(default)]
    pub validation: Validation,
    /// Seed of everything random (initial weights, batches, held-out split, validation draws).
    #[serde(default)]
    pub seed: u64,
}

fn default_action_key() -> String {
    "action".into()
}
fn one() -> usize {
    1
}
fn default_model() -> ModelConfig {
    ModelConfig::Mlp(MlpConfig::default())
}

/// Optimiser settings of a dataset task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Optimiser {
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
    /// Decoupled weight decay.
    pub weight_decay: f64,
    /// Global grad-norm clip (absent: none).
    pub grad_clip: Option<f64>,
    /// EMA decay of the evaluated weights (absent: raw weights).
    pub ema: Option<f64>,
}

impl Default for Optimiser {
    fn default() -> Self {
        Self {
            steps: 2000,
            batch_size: 128,
            lr: 1e-3,
            min_lr: 0.0,
            warmup: 100,
            weight_decay: 1e-6,
            grad_clip: Some(1.0),
            ema: None,
        }
    }
}

/// Held-out episodes and checkpoint validation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Validation {
    /// Fraction of the episodes held out (at least one), chosen by the seed.
    pub held_out: f64,
    /// Held-out episodes by position in `episode_index` order (overrides `held_out`).
    pub held_out_episodes: Vec<usize>,
    /// Checkpoints validated (evenly spaced, the last at the end).
    pub checkpoints: usize,
    /// Windows (start frames) of the open-loop action error per checkpoint.
    pub windows: usize,
    /// Batches of the held-out flow loss per checkpoint (of the optimiser's batch size).
    pub loss_batches: usize,
    /// Delay `d` of the sampler (πR² warm start, RTC front).
    pub delay: usize,
}

impl Default for Validation {
    fn default() -> Self {
        Self {
            held_out: 0.2,
            held_out_episodes: Vec::new(),
            checkpoints: 4,
            windows: 64,
            loss_batches: 4,
            delay: 1,
        }
    }
}

impl DatasetTaskConfig {
    /// Parse a task file's text. Unknown fields, also in nested tables (`[model]`,
    /// `[recipe]`), are an error naming the field.
    pub fn from_toml(text: &str) -> Result<Self> {
        let cfg: Self = toml::from_str(text)?;
        let given: toml::Value = toml::from_str(text)?;
        let known = toml::Value::try_from(&cfg).context("serialising the task")?;
        if let Some(field) = unknown_field(&given, &known, "") {
            bail!("unknown field `{field}`");
        }
        cfg.check()?;
        Ok(cfg)
    }

    /// Read a task file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading task file {}", path.display()))?;
        Self::from_toml(&text).with_context(|| format!("task file {}", path.display()))
    }

    fn check(&self) -> Result<()> {
        ensure!(self.horizon >= 1, "`horizon` must be at least 1");
        ensure!(self.n_obs >= 1, "`n_obs` must be at least 1");
        ensure!(
            !self.fast_keys.is_empty(),
            "`fast_keys` must name at least one feature"
        );
        let v = &self.validation;
        ensure!(
            v.checkpoints >= 1,
            "`validation.checkpoints` must be at least 1"
        );
        ensure!(v.windows >= 1, "`validation.windows` must be at least 1");
        ensure!(
            !v.held_out_episodes.is_empty() || (v.held_out > 0.0 && v.held_out < 1.0),
            "`validation.held_out` must be in (0, 1) (or list `validation.held_out_episodes`): \
             validation needs held-out episodes"
        );
        self.policy
            .schedule(&self.recipe)
            .validate(self.horizon)
            .with_context(|| {
                format!(
                    "`horizon` = {} does not fit policy {:?} with recipe.pir2_d_max = {} and \
                     recipe.rtc_d_max = {}",
                    self.horizon, self.policy, self.recipe.pir2_d_max, self.recipe.rtc_d_max
                )
            })?;
        if self.policy.deployments(&self.recipe).is_empty() {
            bail!("policy {:?} has no deployment mode", self.policy);
        }
        Ok(())
    }

    /// The features to read.
    pub fn selection(&self) -> FeatureSelection {
        FeatureSelection {
            fast: self.fast_keys.clone(),
            slow: self.slow_keys.clone(),
            action: self.action_key.clone(),
        }
    }
}

/// The first key of `given` (dotted path) that `known` (the parsed config written back) lacks.
fn unknown_field(given: &toml::Value, known: &toml::Value, prefix: &str) -> Option<String> {
    let (toml::Value::Table(g), toml::Value::Table(k)) = (given, known) else {
        return None;
    };
    for (key, gv) in g {
        let path = if prefix.is_empty() {
            key.clone()
        } else {
            format!("{prefix}.{key}")
        };
        match k.get(key) {
            None => return Some(path),
            Some(kv) => {
                if let Some(f) = unknown_field(gv, kv, &path) {
                    return Some(f);
                }
            }
        }
    }
    None
}

/// One validated checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointScore {
    /// Optimiser step.
    pub step: usize,
    /// Held-out flow-matching loss under the training schedule.
    pub flow_loss: f64,
    /// Held-out open-loop action error of the deployment sampler.
    pub open_loop: OpenLoopError,
}

/// `validation.json`: what was held out and how every checkpoint scored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ValidationReport {
    /// The metric that picks the checkpoint (lower is better).
    pub metric: String,
    /// Held-out episodes (positions in `episode_index` order).
    pub held_out: Vec<usize>,
    /// Episodes trained on.
    pub train_episodes: usize,
    /// Every validated checkpoint, by step.
    pub checkpoints: Vec<CheckpointScore>,
    /// The chosen step.
    pub best_step: Option<usize>,
}

/// The metric named in `validation.json`.
pub const METRIC: &str = "open_loop.nrmse";

/// Split `n` episodes into (train, held-out) positions.
pub fn split(n: usize, v: &Validation, seed: u64) -> Result<(Vec<usize>, Vec<usize>)> {
    let mut held: Vec<usize> = if v.held_out_episodes.is_empty() {
        let k = ((n as f64 * v.held_out).round() as usize).max(1);
        let mut order: Vec<usize> = (0..n).collect();
        let mut rng = Rng::derive(seed, 0x5E1D);
        for i in (1..n).rev() {
            order.swap(i, rng.below(i as u64 + 1) as usize);
        }
        order.truncate(k);
        order
    } else {
        v.held_out_episodes.clone()
    };
    held.sort_unstable();
    held.dedup();
    if let Some(&e) = held.iter().find(|&&e| e >= n) {
        bail!("held-out episode {e} does not exist: the dataset has {n} episodes");
    }
    let train: Vec<usize> = (0..n).filter(|e| held.binary_search(e).is_err()).collect();
    ensure!(
        !train.is_empty(),
        "no episode left to train on: {} of {n} episodes are held out",
        held.len()
    );
    Ok((train, held))
}

/// The model's spec for the dataset's widths.
pub fn spec(cfg: &DatasetTaskConfig, ep: &Episode) -> Spec {
    Spec {
        horizon: cfg.horizon,
        action_dim: ep.action_dim,
        n_obs: cfg.n_obs,
        fast_dim: ep.fast_dim,
        slow: match ep.slow_dim {
            0 => SlowSpec::None,
            dim => SlowSpec::Vector { dim },
        },
        d_vis_max: if ep.slow_dim == 0 { 0 } else { cfg.d_vis_max },
    }
}

/// Every value the task reads must be finite: a NaN or an infinity would make the statistics,
/// the training loss or the validation metric non-finite far from its cause. The first one is
/// one error naming the episode (by position), the frame and the key.
fn check_finite(episodes: &[pir2_sim::dataset::Episode], cfg: &DatasetTaskConfig) -> Result<()> {
    for (e, ep) in episodes.iter().enumerate() {
        let parts: [(&[f32], usize, String); 3] = [
            (&ep.fast, ep.fast_dim, cfg.fast_keys.join(" + ")),
            (&ep.slow, ep.slow_dim, cfg.slow_keys.join(" + ")),
            (&ep.action, ep.action_dim, cfg.action_key.clone()),
        ];
        for (values, dim, key) in parts {
            if let Some(i) = values.iter().position(|v| !v.is_finite()) {
                bail!(
                    "episode {e} (by position), frame {}: {key}[{}] is {}; the dataset must \
                     hold finite values only",
                    i / dim.max(1),
                    i % dim.max(1),
                    values[i]
                );
            }
        }
    }
    Ok(())
}

/// Train `cfg` on the dataset at `data` into `out` (a new directory, or with `resume` the
/// directory of an interrupted run with the same task file); returns the validation report.
pub fn train(
    data: &Path,
    cfg: &DatasetTaskConfig,
    out: &Path,
    resume: bool,
) -> Result<ValidationReport> {
    // The dataset and the split first: a bad key leaves no output directory behind.
    let ds = read_selected(data, &cfg.selection())
        .with_context(|| format!("reading dataset {}", data.display()))?;
    let n = ds.episodes.len();
    check_finite(&ds.episodes, cfg)
        .with_context(|| format!("reading dataset {}", data.display()))?;
    let (train_idx, held_idx) = split(n, &cfg.validation, cfg.seed)?;
    let task_file = out.join("task.toml");
    let text = toml::to_string(cfg).context("serialising the task")?;
    if resume {
        let before = std::fs::read_to_string(&task_file).with_context(|| {
            format!(
                "--resume: {} holds no task.toml of an earlier run",
                out.display()
            )
        })?;
        let same = DatasetTaskConfig::from_toml(&before).is_ok_and(|b| &b == cfg);
        ensure!(
            same,
            "--resume: the task differs from the one {} was trained with ({})",
            out.display(),
            task_file.display()
        );
        if out.join("best").exists() {
            log_line(&format!("{} finished in an earlier run", out.display()));
            return read_report(out);
        }
    } else {
        prepare_out(out)?;
        write_atomically(&task_file, text.as_bytes())?;
    }
    let pick = |idx: &[usize]| {
        idx.iter()
            .map(|&i| ds.episodes[i].clone())
            .collect::<Vec<_>>()
    };
    let (train_eps, held_eps) = (pick(&train_idx), pick(&held_idx));
    let spec = spec(cfg, &ds.episodes[0]);
    let stats = compute_stats(&Episodes(&train_eps), &spec)?;
    let mut model = CandleModel::new(
        Config {
            spec,
            model: cfg.model.clone(),
        },
        stats,
        cfg.seed,
    )?;
    // Recorded in every checkpoint's identity.json: evaluating it as another policy is refused.
    model.set_policy(Some(cfg.policy));
    let schedule = cfg.policy.schedule(&cfg.recipe);
    let o = &cfg.train;
    let v = &cfg.validation;
    let tc = TrainConfig {
        steps: o.steps,
        batch_size: o.batch_size,
        lr: o.lr,
        min_lr: o.min_lr,
        warmup: o.warmup,
        weight_decay: o.weight_decay,
        grad_clip: o.grad_clip,
        ema: o.ema,
        seed: cfg.seed,
        schedule,
        checkpoint_every: Some((o.steps / v.checkpoints).max(1)),
        ..TrainConfig::default()
    };
    let mode = cfg.policy.deployments(&cfg.recipe)[0].mode;
    let head = HeadSpec {
        horizon: spec.horizon,
        action_dim: spec.action_dim,
        n_obs: spec.n_obs,
        fast_dim: spec.fast_dim,
        slow_dim: spec.slow.len(),
        period: (1e9 / ds.fps).round().max(1.0) as u64,
        d_max: cfg.policy.d_max(&cfg.recipe),
        d_vis_max: spec.d_vis_max,
    };
    let mut report = ValidationReport {
        metric: METRIC.into(),
        held_out: held_idx.clone(),
        train_episodes: train_idx.len(),
        checkpoints: if resume {
            read_report(out).map(|r| r.checkpoints).unwrap_or_default()
        } else {
            Vec::new()
        },
        best_step: None,
    };
    log_line(&format!(
        "training {:?} on {} episodes ({} held out) of {}: fast {}, slow {}, action {}",
        cfg.policy,
        train_idx.len(),
        held_idx.len(),
        data.display(),
        spec.fast_dim,
        spec.slow.len(),
        spec.action_dim
    ));
    let report_path = out.join("validation.json");
    let mut failure: Option<anyhow::Error> = None;
    let trained = {
        let on_progress = |p: &Progress| {
            if p.step % 100 == 0 || p.step == p.steps {
                log_line(&format!(
                    "  step {}/{}, loss {:.4}",
                    p.step, p.steps, p.loss
                ));
            }
        };
        let validate = |m: &mut CandleModel, step: usize| -> f64 {
            let ol = OpenLoop {
                spec: head,
                mode,
                delay: v.delay,
                output: output_map(m),
                windows: v.windows,
                seed: cfg.seed ^ 0x0033_0009,
            };
            let scored = score(
                m,
                step,
                &held_eps,
                &ol,
                schedule,
                o.batch_size,
                v.loss_batches,
            )
            .map_err(|e| e.context(format!("validating step {step}")));
            match scored {
                Ok(s) => {
                    log_line(&format!(
                        "  checkpoint {step}: held-out flow loss {:.4}, open-loop RMSE {:.4} \
                         (normalised {:.4})",
                        s.flow_loss, s.open_loop.rmse, s.open_loop.nrmse
                    ));
                    let score = -s.open_loop.nrmse;
                    if !(s.flow_loss.is_finite() && s.open_loop.nrmse.is_finite()) {
                        // A non-finite metric is a diverged model or non-finite held-out
                        // data, never a score (before: it was logged and the command exited 0).
                        failure.get_or_insert(anyhow::anyhow!(
                            "validating step {step}: the held-out flow loss ({}) or open-loop \
                             RMSE ({}) is not finite: the model diverged or the held-out \
                             episodes hold non-finite values",
                            s.flow_loss,
                            s.open_loop.nrmse
                        ));
                    }
                    report.checkpoints.retain(|c| c.step < step);
                    report.checkpoints.push(s);
                    if let Err(e) = write_report(&report_path, &report) {
                        failure.get_or_insert(e);
                    }
                    if score.is_finite() {
                        score
                    } else {
                        f64::NEG_INFINITY
                    }
                }
                Err(e) => {
                    failure.get_or_insert(e);
                    f64::NEG_INFINITY
                }
            }
        };
        // Ctrl-C / SIGTERM: the training state of the step reached is saved
        // (`interrupted-NNNNNN/`, unless a step checkpoint of that step exists) and the run
        // ends with an error naming it; `--resume` continues from there.
        Trainer::new(tc)
            .stop_on(crate::signals::stop_flag())
            .on_progress(on_progress)
            .validate(validate)
            .out_dir(out)
            .resume(resume)
            .run(&mut model, &Episodes(&train_eps))
    };
    if let Some(e) = failure {
        return Err(e);
    }
    let trained = trained?;
    report.best_step = trained.best.map(|b| b.step);
    write_report(&report_path, &report)?;
    model.save(&out.join("best"))?;
    Ok(report)
}

/// Both held-out scores of the model at `step` (the flow loss with fixed draws seeded from
/// the open-loop seed).
fn score(
    m: &mut CandleModel,
    step: usize,
    held: &[Episode],
    ol: &OpenLoop,
    schedule: pir2_schedule::train::TrainSchedule,
    batch_size: usize,
    batches: usize,
) -> Result<CheckpointScore> {
    let flow_loss = held_out_loss(
        m,
        &Episodes(held),
        schedule,
        batch_size,
        batches,
        ol.seed ^ 0x00C2_005C, // = the task seed ^ 0x00F1_0055
    )?;
    let open_loop = open_loop_error(m, held, ol)?;
    Ok(CheckpointScore {
        step,
        flow_loss,
        open_loop,
    })
}

fn write_report(path: &Path, r: &ValidationReport) -> Result<()> {
    write_atomically(path, serde_json::to_string_pretty(r)?.as_bytes())
}

/// `validation.json` of a training run.
pub fn read_report(out: &Path) -> Result<ValidationReport> {
    let p = out.join("validation.json");
    let text = std::fs::read_to_string(&p).with_context(|| format!("reading {}", p.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", p.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = r#"
fast_keys = ["observation.state"]
horizon = 16
policy = "pi_r2"
"#;

    #[test]
    fn a_minimal_task_takes_the_defaults() {
        let c = DatasetTaskConfig::from_toml(MINIMAL).unwrap();
        assert_eq!(c.action_key, "action");
        assert_eq!((c.n_obs, c.d_vis_max, c.seed), (1, 0, 0));
        assert_eq!(c.model, default_model());
        assert_eq!(c.train, Optimiser::default());
        assert_eq!(c.validation, Validation::default());
        assert_eq!(c.recipe, Recipe::default());
    }

    #[test]
    fn unknown_fields_are_named_at_every_level() {
        for (extra, field) in [
            ("horizn = 3", "horizn"),
            ("[train]\nstep = 3", "step"),
            ("[model]\nkind = \"mlp\"\nwidht = 3", "model.widht"),
            ("[recipe]\nnfee = 3", "recipe.nfee"),
            ("[validation]\nheld = 0.1", "held"),
        ] {
            let err = DatasetTaskConfig::from_toml(&format!("{MINIMAL}{extra}\n")).unwrap_err();
            let msg = format!("{err:#}");
            assert!(msg.contains(field), "{extra}: {msg}");
        }
    }

    #[test]
    fn the_split_is_seeded_and_keeps_training_episodes() {
        let v = Validation::default();
        let (t, h) = split(10, &v, 3).unwrap();
        assert_eq!((t.len(), h.len()), (8, 2));
        assert_eq!(split(10, &v, 3).unwrap(), (t.clone(), h.clone()));
        assert_ne!(
            split(10, &v, 4).unwrap().1,
            h,
            "another seed, another split"
        );
        let listed = Validation {
            held_out_episodes: vec![4, 1],
            ..v.clone()
        };
        assert_eq!(split(5, &listed, 0).unwrap().1, [1, 4]);
        assert!(split(
            3,
            &Validation {
                held_out_episodes: vec![3],
                ..v.clone()
            },
            0
        )
        .is_err());
        assert!(split(1, &v, 0).is_err(), "one episode cannot be both");
    }
}
