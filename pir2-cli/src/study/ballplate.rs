//! The ball-on-plate task (the embedded default, `pir2 demo`): LQR-expert demonstrations,
//! candle MLPs, every deployment mode under latency.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use serde::{Deserialize, Serialize};

use pir2_backends::config::{MlpConfig, ModelConfig, SlowSpec, Spec};
use pir2_backends::train::TrainConfig;
use pir2_runtime::Mode;
use pir2_sim::ballplate::{BallPlate, BallPlateConfig};
use pir2_sim::dataset::{CollectConfig, DatasetSpec, DatasetWriter, Episode, WriteMode};
use pir2_sim::expert::{LqrConfig, LqrExpert};

use super::pipeline::{self, bar, log_line, write_atomically};
use super::{Policy, Row, Settings, Study, StudyResult, Task};

/// Everything `pir2 demo` does, as a TOML-able config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DemoConfig {
    /// Demonstrations to collect.
    pub demos: usize,
    /// Optimiser steps per policy (TOML `steps` or `train_steps`; written as `train_steps`,
    /// the earlier name, so that results read the same).
    #[serde(rename = "train_steps", alias = "steps")]
    pub steps: usize,
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
            steps: 2000,
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
            steps: 1000,
            episodes: 30,
            val_episodes: 10,
            checkpoints: 2,
            ..Self::default()
        }
    }

    /// Read a TOML config (`None`: the default, or [`DemoConfig::quick`]).
    pub fn load(path: Option<&Path>, quick: bool) -> Result<Self> {
        match path {
            Some(p) => {
                let text = std::fs::read_to_string(p)
                    .with_context(|| format!("reading config {}", p.display()))?;
                toml::from_str(&text).with_context(|| format!("parsing config {}", p.display()))
            }
            None if quick => Ok(Self::quick()),
            None => Ok(Self::default()),
        }
    }
}

/// The policies the demo trains (one of each per seed), in table order of their rows.
pub const POLICIES: [Policy; 5] = [
    Policy::Flow,
    Policy::Rtc,
    Policy::PiR2,
    Policy::PiR2Hidden,
    Policy::PiR2Full,
];

/// The ball-on-plate task with a [`DemoConfig`].
#[derive(Debug, Clone)]
pub struct BallPlateTask {
    cfg: DemoConfig,
    env: BallPlateConfig,
}

impl BallPlateTask {
    /// The task at the default environment.
    pub fn new(cfg: DemoConfig) -> Self {
        Self {
            cfg,
            env: BallPlateConfig::default(),
        }
    }
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

impl Task for BallPlateTask {
    type Env = BallPlate;
    type Config = DemoConfig;

    fn config(&self) -> &DemoConfig {
        &self.cfg
    }

    fn settings(&self) -> Settings {
        let c = &self.cfg;
        Settings::from_config(
            c.nfe,
            c.flow_steps,
            &c.seeds,
            c.episodes,
            c.checkpoints,
            c.val_episodes,
            c.threads,
        )
    }

    fn spec(&self) -> Spec {
        spec()
    }

    fn period_ns(&self) -> u64 {
        (1e9 / self.env.control_hz).round() as u64
    }

    fn make_env(&self) -> Result<BallPlate> {
        Ok(BallPlate::new(self.env.clone())?)
    }

    fn model(&self, _: Policy) -> ModelConfig {
        ModelConfig::Mlp(MlpConfig {
            width: self.cfg.width,
            depth: self.cfg.depth,
            ..MlpConfig::default()
        })
    }

    fn optimiser(&self) -> TrainConfig {
        let c = &self.cfg;
        TrainConfig {
            steps: c.steps,
            batch_size: c.batch_size,
            lr: c.lr,
            min_lr: c.lr * 0.01,
            warmup: (c.steps / 20).max(1),
            betas: (0.9, 0.999),
            weight_decay: 1e-4,
            grad_clip: Some(1.0),
            ema: None,
            log_every: 50,
            ..TrainConfig::default()
        }
    }

