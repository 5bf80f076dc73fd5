//! The Leap-hand cube task (feature `mujoco`): MPC-expert demonstrations in a
//! LeRobotDataset v3.0, Conditional U-Net 1D policies, the deployment study (modes × unit
//! delay) and the zero-delay horizon study (sync flow `h ∈ {1, 2, 4, 8}` vs πR²).
//!
//! One file on purpose: a task is one file (see [`super`]): its config, demonstrations,
//! model, rows and studies, each field of the config documented against the paper.
//!
//! Defaults of [`LeapStudyConfig`]: the paper's simulation protocol (its appendix, which
//! wins where the paper's main text differs: exponential training delays `p(d) ∝ e^{−d}`
//! over `{0..d_max}` with πR² `d_max` 5 and train-time RTC `d_max` 10, `K = 15` Euler steps
//! for the flow baselines, naive async as a plain swap with `h = d`, no staleness training
//! and no delay embedding, `n_obs = 2`), at a reduced training and evaluation scale that
//! fits a shared 2-core machine (the paper's scale is noted on every field). Deliberate
//! deviations are separate, labelled rows (temporal ensembling: `te_row`), never the
//! default.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use pir2_backends::config::{FilmMode, ModelConfig, SlowSpec, Spec, UNetConfig};
use pir2_backends::train::TrainConfig;
use pir2_runtime::{DelayLaw, LockstepTiming, Mode, Recipe, SlowFrames};
use pir2_sim::dataset::{
    read_dataset, DatasetSpec, DatasetSummary, DatasetWriter, Episode, WriteMode,
};
use pir2_sim::leap::ppo::PpoExpert;
use pir2_sim::leap::{CollectConfig, LeapConfig, LeapCubeEnv, LeapModel, MpcConfig, NU};

use super::pipeline::{self, bar, log_line};
use super::{Policy, Row, Scores, Settings, Study, StudyResult, StudyRow, Sweep, Task};

/// The policies of the Leap study trained by default.
pub const POLICIES: [Policy; 4] = [Policy::PiR2, Policy::PiR2Full, Policy::Rtc, Policy::Flow];

/// Every policy the Leap study can train (the default four, the front-hidden πR² and the
/// zero-delay πR² policies of the horizon study: the paper's streaming ramp and the n-slot
/// extra).
pub const ALL_POLICIES: [Policy; 7] = [
    Policy::PiR2,
    Policy::PiR2Hidden,
    Policy::PiR2Full,
    Policy::Rtc,
    Policy::Flow,
    Policy::PiR2ZeroDelay,
    Policy::PiR2ZeroDelayFull,
];

/// Who demonstrates in `pir2 collect leap-cube` ([`collect_leap`]).
#[derive(Debug, Clone, PartialEq)]
pub enum ExpertChoice {
    /// The sampling MPC on the privileged state (`fast`: the cheaper recipe).
    Mpc {
        /// The faster, weaker recipe.
        fast: bool,
    },
    /// Trained policy weights (`pir2-ppo-expert-v1`), used deterministically: one file for
    /// every seed, or one per seed.
    Weights(Vec<PathBuf>),
}

