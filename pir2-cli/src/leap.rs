//! The Leap-hand cube stack (feature `mujoco`, issue #6): collect MPC-expert demonstrations
//! into a LeRobotDataset v3.0, train πR² and the baselines (Conditional U-Net 1D), and run the
//! deployment study (modes × unit delay through the lock-step runtime) and the zero-delay
//! horizon study (sync flow h ∈ {1, 2, 4, 8} vs πR²).
//!
//! Defaults of [`LeapStudyConfig`] are a reduced scale that fits a shared 2-core machine in
//! minutes; the paper's scale is noted on every field.

use std::path::Path;
use std::time::Instant;

use std::sync::atomic::AtomicUsize;

use anyhow::{bail, Context, Result};
use indicatif::ProgressBar;
use serde::{Deserialize, Serialize};

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, FilmMode, ModelConfig, SlowSpec, Spec, UNetConfig};
use pir2_backends::train::{compute_stats, Progress, TrainConfig};
use pir2_runtime::{HeadSpec, LockstepTiming, Mode};
use pir2_schedule::train::{DelayDist, PiR2Draws, TrainSchedule};
use pir2_schedule::{Alignment, FrontMode};
use pir2_sim::dataset::{
    read_dataset, DatasetSpec, DatasetSummary, DatasetWriter, Episode, WriteMode,
};
use pir2_sim::leap::{CollectConfig, LeapConfig, LeapCubeEnv, LeapModel, MpcConfig, NU};

use crate::demo::{output_map, Episodes};
use crate::pipeline::{bar, evaluate_rows, prepare_out, train_jobs, train_validated};
use crate::plot::{plot_series, Series};
use crate::study::{eval_cell, table, to_series, Cell};

/// Names of the 32 fast entries (noisy joint angles, noisy joint angle − motor target).
pub fn fast_names() -> Vec<String> {
    (0..NU)
        .map(|i| format!("q{i}"))
        .chain((0..NU).map(|i| format!("q{i}_minus_target{i}")))
        .collect()
}