    /// Every mode of every policy: sync flow, naive async (plain and with ensembling),
    /// train-time RTC, πR² without and with async, front hidden, paper full ramp.
    fn rows(&self) -> Vec<Row> {
        let r = self.settings().recipe;
        POLICIES.iter().flat_map(|p| p.deployments(&r)).collect()
    }

    /// Flow is validated in naive async without ensembling, the πR² policies with async.
    fn validation_mode(&self, policy: Policy) -> Mode {
        let rows = self.rows();
        let mine = || rows.iter().filter(|r| r.policy == policy);
        let pick = match policy {
            Policy::Flow => {
                mine().find(|r| matches!(r.mode, Mode::NaiveAsync { ensemble: None, .. }))
            }
            _ => mine().find(|r| matches!(r.mode, Mode::PiR2Async { .. })),
        };
        pick.or_else(|| mine().next())
            .map(|r| r.mode)
            .unwrap_or_else(|| panic!("{policy:?} has no ball-plate row"))
    }

    /// Collects `demos` expert episodes (seed 7) and writes them to `out/dataset`.
    fn demonstrations(&self, out: &Path) -> Result<Vec<Episode>> {
        let demos = collect(self.cfg.demos, 7, true)?;
        write_dataset(&out.join("dataset"), &demos, WriteMode::New)?;
        Ok(demos)
    }

