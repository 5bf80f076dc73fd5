//! Studies: a task trained and evaluated under latency by one pipeline.
//!
//! A [`Task`] supplies what differs between tasks — its environment, the model spec and
//! architecture, the optimiser settings, the rows of its table (policy + deployment mode)
//! and its demonstrations. [`pipeline`] does the rest the same way for every task:
//! demonstrations → train each `(policy, seed)` with closed-loop checkpoint validation →
//! evaluate every row × seed × column through the lock-step runtime → `result.json`,
//! `table.md`, `success.png`.
//!
//! [`report`] rebuilds a study's tables from its cell log alone (`pir2 report`), without the
//! checkpoints and without simulating anything.
//!
//! Shipped tasks: [`ballplate`] (the embedded default, `pir2 demo`) and, with feature
//! `mujoco`, `leap_cube`. A new task is one file: a type implementing [`Task`] (plus its
//! environment, an [`Environment`] of the runtime).
//!
//! A user's own dataset without an environment is the [`dataset`] task (`pir2 train --data
//! DATASET --task task.toml`): the same trainer and checkpoint layout, validated on held-out
//! episodes by the flow loss and the [`open_loop`] action error instead of in closed loop.

pub mod ballplate;
pub mod cells;
pub mod closed_loop;
pub mod dataset;
pub mod evaluate;
pub mod gr00t;
#[cfg(feature = "mujoco")]
pub mod leap_cube;
pub mod open_loop;
pub mod output;
pub mod pipeline;
pub mod report;

use std::path::{Path, PathBuf};

use anyhow::Result;
use serde::{Deserialize, Serialize};

use pir2_backends::config::{ModelConfig, Spec};
use pir2_backends::train::TrainConfig;
use pir2_runtime::{Environment, LockstepTiming, Mode};
use pir2_sim::dataset::Episode;

pub use cells::{mean_std, table, to_series, Cell};
pub use pir2_runtime::{Deployment as Row, Policy, Recipe};

/// The settings every study shares, read from a task's config.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// `n` of the πR² policies, Euler steps of the baselines, sync-flow `h`, ensembling decay.
    pub recipe: Recipe,
    /// Training/evaluation seeds (each trains its own policies, evaluates its own episodes).
    pub seeds: Vec<u64>,
    /// Evaluation episodes per cell.
    pub episodes: usize,
    /// Checkpoints validated in closed loop per training run (evenly spaced, last at the end).
    pub checkpoints: usize,
    /// Closed-loop validation episodes per checkpoint.
    pub val_episodes: usize,
    /// Unit delay of the closed-loop checkpoint validation.
    pub val_d0: usize,
    /// Worker threads (training jobs, evaluation episodes).
    pub threads: usize,
    /// Evaluation episodes run side by side with batched model calls (1: batch-1 calls on
    /// `threads` threads; see [`pipeline::closed_loop`]).
    pub batch_episodes: usize,
    /// Directory of trained policies (`<policy>-seed<s>/best`) loaded instead of trained.
    pub pretrained: Option<PathBuf>,
    /// With `pretrained`: train the policies missing there instead of refusing them
    /// ([`pipeline::train_all`]).
    pub train_missing: bool,
    /// A checkpoint whose validation score ties the best so far replaces it (the later step
    /// wins); `false` keeps the first.
    pub later_ties: bool,
    /// Also report the best checkpoint per cell over the chosen checkpoint and the last
    /// `best_of_last` other step checkpoints of each run (0: off).
    pub best_of_last: usize,
}

impl Settings {
    /// The settings of a task config: πR² at `nfe`, the baselines at `flow_steps` Euler
    /// steps (other recipe knobs at their defaults), checkpoints validated at unit delay 2,
    /// nothing pretrained, ties of validation scores keep the earlier checkpoint.
    pub fn from_config(
        nfe: usize,
        flow_steps: usize,
        seeds: &[u64],
        episodes: usize,
        checkpoints: usize,
        val_episodes: usize,
        threads: usize,
    ) -> Self {
        Settings {
            recipe: Recipe {
                nfe,
                flow_steps,
                ..Recipe::default()
            },
            seeds: seeds.to_vec(),
            episodes,
            checkpoints,
            val_episodes,
            val_d0: 2,
            threads,
            batch_episodes: 1,
            pretrained: None,
            train_missing: false,
            later_ties: false,
            best_of_last: 0,
        }
    }
}

/// A task: what the pipeline needs to collect, train and evaluate policies on it.
pub trait Task: Sync {
    /// The environment the lock-step runtime steps.
    type Env: Environment;
    /// The task's TOML config, written into results (and read back by `--resume`).
    type Config: Serialize + serde::de::DeserializeOwned + PartialEq + Clone;