/// Names of the 9 slow (cube) entries: palm − cube position, rows 2–3 of R(cube quat).
pub fn slow_names() -> Vec<String> {
    let mut v: Vec<String> = [
        "palm_minus_cube_x",
        "palm_minus_cube_y",
        "palm_minus_cube_z",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    for r in 2..=3 {
        for c in 1..=3 {
            v.push(format!("cube_rot_r{r}c{c}"));
        }
    }
    v
}

/// The Leap cube's dataset: 50 fps, 32 fast / 9 slow / 16 action entries.
pub fn dataset_spec() -> DatasetSpec {
    DatasetSpec {
        fps: 50,
        robot_type: Some("leap_hand".into()),
        tasks: vec!["reorient the cube blue side up".into()],
        fast_names: fast_names(),
        slow_names: slow_names(),
        action_names: (0..NU).map(|i| format!("motor_target_delta{i}")).collect(),
    }
}

/// A progress line for logs (progress bars are invisible when stderr is not a terminal).
fn log_line(msg: &str) {
    use std::io::IsTerminal;
    if !std::io::stderr().is_terminal() {
        eprintln!("{msg}");
    }
}

fn load_model() -> Result<LeapModel> {
    LeapModel::load(None)
        .context("loading the Leap cube scene (source .native/env.sh; see scripts/setup-native.sh)")
}

fn to_dataset_episode(ep: &pir2_sim::leap::Episode) -> Episode {
    let mut out = Episode::new(32, 9, NU);
    for f in &ep.frames {
        out.push(&f.fast, &f.slow, &f.action);
    }
    out.done = ep.frames.last().map(|f| f.done).unwrap_or(false);
    out.success = ep.success;
    out.seed = ep.env_seed;
    out
}

/// Collect `per_seed` expert episodes for each collection seed into the LeRobotDataset at
/// `out`. Episodes are ordered seed-major (global index `k·per_seed + i` is episode `i` of
/// `seeds[k]`); with [`WriteMode::Resume`] the episodes already in the dataset are skipped,
/// so an interrupted collection continues where it stopped (the writer is finished every
/// 5 episodes). All episodes are written, failures included (`next.success` says which);
/// training uses the successful ones. `fast_expert` selects [`MpcConfig::fast`]; either
/// recipe runs with [`MpcConfig::pin_first_knot`] so the demonstrated actions are smooth.
pub fn collect_leap(
    out: &Path,
    seeds: &[u64],
    per_seed: usize,
    mode: WriteMode,
    fast_expert: bool,
) -> Result<DatasetSummary> {
    let model = load_model()?;
    let mut w = DatasetWriter::open(out, dataset_spec(), mode)
        .with_context(|| format!("opening dataset {}", out.display()))?;
    let total = seeds.len() * per_seed;
    let mut done = w.num_episodes();
    if done > total {
        bail!(
            "dataset {} already holds {done} episodes, more than the {total} requested",
            out.display()
        );
    }
    let pb = bar(total as u64, "collecting Leap-cube demonstrations");
    pb.set_position(done as u64);
    let base = if fast_expert {
        MpcConfig::fast()
    } else {
        MpcConfig::default()
    };
    // Smooth executed targets: without this the actions are mostly the winning sample's
    // fresh perturbation (std ≈ 0.5 in [−1, 1], no temporal structure) and a cloned policy
    // learns noise (flow loss stuck at its zero-prediction value).
    let mpc = MpcConfig {
        pin_first_knot: true,
        ..base
    };
    let mut successes = 0usize;
    let mut summary = None;
    let t0 = Instant::now();
    while done < total {
        let (k, i) = (done / per_seed, done % per_seed);
        let end = (i + 5).min(per_seed);
        let cfg = CollectConfig {
            env: LeapConfig::paper(),
            mpc,
            seed: seeds[k],
        };
        let eps = pir2_sim::leap::collect(&model, &cfg, i..end, |_| pb.inc(1))?;
        for ep in &eps {
            successes += ep.success as usize;
            w.append(&to_dataset_episode(ep))?;
        }
        done += eps.len();
        summary = Some(w.finish()?);
        w = DatasetWriter::open(out, dataset_spec(), WriteMode::Resume)?;
        pb.set_message(format!("collecting ({successes} successes)"));
        log_line(&format!(
            "collected {done}/{total} episodes ({successes} successes this session), {:.0} s",
            t0.elapsed().as_secs_f64()
        ));
    }
    pb.finish();
    match summary {
        Some(s) => Ok(s),
        None => Ok(w.finish()?),
    }
}

/// The study's scale. Defaults: the reduced scale run on this machine (paper values in the
/// field docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LeapStudyConfig {
    /// Dataset directory (collected with [`collect_leap`]).
    pub dataset: String,
    /// Optimiser steps per policy (paper: far more; not stated per policy).
    pub train_steps: usize,
    /// Batch size (paper 256).
    pub batch_size: usize,
    /// Peak learning rate (paper 1e-4, cosine).
    pub lr: f64,
    /// Warm-up steps (paper 500).
    pub warmup: usize,
    /// U-Net channel widths per level (paper: the diffusion-policy U-Net, 256/512/1024).
    pub widths: Vec<usize>,
    /// GroupNorm groups.
    pub groups: usize,
    /// Checkpoints validated in closed loop per policy.
    pub checkpoints: usize,
    /// Closed-loop validation episodes per checkpoint (at d0 = 2).
    pub val_episodes: usize,
    /// Evaluation episodes per cell (paper 100).
    pub episodes: usize,
    /// Training/evaluation seeds.
    pub seeds: Vec<u64>,
    /// Unit delays of the deployment study.
    pub d0s: Vec<usize>,
    /// Execution horizons of the horizon study.
    pub hs: Vec<usize>,
    /// NFEs per action of the small-n πR² policy.
    pub nfe: usize,
    /// Euler steps of the flow baselines.
    pub flow_steps: usize,
    /// Episode length in control steps (paper 600).
    pub max_steps: usize,
    /// Worker threads.
    pub threads: usize,
    /// Directory of trained policies (`<policy>-seed<s>/best`, as written by
    /// [`train_policies`] / `pir2 train leap-cube` or an earlier study's `checkpoints/`):
    /// policies found there are loaded instead of trained.
    pub pretrained: Option<String>,
    /// Policies whose rows are run (all four by default; rows of the others are skipped).
    pub policies: Vec<LeapPolicy>,
}

