//! `pir2 demo`: the embedded default end to end — collect demonstrations on the
//! ball-on-plate task, train πR² and the baselines (candle MLPs), evaluate every deployment
//! mode under latency through the lock-step runtime, print a table, write JSON and a PNG.
//!
//! Every stage is also a function of its own (`collect`, `train_policy`, `evaluate`), and
//! the CLI's `collect` / `train` / `eval` / `plot` subcommands call them with TOML configs.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use serde::{Deserialize, Serialize};

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, MlpConfig, ModelConfig, SlowSpec, Spec};
use pir2_backends::train::{compute_stats, Dataset, TrainConfig};
use pir2_runtime::{HeadSpec, LockstepTiming, Mode, OutputMap};
use pir2_schedule::train::{DelayDist, FrontVisibility, PiR2Draws, TrainSchedule};
use pir2_schedule::{Alignment, FrontMode};
use pir2_sim::ballplate::{BallPlate, BallPlateConfig};
use pir2_sim::dataset::{CollectConfig, DatasetSpec, DatasetWriter, Episode, WriteMode};
use pir2_sim::expert::{LqrConfig, LqrExpert};

use crate::pipeline::{bar, evaluate_rows, prepare_out, train_jobs, train_validated};
use crate::plot::plot_series;
use crate::study::{eval_cell, table, to_series, Cell};

/// Everything `pir2 demo` does, as a TOML-able config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DemoConfig {
    /// Demonstrations to collect.
    pub demos: usize,
    /// Optimiser steps per policy.
    pub train_steps: usize,
    /// Batch size.
    pub batch_size: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Checkpoints validated in closed loop per policy (evenly spaced, the last at the end).
    pub checkpoints: usize,
    /// Closed-loop validation episodes per checkpoint.
    pub val_episodes: usize,
    /// Test episodes per cell.
    pub episodes: usize,
    /// Seeds (each trains its own policies and evaluates on its own episodes).
    pub seeds: Vec<u64>,
    /// Unit delays.
    pub d0s: Vec<usize>,
    /// NFEs per action of the default πR² policy.
    pub nfe: usize,
    /// Euler steps of the flow baselines.
    pub flow_steps: usize,
    /// Worker threads.
    pub threads: usize,
    /// MLP width.
    pub width: usize,
    /// MLP depth.
    pub depth: usize,
}

impl Default for DemoConfig {
    fn default() -> Self {
        Self {
            demos: 200,
            train_steps: 2000,
            batch_size: 128,
            lr: 1e-3,
            checkpoints: 4,
            val_episodes: 20,
            episodes: 100,
            seeds: vec![0, 1, 2],
            d0s: vec![1, 2, 3],
            nfe: 2,
            flow_steps: 10,
            threads: 2,
            width: 128,
            depth: 3,
        }
    }
}

impl DemoConfig {
    /// The `--quick` variant: fewer demos, steps and episodes.
    pub fn quick() -> Self {
        Self {
            demos: 100,
            train_steps: 1000,
            episodes: 30,
            val_episodes: 10,
            checkpoints: 2,
            ..Self::default()
        }
    }
}

/// The policies the demo trains (one of each per seed).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Policy {
    /// πR², default `n`, front visible.
    PiR2,
    /// πR², default `n`, front hidden.
    PiR2Hidden,
    /// πR² with the paper's literal full-chunk ramp.
    PiR2Full,
    /// Train-time RTC.
    Rtc,
    /// Standard flow (sync and naive async).
    Flow,
}

impl Policy {
    /// All policies.
    pub const ALL: [Policy; 5] = [
        Policy::PiR2,
        Policy::PiR2Hidden,
        Policy::PiR2Full,
        Policy::Rtc,
        Policy::Flow,
    ];

    /// Largest delay the policy must handle (trained `d_max`).
    pub fn d_max(self) -> usize {
        match self {
            Policy::Rtc | Policy::Flow => 6,
            _ => 5,
        }
    }

    /// The training schedule (same family and `n` as deployment).
    pub fn schedule(self, nfe: usize) -> TrainSchedule {
        let base = PiR2Draws {
            alpha: 0.2,
            delay: DelayDist::Uniform { max: 5 },
            n: Some(nfe),
            ..Default::default()
        };
        match self {
            Policy::PiR2 => TrainSchedule::PiR2(base),
            Policy::PiR2Hidden => TrainSchedule::PiR2(PiR2Draws {
                front: FrontVisibility::Hidden,
                ..base
            }),
            Policy::PiR2Full => TrainSchedule::PiR2(PiR2Draws {
                n: None,
                alignment: Alignment::Paper,
                ..base
            }),
            Policy::Rtc => TrainSchedule::TrainTimeRtc {
                delay: DelayDist::Uniform { max: 6 },
            },
            Policy::Flow => TrainSchedule::StandardFlow,
        }
    }