/// The study's scale. Defaults: the reduced scale run on this machine (paper values in the
/// field docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LeapStudyConfig {
    /// Dataset directory (collected with [`collect_leap`]).
    pub dataset: String,
    /// Optimiser steps per policy (paper: far more; not stated per policy). TOML `steps` or
    /// `train_steps`; written as `train_steps`, the earlier name, so that the fingerprints of
    /// logged cells and the committed configs stay as they are.
    #[serde(rename = "train_steps", alias = "steps")]
    pub steps: usize,
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
    /// Episodes of an evaluation cell run side by side with their model calls batched, one
    /// batched call per round of calls (1: every episode on its own with batch-1 calls,
    /// `threads` episodes at a time, as before). The batched kernels round differently from
    /// batch-1 calls, so a batched cell is a measurement of its own, equal in distribution but
    /// not bit for bit: the cell log keys it apart (by this group size and the kernel thread
    /// count), and a cell measured one way is never reused for the other. Training's
    /// closed-loop checkpoint validation always runs batch-1.
    pub batch_episodes: usize,
    /// Directory of trained policies (`<policy>-seed<s>/best`, as written by
    /// [`train_policies`] / `pir2 train leap-cube` or an earlier study's `checkpoints/`):
    /// policies found there are loaded instead of trained. A listed policy missing there is
    /// an error naming its run directory, unless [`train_missing`](Self::train_missing).
    pub pretrained: Option<String>,
    /// With [`pretrained`](Self::pretrained): train a listed policy missing there (into the
    /// study's `--out`) instead of refusing. Off by default, so that a mistyped path or an
    /// unfinished run does not start hours of training unasked (`pir2 eval leap-cube
    /// --train-missing`).
    pub train_missing: bool,
    /// Policies whose rows are run (all four by default; rows of the others are skipped).
    /// Add `pi_r2_zero_delay_full` to train the paper's `d_max = 0` πR² variant of the horizon
    /// study (the full streaming ramp), `pi_r2_zero_delay` for the `n`-slot extra.
    pub policies: Vec<Policy>,
    /// Law of the training delay draws (paper: exponential, rate 1, over `{0..d_max}`;
    /// `{ law = "uniform" }` draws `U{1..d_max}`).
    pub delays: DelayLaw,
    /// Training `d_max` of the πR² policies (paper 5).
    pub pir2_d_max: usize,
    /// Training `d_max` of train-time RTC (paper 10).
    pub rtc_d_max: usize,
    /// Half-width `j` of the `τ` jitter of the πR² staircase draws (the paper names it but
    /// gives no value for the simulation: 0).
    pub jitter: f32,
    /// Staleness of the slow (cube) features seen in training, `d_vis ~ U{0..d_vis_max}`,
    /// and the size of the delay embedding (paper's simulation: neither, 0; at deployment
    /// the slow features are still delayed by the mode's `d_vis`).
    pub d_vis_max: usize,
    /// Slow (cube) frames the policies see, oldest first (the paper: `n_obs = 2` for both
    /// channels; 1 gives the single-frame input of earlier runs). The frames are stacked from
    /// the recorded per-tick observations in training and by [`SlowFrames`] in evaluation,
    /// so a delayed slow input is delayed as a whole.
    pub slow_frames: usize,
    /// Add the "naive async + TE" row (ACT temporal ensembling, which the paper uses only on
    /// the real robot) next to the paper's plain-swap naive async.
    pub te_row: bool,
    /// FiLM of the πR² policies' U-Nets (the baselines keep the shared head, as the paper):
    /// `per_position_heads` (the paper's: one head per chunk position, each initialised as a
    /// copy of the shared head; the default) or `per_position_tau` (the ablation: the shared
    /// head plus one zero-initialised projection of each position's `τ` embedding, shared by all
    /// positions; what pir2 ≤ 0.1 trained, so a config without this field that was written
    /// then means it: see `studies/leap-cube/ablation-per-position-tau.toml`).
    pub pir2_film: FilmMode,
    /// The paper picks "the best epoch per seed" for each cell. With `best_of_last` = k > 0
    /// the study also evaluates every cell with the last k step checkpoints of each training
    /// run besides the chosen one and reports the best per cell as a second, labelled table
    /// (optimistic: it selects on the evaluation episodes). Costs k times the evaluation.
    /// 0: off.
    pub best_of_last: usize,
    /// Add diagnostic rows to the deployment study (not in the paper): the πR² checkpoint run
    /// as a sync-flow policy (`flow_steps` steps on one shared `τ`, which its warm-up branch
    /// trains; `h = d`, holding the robot during each call), next to the flow baseline's
    /// sync row. It separates what the network learned from what the staircase inference
    /// does with it. Off by default; it adds rows without changing any other cell.
    pub diagnostic_rows: bool,
}

impl Default for LeapStudyConfig {
    fn default() -> Self {
        Self {
            dataset: "runs/leap-dataset".into(),
            steps: 400,
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
            flow_steps: 15,
            max_steps: 300,
            threads: 2,
            batch_episodes: 1,
            pretrained: None,
            train_missing: false,
            policies: POLICIES.to_vec(),
            delays: DelayLaw::Exponential { rate: 1.0 },
            pir2_d_max: 5,
            rtc_d_max: 10,
            jitter: 0.0,
            d_vis_max: 0,
            slow_frames: 2,
            te_row: true,
            pir2_film: FilmMode::PerPositionHeads,
            best_of_last: 0,
            diagnostic_rows: false,
        }
    }
}

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
        keys: Default::default(),
    }
}