impl Default for LeapStudyConfig {
    fn default() -> Self {
        Self {
            dataset: "runs/leap-dataset".into(),
            train_steps: 400,
            batch_size: 64,
            lr: 1e-3,
            warmup: 40,
            widths: vec![32, 64],
            groups: 8,
            checkpoints: 2,
            val_episodes: 2,
            episodes: 4,
            seeds: vec![0],
            d0s: vec![1, 2, 3],
            hs: vec![1, 2, 4, 8],
            nfe: 2,
            flow_steps: 10,
            max_steps: 300,
            threads: 2,
            pretrained: None,
            policies: LeapPolicy::ALL.to_vec(),
        }
    }
}

/// The policies of the Leap study.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LeapPolicy {
    /// πR² at small `n` (per-position FiLM).
    PiR2,
    /// πR² with the paper's full-chunk ramp (per-position FiLM).
    PiR2Full,
    /// Train-time RTC (shared FiLM, d_max 6).
    Rtc,
    /// Standard flow (shared FiLM).
    Flow,
}

impl LeapPolicy {
    /// All policies.
    pub const ALL: [LeapPolicy; 4] = [
        LeapPolicy::PiR2,
        LeapPolicy::PiR2Full,
        LeapPolicy::Rtc,
        LeapPolicy::Flow,
    ];

    /// Trained `d_max`.
    pub fn d_max(self) -> usize {
        match self {
            LeapPolicy::Rtc | LeapPolicy::Flow => 6,
            _ => 5,
        }
    }

    /// FiLM variant of the U-Net.
    pub fn film(self) -> FilmMode {
        match self {
            LeapPolicy::PiR2 | LeapPolicy::PiR2Full => FilmMode::PerPosition,
            _ => FilmMode::Shared,
        }
    }

    /// Training schedule (α = 0.2, d ~ U{0..5} for πR²; d ≤ 6 for RTC).
    pub fn schedule(self, nfe: usize) -> TrainSchedule {
        let base = PiR2Draws {
            alpha: 0.2,
            delay: DelayDist::Uniform { max: 5 },
            n: Some(nfe),
            ..Default::default()
        };
        match self {
            LeapPolicy::PiR2 => TrainSchedule::PiR2(base),
            LeapPolicy::PiR2Full => TrainSchedule::PiR2(PiR2Draws {
                n: None,
                alignment: Alignment::Paper,
                ..base
            }),
            LeapPolicy::Rtc => TrainSchedule::TrainTimeRtc {
                delay: DelayDist::Uniform { max: 6 },
            },
            LeapPolicy::Flow => TrainSchedule::StandardFlow,
        }
    }

    /// Closed-loop validation mode.
    pub fn validation_mode(self, cfg: &LeapStudyConfig) -> Mode {
        deployment_rows(cfg)
            .into_iter()
            .find(|r| r.policy == self)
            .map(|r| r.mode)
            .expect("every policy has a deployment row")
    }
}

/// One row of a study.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LeapRow {
    /// Table label.
    pub label: String,
    /// Policy.
    pub policy: LeapPolicy,
    /// Deployment mode.
    pub mode: Mode,
}