    /// The mode used for closed-loop checkpoint validation: the flow policy in naive async
    /// (no ensembling), every other policy in its own row's mode (πR² with async).
    pub fn validation_mode(self, cfg: &DemoConfig) -> Mode {
        let rows = rows(cfg);
        let mine = rows.iter().filter(|r| r.policy == self);
        let pick = match self {
            Policy::Flow => mine
                .clone()
                .find(|r| matches!(r.mode, Mode::NaiveAsync { ensemble: None, .. })),
            _ => mine
                .clone()
                .find(|r| matches!(r.mode, Mode::PiR2Async { .. }) || self == Policy::Rtc),
        };
        pick.or_else(|| mine.clone().next())
            .map(|r| r.mode)
            .expect("every policy has a row")
    }
}

/// One row of the study: a label, the policy and the deployment mode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Row {
    /// Table label.
    pub label: String,
    /// Policy.
    pub policy: Policy,
    /// Deployment mode.
    pub mode: Mode,
}

/// The demo's rows.
pub fn rows(cfg: &DemoConfig) -> Vec<Row> {
    let k = cfg.flow_steps;
    let n = Some(cfg.nfe);
    let (fresh, vis, hid) = (Alignment::Fresh, FrontMode::Visible, FrontMode::Hidden);
    vec![
        Row {
            label: "sync flow".into(),
            policy: Policy::Flow,
            mode: Mode::SyncFlow { steps: k, h: 8 },
        },
        Row {
            label: "naive async".into(),
            policy: Policy::Flow,
            mode: Mode::NaiveAsync {
                steps: k,
                ensemble: None,
            },
        },
        Row {
            label: "naive async + TE".into(),
            policy: Policy::Flow,
            mode: Mode::NaiveAsync {
                steps: k,
                ensemble: Some(0.1),
            },
        },
        Row {
            label: "train-time RTC".into(),
            policy: Policy::Rtc,
            mode: Mode::TrainTimeRtc { steps: k },
        },
        Row {
            label: format!("πR² w/o async (n={})", cfg.nfe),
            policy: Policy::PiR2,
            mode: Mode::PiR2Sync {
                nfe: n,
                alignment: fresh,
                front: vis,
            },
        },
        Row {
            label: format!("πR² async (n={})", cfg.nfe),
            policy: Policy::PiR2,
            mode: Mode::PiR2Async {
                nfe: n,
                alignment: fresh,
                front: vis,
            },
        },
        Row {
            label: format!("πR² async, front hidden (n={})", cfg.nfe),
            policy: Policy::PiR2Hidden,
            mode: Mode::PiR2Async {
                nfe: n,
                alignment: fresh,
                front: hid,
            },
        },
        Row {
            label: "πR² async, paper full ramp".into(),
            policy: Policy::PiR2Full,
            mode: Mode::PiR2Async {
                nfe: None,
                alignment: Alignment::Paper,
                front: vis,
            },
        },
    ]
}

/// The ball-on-plate spec (H = 16, 2 fast frames, 4-d delayed camera tracker).
pub fn spec() -> Spec {
    Spec {
        horizon: 16,
        action_dim: 2,
        n_obs: 2,
        fast_dim: pir2_sim::ballplate::FAST_DIM,
        slow: SlowSpec::Vector {
            dim: pir2_sim::ballplate::SLOW_DIM,
        },
        d_vis_max: 3,
    }
}

fn head_spec(policy: Policy, period: u64) -> HeadSpec {
    let s = spec();
    HeadSpec {
        horizon: s.horizon,
        action_dim: s.action_dim,
        n_obs: s.n_obs,
        fast_dim: s.fast_dim,
        slow_dim: s.slow.len(),
        period,
        d_max: policy.d_max(),
        d_vis_max: s.d_vis_max,
    }
}

/// Sim episodes as a training dataset.
#[derive(Debug)]
pub struct Episodes<'a>(pub &'a [Episode]);

impl Dataset for Episodes<'_> {
    fn num_episodes(&self) -> usize {
        self.0.len()
    }
    fn episode_len(&self, e: usize) -> usize {
        self.0[e].len()
    }
    fn fast(&self, e: usize, t: usize) -> &[f32] {
        self.0[e].fast(t)
    }
    fn slow(&self, e: usize, t: usize) -> &[f32] {
        self.0[e].slow(t)
    }
    fn action(&self, e: usize, t: usize) -> &[f32] {
        self.0[e].action(t)
    }
}