/// The model spec: H = 16, 16-d action, n_obs = 2 fast frames of 32, `slow_frames` slow
/// (cube) frames of 9 (the paper: 2), staleness training and delay embedding up to
/// `d_vis_max` (the paper's simulation: 0).
pub fn spec(d_vis_max: usize, slow_frames: usize) -> Spec {
    Spec {
        horizon: 16,
        action_dim: NU,
        n_obs: 2,
        fast_dim: 32,
        slow: SlowSpec::Vector {
            dim: 9 * slow_frames,
        },
        d_vis_max,
    }
}

fn load_model() -> Result<LeapModel> {
    LeapModel::load(None)
        .context("loading the Leap cube scene (source .native/env.sh; see scripts/setup-native.sh)")
}

/// The Leap cube task with a [`LeapStudyConfig`] (holds the loaded scene).
pub struct LeapCubeTask {
    cfg: LeapStudyConfig,
    scene: LeapModel,
}

impl std::fmt::Debug for LeapCubeTask {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LeapCubeTask")
            .field("cfg", &self.cfg)
            .finish_non_exhaustive()
    }
}

impl LeapCubeTask {
    /// Load the scene. A config with `slow_frames = 0` is refused.
    pub fn new(cfg: LeapStudyConfig) -> Result<Self> {
        if cfg.slow_frames == 0 {
            bail!("config: slow_frames must be >= 1 (the paper uses 2)");
        }
        Ok(Self {
            cfg,
            scene: load_model()?,
        })
    }

    /// The deployment study: every row of [`Task::rows`] at each unit delay of `d0s`, after a
    /// sync-flow row (when `flow` is trained) that acts with `h = d` and holds the robot while
    /// each call runs.
    pub fn deployment_study(&self) -> Study {
        let mut study = Study::deployment(self.rows(), &self.cfg.d0s);
        if self.cfg.policies.contains(&Policy::Flow) {
            study.rows.insert(
                0,
                StudyRow {
                    row: Row {
                        label: "sync flow (h = d, waits during inference)".into(),
                        policy: Policy::Flow,
                        mode: Mode::SyncFlow {
                            steps: self.cfg.flow_steps,
                            h: 1,
                        },
                    },
                    sweep: Sweep::UnitDelaySync,
                },
            );
        }
        if self.cfg.diagnostic_rows && self.cfg.policies.contains(&Policy::PiR2) {
            study.rows.push(StudyRow {
                row: Row {
                    label: format!(
                        "diagnostic: πR² checkpoint as sync flow (K = {}, h = d)",
                        self.cfg.flow_steps
                    ),
                    policy: Policy::PiR2,
                    mode: Mode::SyncFlow {
                        steps: self.cfg.flow_steps,
                        h: 1,
                    },
                },
                sweep: Sweep::UnitDelaySync,
            });
        }
        study
    }

    /// The horizon study at zero delay (`call_ticks = 0`, no slow delay): sync flow with
    /// each `h ∈ hs` vs πR² (n = `nfe`; the `d_max = 0` policy when `policies` holds
    /// `pir2_zero_delay`, the paper's variant; and the full ramp), which acts every tick. πR²
    /// does not depend on `h`: it is evaluated once and its cell repeated in every column.
    pub fn horizon_study(&self) -> Study {
        let c = &self.cfg;
        let zero = LockstepTiming::zero_latency();
        let rows = self.rows();
        let find = |p: Policy, m: fn(&Mode) -> bool| {
            rows.iter().find(|r| r.policy == p && m(&r.mode)).cloned()
        };
        let mut out = Vec::new();
        if c.policies.contains(&Policy::Flow) {
            let steps = c.flow_steps;
            out.push(StudyRow {
                row: Row {
                    label: "sync flow".into(),
                    policy: Policy::Flow,
                    mode: Mode::SyncFlow { steps, h: 1 },
                },
                sweep: Sweep::Horizon,
            });
        }
        let pir2 = find(Policy::PiR2, |m| matches!(m, Mode::PiR2Async { .. }));
        if let Some(r) = pir2 {
            out.push(StudyRow {
                row: Row {
                    label: format!("πR² (n={})", c.nfe),
                    ..r
                },
                sweep: Sweep::Once(zero),
            });
        }
        if c.policies.contains(&Policy::PiR2ZeroDelayFull) {
            let r = Policy::PiR2ZeroDelayFull
                .deployments(&self.settings().recipe)
                .remove(0);
            out.push(StudyRow {
                row: Row {
                    label: "πR² zero-delay policy, d_max = 0, paper streaming ramp".into(),
                    ..r
                },
                sweep: Sweep::Once(zero),
            });
        }
        if c.policies.contains(&Policy::PiR2ZeroDelay) {
            let r = Policy::PiR2ZeroDelay
                .deployments(&self.settings().recipe)
                .remove(0);
            out.push(StudyRow {
                row: Row {
                    label: format!("πR² zero-delay policy, d_max = 0 (n={})", c.nfe),
                    ..r
                },
                sweep: Sweep::Once(zero),
            });
        }
        if let Some(r) = find(Policy::PiR2Full, |_| true) {
            out.push(StudyRow {
                row: Row {
                    label: "πR², paper full ramp".into(),
                    ..r
                },
                sweep: Sweep::Once(zero),
            });
        }
        Study {
            name: "horizon".into(),
            key: "h".into(),
            x_label: "execution horizon h (ticks), zero delay".into(),
            columns: c.hs.clone(),
            rows: out,
            seed_base: 3_000_000,
        }
    }
}