/// Rows of the deployment study.
pub fn deployment_rows(cfg: &LeapStudyConfig) -> Vec<LeapRow> {
    let k = cfg.flow_steps;
    let n = Some(cfg.nfe);
    let vis = FrontMode::Visible;
    vec![
        LeapRow {
            label: "naive async + TE".into(),
            policy: LeapPolicy::Flow,
            mode: Mode::NaiveAsync {
                steps: k,
                ensemble: Some(0.1),
            },
        },
        LeapRow {
            label: "train-time RTC".into(),
            policy: LeapPolicy::Rtc,
            mode: Mode::TrainTimeRtc { steps: k },
        },
        LeapRow {
            label: format!("πR² w/o async (n={})", cfg.nfe),
            policy: LeapPolicy::PiR2,
            mode: Mode::PiR2Sync {
                nfe: n,
                alignment: Alignment::Fresh,
                front: vis,
            },
        },
        LeapRow {
            label: format!("πR² async (n={})", cfg.nfe),
            policy: LeapPolicy::PiR2,
            mode: Mode::PiR2Async {
                nfe: n,
                alignment: Alignment::Fresh,
                front: vis,
            },
        },
        LeapRow {
            label: "πR² async, paper full ramp".into(),
            policy: LeapPolicy::PiR2Full,
            mode: Mode::PiR2Async {
                nfe: None,
                alignment: Alignment::Paper,
                front: vis,
            },
        },
    ]
}

/// The model spec: H = 16, 16-d action, n_obs = 2, 32 fast, 9 slow, d_vis ≤ 3.
pub fn spec() -> Spec {
    Spec {
        horizon: 16,
        action_dim: NU,
        n_obs: 2,
        fast_dim: 32,
        slow: SlowSpec::Vector { dim: 9 },
        d_vis_max: 3,
    }
}

fn head_spec(policy: LeapPolicy) -> HeadSpec {
    let s = spec();
    HeadSpec {
        horizon: s.horizon,
        action_dim: s.action_dim,
        n_obs: s.n_obs,
        fast_dim: s.fast_dim,
        slow_dim: s.slow.len(),
        period: 20_000_000,
        d_max: policy.d_max(),
        d_vis_max: s.d_vis_max,
    }
}

fn env_config(cfg: &LeapStudyConfig) -> LeapConfig {
    LeapConfig {
        max_steps: cfg.max_steps,
        ..LeapConfig::paper()
    }
}

/// Closed-loop successes (and overrun ticks) of `model` under `mode` with `timing` over
/// `episodes` episodes seeded from `seed`.
#[allow(clippy::too_many_arguments)]
pub fn closed_loop(
    leap: &LeapModel,
    cfg: &LeapStudyConfig,
    model: &CandleModel,
    policy: LeapPolicy,
    mode: &Mode,
    timing: LockstepTiming,
    episodes: usize,
    seed: u64,
    threads: usize,
    progress: &(dyn Fn() + Sync),
) -> Result<(usize, u64)> {
    let out = output_map(model);
    let weights = model.snapshot()?;
    let (config, stats) = (model.config().clone(), model.stats().clone());
    let make_model = || {
        let mut c = CandleModel::new(config.clone(), stats.clone(), 0).expect("config was valid");
        c.restore(&weights).expect("same architecture");
        c
    };
    let env_cfg = env_config(cfg);
    let make_env = || LeapCubeEnv::new(leap, env_cfg).expect("paper config is valid");
    Ok(eval_cell(
        &make_env,
        &make_model,
        head_spec(policy),
        mode,
        timing,
        &out,
        episodes,
        seed,
        threads,
        progress,
    )?)
}

/// Load the dataset and keep the successful episodes.
pub fn load_demos(root: &Path) -> Result<Vec<Episode>> {
    let ds = read_dataset(root).with_context(|| format!("reading dataset {}", root.display()))?;
    let eps: Vec<Episode> = ds
        .episodes
        .into_iter()
        .filter(|e| e.success && e.len() >= 2)
        .collect();
    if eps.is_empty() {
        bail!("dataset {} has no successful episodes", root.display());
    }
    Ok(eps)
}