/// Collect `n` expert demonstrations (seeded).
pub fn collect(n: usize, seed: u64, show: bool) -> Result<Vec<Episode>> {
    let task = BallPlateConfig::default();
    let mut env = BallPlate::new(task.clone())?;
    let mut expert = LqrExpert::new(&task, LqrConfig::default())?;
    let pb = if show {
        bar(n as u64, "collecting demonstrations")
    } else {
        ProgressBar::hidden()
    };
    let cfg = CollectConfig {
        episodes: n,
        seed,
        ..CollectConfig::default()
    };
    let eps = pir2_sim::dataset::collect_episodes(&mut env, &mut expert, &cfg, &mut |p| {
        pb.set_position(p.kept as u64)
    })?;
    pb.finish();
    Ok(eps)
}

/// Write episodes as a LeRobotDataset v3.0 (the same writer as every other stack).
pub fn write_dataset(root: &Path, episodes: &[Episode], mode: WriteMode) -> Result<()> {
    let fps = BallPlateConfig::default().control_hz.round() as u32;
    let mut w = DatasetWriter::open(root, DatasetSpec::ballplate(fps), mode)
        .with_context(|| format!("opening dataset {}", root.display()))?;
    for ep in episodes {
        w.append(ep)?;
    }
    w.finish()?;
    Ok(())
}

/// A copy of a model for another thread (same weights, own scratch).
pub fn clone_model(m: &CandleModel) -> Result<CandleModel> {
    let mut c = CandleModel::new(m.config().clone(), m.stats().clone(), 0)?;
    c.restore(&m.snapshot()?)?;
    Ok(c)
}

/// The output map that denormalises the model's actions.
pub fn output_map(m: &CandleModel) -> OutputMap {
    let n = &m.stats().action;
    OutputMap {
        scale: n.std.clone(),
        offset: n.mean.clone(),
    }
}

/// Closed-loop success of `model` under `mode` at unit delay `d0` over `episodes` episodes
/// starting at episode seed `seed`.
pub fn closed_loop(
    model: &CandleModel,
    policy: Policy,
    mode: &Mode,
    d0: usize,
    episodes: usize,
    seed: u64,
    threads: usize,
    progress: &(dyn Fn() + Sync),
) -> Result<(usize, u64)> {
    let task = BallPlateConfig::default();
    let period = (1e9 / task.control_hz).round() as u64;
    let spec = head_spec(policy, period);
    let out = output_map(model);
    let weights = model.snapshot()?;
    let (config, stats) = (model.config().clone(), model.stats().clone());
    let make_model = || {
        let mut c = CandleModel::new(config.clone(), stats.clone(), 0).expect("config was valid");
        c.restore(&weights).expect("same architecture");
        c
    };
    let make_env = || BallPlate::new(task.clone()).expect("default task is valid");
    let timing = LockstepTiming::for_mode(mode, d0);
    Ok(eval_cell(
        &make_env,
        &make_model,
        spec,
        mode,
        timing,
        &out,
        episodes,
        seed,
        threads,
        progress,
    )?)
}

/// Train one policy; the checkpoint is chosen by closed-loop validation.
pub fn train_policy(
    data: &[Episode],
    policy: Policy,
    seed: u64,
    cfg: &DemoConfig,
    out_dir: Option<&Path>,
    pb: &ProgressBar,
) -> Result<(CandleModel, Vec<(usize, f64)>)> {
    let spec = spec();
    let stats = compute_stats(&Episodes(data), &spec)?;
    let config = Config {
        spec,
        model: ModelConfig::Mlp(MlpConfig {
            width: cfg.width,
            depth: cfg.depth,
            ..MlpConfig::default()
        }),
    };
    let mut model = CandleModel::new(config, stats, seed)?;
    let every = (cfg.train_steps / cfg.checkpoints.max(1)).max(1);
    let tc = TrainConfig {
        steps: cfg.train_steps,
        batch_size: cfg.batch_size,
        lr: cfg.lr,
        min_lr: cfg.lr * 0.01,
        warmup: (cfg.train_steps / 20).max(1),
        betas: (0.9, 0.999),
        weight_decay: 1e-4,
        grad_clip: Some(1.0),
        ema: None,
        seed,
        schedule: policy.schedule(cfg.nfe),
        checkpoint_every: Some(every),
        log_every: 50,
        ..TrainConfig::default()
    };
    let val_mode = policy.validation_mode(cfg);
    let val_seed = 1_000_000 + seed;
    let scores = train_validated(
        &mut model,
        &Episodes(data),
        tc,
        out_dir,
        |p| pb.set_position(p.step as u64),
        cfg.val_episodes,
        |m| {
            let (ok, _) = closed_loop(
                m,
                policy,
                &val_mode,
                2,
                cfg.val_episodes,
                val_seed,
                1,
                &|| {},
            )?;
            Ok(ok)
        },
    )?;
    Ok((model, scores))
}