    fn title(&self, _study: &str) -> String {
        format!(
            "ball-on-plate: success vs unit delay (mean ± std over {} seeds)",
            self.cfg.seeds.len()
        )
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

/// `pir2 collect ballplate`: collect `n` expert episodes (seed `seed`) straight into the
/// dataset at `root`. Once `stop` is set (Ctrl-C) the episode in progress is finished and
/// the episodes kept so far are written; `--resume` adds the rest later.
pub fn collect_into(
    root: &Path,
    n: usize,
    seed: u64,
    mode: WriteMode,
    stop: &std::sync::atomic::AtomicBool,
) -> Result<(
    pir2_sim::dataset::CollectStats,
    pir2_sim::dataset::DatasetSummary,
)> {
    let task = BallPlateConfig::default();
    let mut env = BallPlate::new(task.clone())?;
    let mut expert = LqrExpert::new(&task, LqrConfig::default())?;
    let pb = bar(n as u64, "collecting demonstrations");
    let cfg = CollectConfig {
        episodes: n,
        seed,
        ..CollectConfig::default()
    };
    let fps = task.control_hz.round() as u32;
    let r = pir2_sim::dataset::collect_to_dataset_until(
        &mut env,
        &mut expert,
        &cfg,
        root,
        &DatasetSpec::ballplate(fps),
        mode,
        stop,
        &mut |p| pb.set_position(p.kept as u64),
    )
    .with_context(|| format!("collecting into {}", root.display()))?;
    pb.finish();
    Ok(r)
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

/// The demo's result file.
pub type DemoResult = StudyResult<DemoConfig>;

/// Run the whole demo into `out` (a new directory): collect, train every policy × seed,
/// evaluate every row × unit delay × seed.
pub fn run(cfg: &DemoConfig, out: &Path) -> Result<DemoResult> {
    let task = BallPlateTask::new(cfg.clone());
    let study = Study::deployment(task.rows(), &cfg.d0s);
    pipeline::run(&task, &study, out, false)
}

/// What a `pir2 train ballplate` run in a directory was started with (`train.toml`), so
/// `--resume` continues only the same run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct TrainRun {
    policy: Policy,
    seed: u64,
    config: DemoConfig,
}

/// File of a `pir2 train ballplate` directory recording the run ([`TrainRun`]).
const TRAIN_RUN_FILE: &str = "train.toml";

/// `pir2 train ballplate`: train one policy on a dataset into `out` (a new directory:
/// step checkpoints under `out/steps`, the chosen one in `out/best`). Returns the
/// closed-loop validation scores of this run's checkpoints.
///
/// With `resume`, `out` is an interrupted run of the same policy, seed and config (checked
/// against `out/train.toml`) on the same demonstrations (`out/data.json`): training continues
/// from its last step checkpoint or `interrupted-*` state; a run whose `best/` exists is left
/// as it is (no scores).
pub fn train_checkpoint(
    data: &Path,
    policy: Policy,
    cfg: &DemoConfig,
    seed: u64,
    out: &Path,
    resume: bool,
) -> Result<super::Scores> {
    let run = TrainRun {
        policy,
        seed,
        config: cfg.clone(),
    };
    let run_file = out.join(TRAIN_RUN_FILE);
    if resume {
        let before = std::fs::read_to_string(&run_file).with_context(|| {
            format!(
                "--resume: {} is not a ballplate training run to continue (no readable {})",
                out.display(),
                TRAIN_RUN_FILE
            )
        })?;
        let before: TrainRun = toml::from_str(&before)
            .with_context(|| format!("--resume: reading {}", run_file.display()))?;
        if before != run {
            anyhow::bail!(
                "--resume: {} was trained as --policy {} --seed {} with another config than \
                 this one ({}); resume with the same policy, seed and --config, or train into \
                 a new directory",
                out.display(),
                before.policy.name(),
                before.seed,
                run_file.display()
            );
        }
        if out.join("best").exists() {
            log_line(&format!("{} finished in an earlier run", out.display()));
            return Ok(Vec::new());
        }
    } else if out.exists() {
        anyhow::bail!(
            "checkpoint directory {} already exists; choose another --out (or --resume an \
             interrupted run there)",
            out.display()
        );
    }
    let ds = pir2_sim::dataset::read_dataset(data)
        .with_context(|| format!("reading dataset {}", data.display()))?;
    if !resume {
        std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
        let text = toml::to_string(&run).context("serialising the run")?;
        write_atomically(&run_file, text.as_bytes())?;
    }
    pipeline::check_data(&out.join(pipeline::DATA_FILE), &ds.episodes, resume)?;
    let task = BallPlateTask::new(cfg.clone());
    let pb = indicatif::ProgressBar::new(cfg.steps as u64);
    let (model, scores) = pipeline::train_policy_resumable(
        &task,
        &ds.episodes,
        policy,
        seed,
        Some(&out.join("steps")),
        resume,
        &|s| pb.set_position(s as u64),
    )?;
    pb.finish();
    model.save(&out.join("best"))?;
    Ok(scores)
}

/// `pir2 eval ballplate`: a checkpoint of `policy` in each of its rows at each unit delay,
/// `episodes` episodes per cell seeded from `seed`; `models` runs the action head (the
/// checkpoint itself, or a policy server running it).
pub fn eval_checkpoint(
    models: &pipeline::Models<'_>,
    policy: Policy,
    d0s: &[usize],
    episodes: usize,
    seed: u64,
) -> Result<(Vec<super::Cell>, Vec<String>)> {
    let task = BallPlateTask::new(DemoConfig {
        episodes,
        seeds: vec![seed],
        ..DemoConfig::default()
    });
    let rows: Vec<Row> = task
        .rows()
        .into_iter()
        .filter(|r| r.policy == policy)
        .collect();
    let labels = rows.iter().map(|r| r.label.clone()).collect();
    let study = Study {
        seed_base: 0,
        ..Study::deployment(rows, d0s)
    };
    let cells = pipeline::evaluate(&task, &study, &|_, _| models, None, &ProgressBar::hidden())?;
    Ok((cells, labels))
}

/// A fresh output directory under `runs/`.
pub fn default_out_dir() -> PathBuf {
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    PathBuf::from("runs").join(format!("demo-{t}"))
}

#[cfg(test)]
mod tests {
    use super::DemoConfig;

    #[test]
    fn the_step_count_is_read_as_steps_or_train_steps_and_written_as_train_steps() {
        let new: DemoConfig = toml::from_str("steps = 7").unwrap();
        let old: DemoConfig = toml::from_str("train_steps = 7").unwrap();
        assert_eq!(new, old);
        assert_eq!(new.steps, 7);
        let text = toml::to_string(&new).unwrap();
        assert!(text.contains("train_steps = 7"), "{text}");
        assert!(toml::from_str::<DemoConfig>("steps = 7\ntrain_steps = 7").is_err());
    }
}