/// Train one policy (U-Net; AdamW β = (0.95, 0.999), cosine, wd 1e-6, clip 1.0; steps, batch,
/// lr, warm-up and widths from `cfg`); the checkpoint is chosen by closed-loop validation at
/// d0 = 2. Returns the model and the validation scores.
pub fn train_leap(
    leap: &LeapModel,
    data: &[Episode],
    policy: LeapPolicy,
    seed: u64,
    cfg: &LeapStudyConfig,
    out_dir: Option<&Path>,
    pb: &ProgressBar,
) -> Result<(CandleModel, Scores)> {
    let spec = spec();
    let stats = compute_stats(&Episodes(data), &spec)?;
    let unet = UNetConfig {
        widths: cfg.widths.clone(),
        groups: cfg.groups,
        tau_dim: 32,
        dvis_dim: 8,
        film: policy.film(),
        ..UNetConfig::default()
    };
    let config = Config {
        spec,
        model: ModelConfig::UNet(unet),
    };
    let mut model = CandleModel::new(config, stats, seed)?;
    let every = (cfg.train_steps / cfg.checkpoints.max(1)).max(1);
    let tc = TrainConfig {
        steps: cfg.train_steps,
        batch_size: cfg.batch_size,
        lr: cfg.lr,
        min_lr: 0.0,
        warmup: cfg.warmup.min(cfg.train_steps.saturating_sub(1)),
        betas: (0.95, 0.999),
        weight_decay: 1e-6,
        grad_clip: Some(1.0),
        ema: None,
        seed,
        schedule: policy.schedule(cfg.nfe),
        checkpoint_every: Some(every),
        log_every: 50,
        ..TrainConfig::default()
    };
    let val_mode = policy.validation_mode(cfg);
    let val_timing = LockstepTiming::for_mode(&val_mode, 2);
    let val_seed = 1_000_000 + seed;
    let t0 = Instant::now();
    let mut loss_sum = 0.0f64;
    let on_progress = |p: &Progress| {
        pb.set_position(p.step as u64);
        loss_sum += p.loss as f64;
        if p.step % 100 == 0 || p.step == p.steps {
            log_line(&format!(
                "  {policy:?} seed {seed}: step {}/{}, mean loss {:.4}, {:.1} steps/s",
                p.step,
                p.steps,
                loss_sum / 100.0,
                p.step as f64 / t0.elapsed().as_secs_f64()
            ));
            loss_sum = 0.0;
        }
    };
    let scores = train_validated(
        &mut model,
        &Episodes(data),
        tc,
        out_dir,
        on_progress,
        cfg.val_episodes,
        |m| {
            let (ok, _) = closed_loop(
                leap,
                cfg,
                m,
                policy,
                &val_mode,
                val_timing,
                cfg.val_episodes,
                val_seed,
                1,
                &|| {},
            )?;
            log_line(&format!(
                "  {policy:?} seed {seed}: checkpoint validation {ok}/{} at d0 = 2",
                cfg.val_episodes
            ));
            Ok(ok)
        },
    )?;
    Ok((model, scores))
}

/// Closed-loop validation scores of one training run: `(step, success rate)`.
pub use crate::pipeline::Scores;

/// Result of a Leap study.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LeapStudyResult {
    /// `deployment` or `horizon`.
    pub study: String,
    /// Config used.
    pub config: LeapStudyConfig,
    /// Successful demonstrations trained on.
    pub demos: usize,
    /// Row labels in table order.
    pub labels: Vec<String>,
    /// Column keys (d0 for deployment, h for horizon).
    pub columns: Vec<usize>,
    /// All cells (`d0` holds the column key).
    pub cells: Vec<Cell>,
    /// Validation scores per (policy, seed).
    pub validation: Vec<(LeapPolicy, u64, Scores)>,
    /// Wall time per stage, seconds.
    pub timings: Vec<(String, f64)>,
}

type Trained = Vec<(LeapPolicy, u64, CandleModel, Scores)>;