impl Task for LeapCubeTask {
    type Env = SlowFrames<LeapCubeEnv>;
    type Config = LeapStudyConfig;

    fn config(&self) -> &LeapStudyConfig {
        &self.cfg
    }

    fn settings(&self) -> Settings {
        let c = &self.cfg;
        let base = Settings::from_config(
            c.nfe,
            c.flow_steps,
            &c.seeds,
            c.episodes,
            c.checkpoints,
            c.val_episodes,
            c.threads,
        );
        Settings {
            pretrained: c.pretrained.as_ref().map(Into::into),
            train_missing: c.train_missing,
            // Success rates over 20 episodes tie often; the later checkpoint wins a tie.
            later_ties: true,
            best_of_last: c.best_of_last,
            batch_episodes: c.batch_episodes,
            recipe: Recipe {
                delays: c.delays,
                pir2_d_max: c.pir2_d_max,
                rtc_d_max: c.rtc_d_max,
                jitter: c.jitter,
                ..base.recipe
            },
            ..base
        }
    }

    fn spec(&self) -> Spec {
        spec(self.cfg.d_vis_max, self.cfg.slow_frames)
    }

    fn period_ns(&self) -> u64 {
        20_000_000
    }

    fn make_env(&self) -> Result<SlowFrames<LeapCubeEnv>> {
        let cfg = LeapConfig {
            max_steps: self.cfg.max_steps,
            ..LeapConfig::paper()
        };
        Ok(SlowFrames::new(
            LeapCubeEnv::new(&self.scene, cfg)?,
            self.cfg.slow_frames,
        ))
    }

    /// U-Net with per-position FiLM ([`LeapStudyConfig::pir2_film`]) for the πR² policies,
    /// shared FiLM for the baselines.
    fn model(&self, policy: Policy) -> ModelConfig {
        unet(&self.cfg, policy)
    }

    /// The same config with another `pir2_film`, when `policy`'s network does not change
    /// with it (the baselines, whose U-Nets keep the shared FiLM): the per-position heads
    /// study and the shared-projection ablation share their baselines' cells.
    fn equivalent_fingerprints(&self, policy: Policy) -> Result<Vec<String>> {
        let mut out = Vec::new();
        for film in [
            FilmMode::Shared,
            FilmMode::PerPositionHeads,
            FilmMode::PerPositionTau,
        ] {
            let other = LeapStudyConfig {
                pir2_film: film,
                ..self.cfg.clone()
            };
            if film != self.cfg.pir2_film && unet(&other, policy) == unet(&self.cfg, policy) {
                out.push(super::evaluate::config_fingerprint(&other)?);
                out.extend(super::evaluate::earlier_config_fingerprints(&other)?);
            }
        }
        Ok(out)
    }

    /// AdamW β = (0.95, 0.999), cosine to 0, wd 1e-6, clip 1.0; steps, batch, lr and
    /// warm-up from the config.
    fn optimiser(&self) -> TrainConfig {
        let c = &self.cfg;
        TrainConfig {
            steps: c.steps,
            batch_size: c.batch_size,
            lr: c.lr,
            min_lr: 0.0,
            warmup: c.warmup.min(c.steps.saturating_sub(1)),
            betas: (0.95, 0.999),
            weight_decay: 1e-6,
            grad_clip: Some(1.0),
            ema: None,
            log_every: 50,
            ..TrainConfig::default()
        }
    }