/// Closed-loop validation scores `(step, success)` of one training run.
pub use crate::pipeline::Scores;

/// The demo's result file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DemoResult {
    /// Config used.
    pub config: DemoConfig,
    /// Rows (labels in table order).
    pub labels: Vec<String>,
    /// All cells.
    pub cells: Vec<Cell>,
    /// Checkpoint validation scores per (policy, seed).
    pub validation: Vec<(Policy, u64, Scores)>,
    /// Wall time of each stage, seconds.
    pub timings: Vec<(String, f64)>,
}

/// Run the whole demo into `out` (a new directory).
pub fn run(cfg: &DemoConfig, out: &Path) -> Result<DemoResult> {
    prepare_out(out)?;
    let t0 = Instant::now();
    let mut timings = Vec::new();
    let demos = collect(cfg.demos, 7, true)?;
    write_dataset(&out.join("dataset"), &demos, WriteMode::New)?;
    timings.push(("collect".to_string(), t0.elapsed().as_secs_f64()));

    // Train every (policy, seed) on the worker threads.
    let t1 = Instant::now();
    let jobs: Vec<(Policy, u64)> = cfg
        .seeds
        .iter()
        .flat_map(|&s| Policy::ALL.iter().map(move |&p| (p, s)))
        .collect();
    let pb = bar((jobs.len() * cfg.train_steps) as u64, "training policies");
    let done_steps: Vec<AtomicUsize> = jobs.iter().map(|_| AtomicUsize::new(0)).collect();
    let models = train_jobs(&jobs, cfg.threads, |j, policy, seed| {
        let local = ProgressBar::hidden();
        let ckpt = out
            .join("checkpoints")
            .join(format!("{policy:?}-seed{seed}").to_lowercase());
        let trained = train_policy(&demos, policy, seed, cfg, Some(&ckpt), &local)?;
        done_steps[j].store(cfg.train_steps, Ordering::SeqCst);
        pb.set_position(
            done_steps
                .iter()
                .map(|d| d.load(Ordering::SeqCst) as u64)
                .sum(),
        );
        Ok(trained)
    })?;
    pb.finish();
    timings.push(("train".to_string(), t1.elapsed().as_secs_f64()));

    // Evaluate every row × d0 × seed.
    let t2 = Instant::now();
    let rows = rows(cfg);
    let total = rows.len() * cfg.d0s.len() * cfg.seeds.len() * cfg.episodes;
    let pb = bar(total as u64, "evaluating deployment modes");
    let cells = evaluate_rows(
        rows.iter().map(|r| (r.label.as_str(), r.policy, &r.mode)),
        &cfg.seeds,
        &cfg.d0s,
        cfg.episodes,
        |policy, mode, seed, d0| {
            let j = jobs
                .iter()
                .position(|&(p, s)| p == policy && s == seed)
                .expect("trained");
            let tick = || pb.inc(1);
            closed_loop(
                &models[j].0,
                policy,
                mode,
                d0,
                cfg.episodes,
                2_000_000 + seed,
                cfg.threads,
                &tick,
            )
        },
    )?;
    pb.finish();
    timings.push(("evaluate".to_string(), t2.elapsed().as_secs_f64()));
    let labels: Vec<String> = rows.iter().map(|r| r.label.clone()).collect();
    let validation = jobs
        .iter()
        .zip(&models)
        .map(|(&(p, s), m)| (p, s, m.1.clone()))
        .collect();
    timings.push(("total".to_string(), t0.elapsed().as_secs_f64()));
    let result = DemoResult {
        config: cfg.clone(),
        labels,
        cells,
        validation,
        timings,
    };
    write_outputs(&result, out)?;
    Ok(result)
}

/// Write `result.json`, `table.md` and `success.png`.
pub fn write_outputs(result: &DemoResult, out: &Path) -> Result<()> {
    let json = serde_json::to_string_pretty(result)?;
    std::fs::write(out.join("result.json"), json)
        .with_context(|| format!("writing {}", out.join("result.json").display()))?;
    let t = table(&result.cells, &result.labels, &result.config.d0s);
    std::fs::write(out.join("table.md"), &t)?;
    let series = to_series(&result.cells, &result.labels, &result.config.d0s);
    plot_series(
        &out.join("success.png"),
        &format!(
            "ball-on-plate: success vs unit delay (mean ± std over {} seeds)",
            result.config.seeds.len()
        ),
        "unit delay d0 (ticks)",
        "success rate",
        &series,
    )?;
    Ok(())
}

/// A fresh output directory under `runs/`.
pub fn default_out_dir() -> PathBuf {
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    PathBuf::from("runs").join(format!("demo-{t}"))
}