/// Directory name of a trained policy under a checkpoints directory.
pub fn policy_dir(p: LeapPolicy, seed: u64) -> String {
    format!("{p:?}-seed{seed}").to_lowercase()
}

/// Train (or load from `cfg.pretrained`) every policy × seed; each trained policy's best
/// checkpoint is saved to `ckpt_root/<policy>-seed<s>/best`.
fn train_all(
    leap: &LeapModel,
    demos: &[Episode],
    policies: &[LeapPolicy],
    cfg: &LeapStudyConfig,
    ckpt_root: &Path,
) -> Result<Trained> {
    let jobs: Vec<(LeapPolicy, u64)> = cfg
        .seeds
        .iter()
        .flat_map(|&s| policies.iter().map(move |&p| (p, s)))
        .collect();
    let pb = bar(
        (jobs.len() * cfg.train_steps) as u64,
        &format!("training {} policies", jobs.len()),
    );
    let done = AtomicUsize::new(0);
    // Policies train in parallel on `threads` workers (each seeded on its own).
    let models = train_jobs(&jobs, cfg.threads, |i, p, s| {
        if let Some(dir) = &cfg.pretrained {
            let best = Path::new(dir).join(policy_dir(p, s)).join("best");
            if best.exists() {
                let m = CandleModel::load_expect(&best, &spec())
                    .with_context(|| format!("loading {}", best.display()))?;
                log_line(&format!("loaded {p:?} seed {s} from {}", best.display()));
                return Ok((m, Vec::new()));
            }
        }
        let t = Instant::now();
        let ckpt = ckpt_root.join(policy_dir(p, s));
        let (m, scores) = train_leap(leap, demos, p, s, cfg, Some(&ckpt), &ProgressBar::hidden())?;
        m.save(&ckpt.join("best"))?;
        pb.set_position(
            (done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1) as u64
                * cfg.train_steps as u64,
        );
        log_line(&format!(
            "trained {p:?} seed {s} ({}/{}) in {:.0} s; closed-loop validation (step, success): {scores:?}",
            i + 1,
            jobs.len(),
            t.elapsed().as_secs_f64()
        ));
        Ok((m, scores))
    })?;
    pb.finish();
    Ok(jobs
        .into_iter()
        .zip(models)
        .map(|((p, s), (m, sc))| (p, s, m, sc))
        .collect())
}

/// Train `policies` × `cfg.seeds` on the dataset `cfg.dataset` into `out` (a new directory):
/// `out/<policy>-seed<s>/` holds the step checkpoints, `loss.jsonl`, `best.json` and the chosen
/// checkpoint `best/`. Point [`LeapStudyConfig::pretrained`] at `out` to evaluate them.
pub fn train_policies(
    cfg: &LeapStudyConfig,
    policies: &[LeapPolicy],
    out: &Path,
) -> Result<Vec<(LeapPolicy, u64, Scores)>> {
    prepare_out(out)?;
    let leap = load_model()?;
    let demos = load_demos(Path::new(&cfg.dataset))?;
    let cfg = LeapStudyConfig {
        pretrained: None,
        ..cfg.clone()
    };
    let trained = train_all(&leap, &demos, policies, &cfg, out)?;
    std::fs::write(
        out.join("config.toml"),
        toml::to_string(&cfg).context("serialising the config")?,
    )?;
    Ok(trained.into_iter().map(|t| (t.0, t.1, t.3)).collect())
}

fn model_of(trained: &Trained, p: LeapPolicy, s: u64) -> &CandleModel {
    &trained
        .iter()
        .find(|t| t.0 == p && t.1 == s)
        .expect("trained")
        .2
}