    /// Naive async (plain swap, `h = d`), naive async + TE (only with `te_row`, labelled as
    /// outside the paper's protocol), train-time RTC, πR² without and with async, πR² with
    /// the front hidden, πR² full ramp (rows of policies outside the config's `policies` are
    /// left out; the zero-delay policy has its row in the horizon study only).
    fn rows(&self) -> Vec<Row> {
        let r = self.settings().recipe;
        [
            Policy::Flow,
            Policy::Rtc,
            Policy::PiR2,
            Policy::PiR2Hidden,
            Policy::PiR2Full,
        ]
        .iter()
        .filter(|p| self.cfg.policies.contains(p))
        .flat_map(|p| p.deployments(&r))
        .filter(|d| match d.mode {
            Mode::SyncFlow { .. } => false,
            Mode::NaiveAsync { ensemble, .. } => ensemble.is_none() || self.cfg.te_row,
            _ => true,
        })
        .map(|mut d| {
            if matches!(
                d.mode,
                Mode::NaiveAsync {
                    ensemble: Some(_),
                    ..
                }
            ) {
                d.label = "naive async + TE (not in the paper's sim)".into();
            }
            d
        })
        .collect()
    }

    /// The zero-delay policy is validated at zero latency (it cannot run with a delay);
    /// every other policy in its first row's mode.
    fn validation(&self, policy: Policy) -> (Mode, LockstepTiming) {
        if matches!(policy, Policy::PiR2ZeroDelay | Policy::PiR2ZeroDelayFull) {
            let r = self.settings().recipe;
            let mode = policy.deployments(&r).remove(0).mode;
            return (mode, LockstepTiming::zero_latency());
        }
        let mode = self.validation_mode(policy);
        let t = LockstepTiming::for_mode(&mode, self.settings().val_d0);
        (mode, t)
    }

    /// The successful episodes of the config's dataset.
    fn demonstrations(&self, _out: &Path) -> Result<Vec<Episode>> {
        let demos = load_demos(Path::new(&self.cfg.dataset))?;
        Ok(demos
            .iter()
            .map(|e| e.with_slow_frames(self.cfg.slow_frames))
            .collect())
    }

    fn title(&self, study: &str) -> String {
        format!(
            "Leap cube ({study} study): success (mean ± std over {} seeds)",
            self.cfg.seeds.len()
        )
    }
}