    /// The config.
    fn config(&self) -> &Self::Config;
    /// The settings every study shares.
    fn settings(&self) -> Settings;
    /// The model's interface (horizon, dims, `n_obs`, slow input, `d_vis_max`).
    fn spec(&self) -> Spec;
    /// Control period in nanoseconds.
    fn period_ns(&self) -> u64;
    /// A fresh environment (one per evaluation thread).
    fn make_env(&self) -> Result<Self::Env>;
    /// The architecture trained for `policy`.
    fn model(&self, policy: Policy) -> ModelConfig;
    /// Optimiser settings (steps, batch, learning rate and its schedule, ...). The pipeline
    /// sets the seed, the training schedule ([`Policy::schedule`]) and the checkpoint spacing.
    fn optimiser(&self) -> TrainConfig;
    /// The deployment rows of the task's table, in table order.
    fn rows(&self) -> Vec<Row>;
    /// The mode a checkpoint of `policy` is validated in (default: its first row's).
    fn validation_mode(&self, policy: Policy) -> Mode {
        self.rows()
            .into_iter()
            .find(|r| r.policy == policy)
            .map(|r| r.mode)
            .unwrap_or_else(|| panic!("{policy:?} has no row in this task"))
    }
    /// The mode and timing a checkpoint of `policy` is validated in (default:
    /// [`validation_mode`](Self::validation_mode) at the settings' unit delay `val_d0`).
    fn validation(&self, policy: Policy) -> (Mode, LockstepTiming) {
        let mode = self.validation_mode(policy);
        let t = LockstepTiming::for_mode(&mode, self.settings().val_d0);
        (mode, t)
    }
    /// The demonstrations to train on; `out` is the study's output directory (a task that
    /// collects them writes its dataset there).
    fn demonstrations(&self, out: &Path) -> Result<Vec<Episode>>;
    /// Plot title of `study` (`deployment`, `horizon`, ...).
    fn title(&self, study: &str) -> String;
    /// Fingerprints of other configs whose cells of `policy` are this config's: configs
    /// that differ from it only in settings `policy`'s training and evaluation do not read
    /// (the Leap task: the πR² U-Nets' FiLM, for the baselines). A report takes `policy`'s
    /// cells logged under them (`pir2 report`). Default: none.
    fn equivalent_fingerprints(&self, _policy: Policy) -> Result<Vec<String>> {
        Ok(Vec::new())
    }
}

/// How a row's cells are run across the study's columns.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Sweep {
    /// Columns are unit delays `d0`: the row's mode with the paper's timing at `d0`.
    UnitDelay,
    /// Columns are execution horizons `h` of a sync-flow row, at zero latency.
    Horizon,
    /// Columns are unit delays `d0` of a sync-flow row with the paper's timing at `d0` and the
    /// execution horizon `h = d` (the paper's "h = d for all methods"); the robot holds its
    /// last action while a call runs.
    UnitDelaySync,
    /// One evaluation per seed with this timing, repeated in every column.
    Once(LockstepTiming),
}

/// One row of a study: a deployment and how it sweeps the columns.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyRow {
    /// Policy, mode and label.
    pub row: Row,
    /// How its cells are run.
    pub sweep: Sweep,
}

/// A study: rows × seeds × columns.
#[derive(Debug, Clone, PartialEq)]
pub struct Study {
    /// Name (`deployment`, `horizon`).
    pub name: String,
    /// Column key in the table (`d0`, `h`).
    pub key: String,
    /// Plot x-axis label.
    pub x_label: String,
    /// Column values.
    pub columns: Vec<usize>,
    /// Rows in table order.
    pub rows: Vec<StudyRow>,
    /// Evaluation episodes of seed `s` are seeded from `seed_base + s`.
    pub seed_base: u64,
}

impl Study {
    /// The deployment study: every row at every unit delay of `d0s`.
    pub fn deployment(rows: Vec<Row>, d0s: &[usize]) -> Self {
        Study {
            name: "deployment".into(),
            key: "d0".into(),
            x_label: "unit delay d0 (ticks)".into(),
            columns: d0s.to_vec(),
            rows: rows
                .into_iter()
                .map(|row| StudyRow {
                    row,
                    sweep: Sweep::UnitDelay,
                })
                .collect(),
            seed_base: 2_000_000,
        }
    }

    /// The policies the rows deploy, in [`Policy::ALL`] order.
    pub fn policies(&self) -> Vec<Policy> {
        Policy::ALL
            .into_iter()
            .filter(|p| self.rows.iter().any(|r| r.row.policy == *p))
            .collect()
    }
}

/// Closed-loop validation scores of one training run: `(step, success rate)`.
pub type Scores = Vec<(usize, f64)>;

/// The result file of a study (`result.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StudyResult<C> {
    /// Study name (`deployment`, `horizon`).
    pub study: String,
    /// Config used.
    pub config: C,
    /// Demonstrations trained on.
    pub demos: usize,
    /// Row labels in table order.
    pub labels: Vec<String>,
    /// Column key (`d0`, `h`).
    pub key: String,
    /// Column values.
    pub columns: Vec<usize>,
    /// All cells (`d0` holds the column value).
    pub cells: Vec<Cell>,
    /// How many step checkpoints besides the chosen one each best-per-cell cell considered
    /// (0: not measured).
    #[serde(default)]
    pub best_of_last: usize,
    /// The cells under the paper's optimistic protocol, the best checkpoint per row × column ×
    /// seed (empty when not measured).
    #[serde(default)]
    pub best_per_cell: Vec<Cell>,
    /// Closed-loop validation scores per (policy, seed).
    pub validation: Vec<(Policy, u64, Scores)>,
    /// Wall time of each stage, seconds.
    pub timings: Vec<(String, f64)>,
}

impl<C> StudyResult<C> {
    /// The Markdown table (columns named by the study's key).
    /// With best-per-cell cells, a second, labelled table follows.
    pub fn table(&self) -> String {
        let mut t = cells::table_keyed(&self.cells, &self.labels, &self.columns, &self.key);
        if !self.best_per_cell.is_empty() {
            t += &format!(
                "\nBest checkpoint per cell (the paper's protocol; optimistic: per seed, the best of \
                 the chosen checkpoint and the last {} other step checkpoints, selected on the \
                 evaluation episodes):\n\n",
                self.best_of_last
            );
            t += &cells::table_keyed(&self.best_per_cell, &self.labels, &self.columns, &self.key);
        }
        t
    }
}