/// Deployment study: every row of [`deployment_rows`] × `d0s` × seeds through the lock-step
/// runtime with `LockstepTiming::for_mode` (h = d, slow features delayed by d_vis).
/// Writes `result.json`, `table.md`, `success.png` into `out` (a new directory).
pub fn study_deployment(cfg: &LeapStudyConfig, out: &Path) -> Result<LeapStudyResult> {
    prepare_out(out)?;
    let t0 = Instant::now();
    let leap = load_model()?;
    let demos = load_demos(Path::new(&cfg.dataset))?;
    let rows: Vec<LeapRow> = deployment_rows(cfg)
        .into_iter()
        .filter(|r| cfg.policies.contains(&r.policy))
        .collect();
    let policies: Vec<LeapPolicy> = LeapPolicy::ALL
        .into_iter()
        .filter(|p| rows.iter().any(|r| r.policy == *p))
        .collect();
    let trained = train_all(&leap, &demos, &policies, cfg, &out.join("checkpoints"))?;
    let mut timings = vec![("train".to_string(), t0.elapsed().as_secs_f64())];
    let t1 = Instant::now();
    let pb = bar(
        (rows.len() * cfg.d0s.len() * cfg.seeds.len() * cfg.episodes) as u64,
        "evaluating deployment modes",
    );
    let cells = evaluate_rows(
        rows.iter().map(|r| (r.label.as_str(), r.policy, &r.mode)),
        &cfg.seeds,
        &cfg.d0s,
        cfg.episodes,
        |policy, mode, seed, d0| {
            let r = closed_loop(
                &leap,
                cfg,
                model_of(&trained, policy, seed),
                policy,
                mode,
                LockstepTiming::for_mode(mode, d0),
                cfg.episodes,
                2_000_000 + seed,
                cfg.threads,
                &|| pb.inc(1),
            )?;
            log_line(&format!(
                "{policy:?} {mode:?} d0={d0} seed {seed}: {}/{}",
                r.0, cfg.episodes
            ));
            Ok(r)
        },
    )?;
    pb.finish();
    timings.push(("evaluate".to_string(), t1.elapsed().as_secs_f64()));
    timings.push(("total".to_string(), t0.elapsed().as_secs_f64()));
    let result = LeapStudyResult {
        study: "deployment".into(),
        config: cfg.clone(),
        demos: demos.len(),
        labels: rows.iter().map(|r| r.label.clone()).collect(),
        columns: cfg.d0s.clone(),
        cells,
        validation: trained.iter().map(|t| (t.0, t.1, t.3.clone())).collect(),
        timings,
    };
    write_outputs(&result, out, "unit delay d0 (ticks)")?;
    Ok(result)
}