/// The U-Net `cfg` trains for `policy`: per-position FiLM (`cfg.pir2_film`) for the πR²
/// policies, the shared FiLM for the baselines.
fn unet(cfg: &LeapStudyConfig, policy: Policy) -> ModelConfig {
    let film = match policy {
        Policy::Rtc | Policy::Flow => FilmMode::Shared,
        _ => cfg.pir2_film,
    };
    ModelConfig::UNet(UNetConfig {
        widths: cfg.widths.clone(),
        groups: cfg.groups,
        tau_dim: 32,
        dvis_dim: 8,
        film,
        ..UNetConfig::default()
    })
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
/// training uses the successful ones. The MPC expert ([`MpcConfig::fast`] when `fast`) runs
/// with [`MpcConfig::pin_first_knot`] so the demonstrated actions are smooth; trained
/// weights act deterministically on the recorded observation. Episodes are written in
/// batches of up to 5; once `stop` is set (Ctrl-C) the batch in progress is finished and
/// written, and collection ends (resume with [`WriteMode::Resume`]).
pub fn collect_leap(
    out: &Path,
    seeds: &[u64],
    per_seed: usize,
    mode: WriteMode,
    expert: &ExpertChoice,
    stop: &std::sync::atomic::AtomicBool,
) -> Result<DatasetSummary> {
    let model = load_model()?;
    let mut policies = match expert {
        ExpertChoice::Mpc { .. } => Vec::new(),
        ExpertChoice::Weights(files) => {
            if files.len() != 1 && files.len() != seeds.len() {
                bail!(
                    "{} expert files for {} seeds: give one file, or one per seed",
                    files.len(),
                    seeds.len()
                );
            }
            files
                .iter()
                .map(|f| {
                    PpoExpert::load(f)
                        .with_context(|| format!("loading expert weights {}", f.display()))
                })
                .collect::<Result<Vec<_>>>()?
        }
    };
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
    let base = if matches!(expert, ExpertChoice::Mpc { fast: true }) {
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
    let t0 = Instant::now();
    while done < total {
        // Ctrl-C: the batch in progress was finished and written; stop here (`--resume`
        // continues).
        if stop.load(std::sync::atomic::Ordering::SeqCst) {
            log_line(&format!(
                "interrupted: {done}/{total} episodes written; `--resume` continues"
            ));
            break;
        }
        let (k, i) = (done / per_seed, done % per_seed);
        let end = (i + 5).min(per_seed);
        let eps = if policies.is_empty() {
            let cfg = CollectConfig {
                env: LeapConfig::paper(),
                mpc,
                seed: seeds[k],
            };
            pir2_sim::leap::collect(&model, &cfg, i..end, |_| pb.inc(1))?
        } else {
            let which = k.min(policies.len() - 1);
            pir2_sim::leap::collect_with(
                &model,
                LeapConfig::paper(),
                seeds[k],
                &mut policies[which],
                i..end,
                |_| pb.inc(1),
            )?
        };
        for ep in &eps {
            successes += ep.success as usize;
            w.append(&to_dataset_episode(ep))?;
        }
        done += eps.len();
        w.flush()?;
        pb.set_message(format!("collecting ({successes} successes)"));
        log_line(&format!(
            "collected {done}/{total} episodes ({successes} successes this session), {:.0} s",
            t0.elapsed().as_secs_f64()
        ));
    }
    pb.finish();
    Ok(w.finish()?)
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

/// Result of a Leap study.
pub type LeapStudyResult = StudyResult<LeapStudyConfig>;

/// Train `policies` × `cfg.seeds` (or only `seeds` of them) on the dataset `cfg.dataset` into
/// `out` (a new directory):
/// `out/<policy>-seed<s>/` holds the step checkpoints, `loss.jsonl`, `best.json` and the chosen
/// checkpoint `best/`. Point [`LeapStudyConfig::pretrained`] at `out` to evaluate them.
/// With `resume`, `out` is an earlier run of the same config ([`pipeline::train_into`]).
pub fn train_policies(
    cfg: &LeapStudyConfig,
    policies: &[Policy],
    seeds: Option<&[u64]>,
    out: &Path,
    resume: bool,
) -> Result<Vec<(Policy, u64, Scores)>> {
    if let Some(p) = policies.iter().find(|p| !ALL_POLICIES.contains(p)) {
        bail!("policy {p:?} is not part of the leap-cube study ({ALL_POLICIES:?})");
    }
    let task = LeapCubeTask::new(LeapStudyConfig {
        pretrained: None,
        ..cfg.clone()
    })?;
    pipeline::train_into(&task, policies, seeds, out, resume)
}

/// Deployment study: every row × `d0s` × seeds through the lock-step runtime with
/// `LockstepTiming::for_mode` (h = d, slow features delayed by d_vis). Writes
/// `result.json`, `table.md`, `success.png` into `out` (a new directory, or with `resume`
/// an interrupted evaluation of the same config, whose measured cells are reused).
pub fn study_deployment(
    cfg: &LeapStudyConfig,
    out: &Path,
    resume: bool,
) -> Result<LeapStudyResult> {
    let task = LeapCubeTask::new(cfg.clone())?;
    pipeline::run(&task, &task.deployment_study(), out, resume)
}

/// Horizon study ([`LeapCubeTask::horizon_study`]) into `out` (as [`study_deployment`]).
pub fn study_horizon(cfg: &LeapStudyConfig, out: &Path, resume: bool) -> Result<LeapStudyResult> {
    let task = LeapCubeTask::new(cfg.clone())?;
    let study = task.horizon_study();
    pipeline::run(&task, &study, out, resume)
}

#[cfg(test)]
mod tests {
    use super::LeapStudyConfig;
    use crate::study::evaluate::config_fingerprint;

    #[test]
    fn the_step_count_is_read_as_steps_or_train_steps_under_one_fingerprint() {
        let new: LeapStudyConfig = toml::from_str("steps = 20000").unwrap();
        let old: LeapStudyConfig = toml::from_str("train_steps = 20000").unwrap();
        assert_eq!(new, old);
        assert_eq!(new.steps, 20000);
        assert_eq!(
            config_fingerprint(&new).unwrap(),
            config_fingerprint(&old).unwrap()
        );
        let text = toml::to_string(&new).unwrap();
        assert!(text.contains("train_steps = 20000"), "{text}");
    }
}