/// Horizon study at zero delay (`call_ticks = 0`, no slow delay): sync flow with each
/// `h ∈ hs` vs πR² (n = `nfe`, and the full ramp), which acts every tick. πR² does not
/// depend on `h`: it is evaluated once and its cell repeated in every column.
pub fn study_horizon(cfg: &LeapStudyConfig, out: &Path) -> Result<LeapStudyResult> {
    prepare_out(out)?;
    let t0 = Instant::now();
    let leap = load_model()?;
    let demos = load_demos(Path::new(&cfg.dataset))?;
    let policies: Vec<LeapPolicy> = [LeapPolicy::Flow, LeapPolicy::PiR2, LeapPolicy::PiR2Full]
        .into_iter()
        .filter(|p| cfg.policies.contains(p))
        .collect();
    let trained = train_all(&leap, &demos, &policies, cfg, &out.join("checkpoints"))?;
    let mut timings = vec![("train".to_string(), t0.elapsed().as_secs_f64())];
    let t1 = Instant::now();
    let zero = LockstepTiming {
        call_ticks: 0,
        slow_delay: 0,
        overrun_ticks: 0,
        overrun_every: 0,
        pin_delay: true,
    };
    let pir2_rows: Vec<(String, LeapPolicy, Mode)> = [
        (
            format!("πR² (n={})", cfg.nfe),
            LeapPolicy::PiR2,
            Mode::PiR2Async {
                nfe: Some(cfg.nfe),
                alignment: Alignment::Fresh,
                front: FrontMode::Visible,
            },
        ),
        (
            "πR², paper full ramp".to_string(),
            LeapPolicy::PiR2Full,
            Mode::PiR2Async {
                nfe: None,
                alignment: Alignment::Paper,
                front: FrontMode::Visible,
            },
        ),
    ]
    .into_iter()
    .filter(|r| policies.contains(&r.1))
    .collect();
    let flow_hs: &[usize] = if policies.contains(&LeapPolicy::Flow) {
        &cfg.hs
    } else {
        &[]
    };
    let pb = bar(
        ((flow_hs.len() + pir2_rows.len()) * cfg.seeds.len() * cfg.episodes) as u64,
        "evaluating horizon sweep",
    );
    let mut cells = Vec::new();
    let flow_label = "sync flow".to_string();
    for &seed in &cfg.seeds {
        for &h in flow_hs {
            let model = model_of(&trained, LeapPolicy::Flow, seed);
            let mode = Mode::SyncFlow {
                steps: cfg.flow_steps,
                h,
            };
            let (ok, overruns) = closed_loop(
                &leap,
                cfg,
                model,
                LeapPolicy::Flow,
                &mode,
                zero,
                cfg.episodes,
                3_000_000 + seed,
                cfg.threads,
                &|| pb.inc(1),
            )?;
            log_line(&format!(
                "sync flow h={h} seed {seed}: {ok}/{}",
                cfg.episodes
            ));
            cells.push(Cell {
                label: flow_label.clone(),
                d0: h,
                seed,
                successes: ok,
                episodes: cfg.episodes,
                overruns,
            });
        }
        for (label, p, mode) in &pir2_rows {
            let model = model_of(&trained, *p, seed);
            let (ok, overruns) = closed_loop(
                &leap,
                cfg,
                model,
                *p,
                mode,
                zero,
                cfg.episodes,
                3_000_000 + seed,
                cfg.threads,
                &|| pb.inc(1),
            )?;
            log_line(&format!("{label} seed {seed}: {ok}/{}", cfg.episodes));
            for &h in &cfg.hs {
                cells.push(Cell {
                    label: label.clone(),
                    d0: h,
                    seed,
                    successes: ok,
                    episodes: cfg.episodes,
                    overruns,
                });
            }
        }
    }
    pb.finish();
    timings.push(("evaluate".to_string(), t1.elapsed().as_secs_f64()));
    timings.push(("total".to_string(), t0.elapsed().as_secs_f64()));
    let mut labels = if flow_hs.is_empty() {
        vec![]
    } else {
        vec![flow_label]
    };
    labels.extend(pir2_rows.iter().map(|r| r.0.clone()));
    let result = LeapStudyResult {
        study: "horizon".into(),
        config: cfg.clone(),
        demos: demos.len(),
        labels,
        columns: cfg.hs.clone(),
        cells,
        validation: trained.iter().map(|t| (t.0, t.1, t.3.clone())).collect(),
        timings,
    };
    write_outputs(&result, out, "execution horizon h (ticks), zero delay")?;
    Ok(result)
}

/// The Markdown table of a study (columns named `d0=` for deployment, `h=` for horizon).
pub fn result_table(result: &LeapStudyResult) -> String {
    let t = table(&result.cells, &result.labels, &result.columns);
    if result.study == "horizon" {
        t.replace(" d0=", " h=")
    } else {
        t
    }
}

fn write_outputs(result: &LeapStudyResult, out: &Path, xlabel: &str) -> Result<()> {
    std::fs::write(
        out.join("result.json"),
        serde_json::to_string_pretty(result)?,
    )?;
    std::fs::write(out.join("table.md"), result_table(result))?;
    let series: Vec<Series> = to_series(&result.cells, &result.labels, &result.columns);
    plot_series(
        &out.join("success.png"),
        &format!(
            "Leap cube ({} study): success (mean ± std over {} seeds)",
            result.study,
            result.config.seeds.len()
        ),
        xlabel,
        "success rate",
        &series,
    )?;
    Ok(())
}
