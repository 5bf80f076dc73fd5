//! `pir2 collect|train|eval|report TASK`: the stock tasks by name, from one registry
//! ([`TASKS`]), and the options of those commands.
//!
//! A stock task is a type implementing [`TaskCommands`] in a file of this module and one
//! [`Entry`] in [`TASKS`]. A task a build lacks (the Leap cube without feature `mujoco`)
//! keeps its entry with the error that says how to build it, so the commands accept the
//! same names in every build. A user's own dataset (`pir2 train --task task.toml`) is the
//! [`dataset`] task, chosen by its task file instead of a name.

pub mod ballplate;
pub mod dataset;
#[cfg(feature = "mujoco")]
pub mod leap_cube;

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;

use anyhow::{anyhow, Result};
use clap::builder::{PossibleValuesParser, TypedValueParser};

use pir2_runtime::Policy;
use pir2_sim::dataset::WriteMode;

use crate::remote::TlsOptions;

/// What `pir2 collect|train|eval|report` do for one stock task.
pub trait TaskCommands: Sync {
    /// `pir2 collect TASK`: expert demonstrations into a LeRobotDataset v3.0 directory;
    /// `stop` (Ctrl-C) ends it after the episode in progress, keeping what was written.
    fn collect(&self, o: &CollectOptions, stop: &AtomicBool) -> Result<()>;
    /// `pir2 train TASK`: train the task's policy (or policies) on a dataset.
    fn train(&self, o: &TrainOptions) -> Result<()>;
    /// `pir2 eval TASK`: evaluate a checkpoint, or run the task's study.
    fn eval(&self, o: &EvalOptions) -> Result<()>;
    /// `pir2 report TASK`: a study's tables from its cell log (only tasks whose
    /// [`Entry::reports`] is set are offered).
    fn report(&self, o: &ReportOptions) -> Result<()>;
}

/// One stock task of the registry.
#[derive(Clone, Copy)]
pub struct Entry {
    /// Its name on the command line.
    pub name: &'static str,
    /// Whether `pir2 report` rebuilds its tables (its evaluation keeps a cell log).
    pub reports: bool,
    /// Its commands, or in a build without them the error that says how to build them.
    pub commands: Result<&'static dyn TaskCommands, &'static str>,
}

impl std::fmt::Debug for Entry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Entry")
            .field("name", &self.name)
            .field("reports", &self.reports)
            .field("built", &self.commands.is_ok())
            .finish()
    }
}

/// The error every `leap-cube` command gives in a build without the `mujoco` feature.
pub const NEEDS_MUJOCO: &str = "the leap-cube task needs MuJoCo: build with `--features mujoco` \
     (cargo run --release -p pir2-cli --features mujoco -- ...; run `bash scripts/setup-native.sh` \
     and `source .native/env.sh` first)";

#[cfg(feature = "mujoco")]
const LEAP_CUBE: Result<&'static dyn TaskCommands, &'static str> = Ok(&leap_cube::LeapCube);
#[cfg(not(feature = "mujoco"))]
const LEAP_CUBE: Result<&'static dyn TaskCommands, &'static str> = Err(NEEDS_MUJOCO);

/// The stock tasks, in the order the commands list them.
pub static TASKS: [Entry; 2] = [
    Entry {
        name: "ballplate",
        reports: false,
        commands: Ok(&ballplate::BallPlate),
    },
    Entry {
        name: "leap-cube",
        reports: true,
        commands: LEAP_CUBE,
    },
];

/// The commands of the task called `name` (an error for a task this build lacks).
pub fn task(name: &str) -> Result<&'static dyn TaskCommands> {
    let e = TASKS
        .iter()
        .find(|e| e.name == name)
        .ok_or_else(|| anyhow!("unknown task {name}"))?;
    e.commands.map_err(|msg| anyhow!(msg))
}

/// The names of the stock tasks, for the commands' argument parser.
fn task_names() -> PossibleValuesParser {
    PossibleValuesParser::new(TASKS.iter().map(|e| e.name))
}

/// The names of the tasks `pir2 report` knows.
fn reporting_task_names() -> PossibleValuesParser {
    PossibleValuesParser::new(TASKS.iter().filter(|e| e.reports).map(|e| e.name))
}

/// `--policy`: the policies by their command-line names.
pub(crate) fn policy_parser() -> impl TypedValueParser<Value = Policy> {
    PossibleValuesParser::new(BALLPLATE_POLICIES.map(Policy::name)).map(|s| {
        *BALLPLATE_POLICIES
            .iter()
            .find(|p| p.name() == s)
            .expect("a possible value")
    })
}

/// The policies of the ball-plate task (and of a candle checkpoint's `--policy`).
pub(crate) const BALLPLATE_POLICIES: [Policy; 5] = [
    Policy::PiR2,
    Policy::PiR2Hidden,
    Policy::PiR2Full,
    Policy::Rtc,
    Policy::Flow,
];

/// `pir2 train --policy`: a policy by its name ([`Policy::name`]: `pir2-full`,
/// `pir2-zero-delay-full`, ...) or by its name in study configs (`pi_r2_zero_delay_full`, ...).
pub(crate) fn train_policy(s: &str) -> std::result::Result<Policy, String> {
    if let Some(p) = Policy::ALL.iter().find(|p| p.name() == s) {
        return Ok(*p);
    }
    config_policy(s).map_err(|e| {
        let names: Vec<&str> = Policy::ALL.iter().map(|p| p.name()).collect();
        format!("{e}; or {}", names.join(", "))
    })
}

/// A policy by its name in study configs (`policies = [...]`: `flow`, `rtc`, `pi_r2`,
/// `pi_r2_full`, ...).
pub(crate) fn config_policy(s: &str) -> std::result::Result<Policy, String> {
    serde_json::from_value(serde_json::Value::String(s.to_string())).map_err(|_| {
        let names: Vec<String> = Policy::ALL
            .iter()
            .filter_map(|p| serde_json::to_value(p).ok()?.as_str().map(str::to_string))
            .collect();
        format!("unknown policy `{s}` (one of {})", names.join(", "))
    })
}

/// `pir2 collect`.
#[derive(Debug, Clone, clap::Args)]
pub struct CollectOptions {
    /// The task (leap-cube needs a build with `--features mujoco`).
    #[arg(value_parser = task_names(), default_value = "ballplate")]
    pub task: String,
    /// Dataset directory.
    #[arg(long)]
    pub out: PathBuf,
    /// leap-cube: expert seeds (episodes are stored seed-major).
    #[arg(long, value_delimiter = ',', default_value = "0,1,2,3")]
    pub seeds: Vec<u64>,
    /// leap-cube: episodes per expert seed.
    #[arg(long, default_value_t = 50)]
    pub per_seed: usize,
    /// leap-cube: the faster, weaker MPC expert.
    #[arg(long, conflicts_with = "expert")]
    pub fast: bool,
    /// leap-cube: demonstrate with trained policy weights (`pir2-ppo-expert-v1`
    /// safetensors, e.g. from `leap_ppo` or `scripts/playground-expert.py`) instead of
    /// the MPC: one file for all seeds, or one per seed (in the order of `--seeds`).
    #[arg(long, value_delimiter = ',')]
    pub expert: Vec<PathBuf>,
    /// Episodes to keep.
    #[arg(long, default_value_t = 200)]
    pub episodes: usize,
    /// Seed.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Append the missing episodes to an existing dataset.
    #[arg(long, conflicts_with = "overwrite")]
    pub resume: bool,
    /// Replace an existing dataset.
    #[arg(long)]
    pub overwrite: bool,
}

impl CollectOptions {
    /// New, resume or overwrite, as `--resume` / `--overwrite` say.
    pub fn write_mode(&self) -> WriteMode {
        if self.resume {
            WriteMode::Resume
        } else if self.overwrite {
            WriteMode::Overwrite
        } else {
            WriteMode::New
        }
    }
}

/// `pir2 train`.
#[derive(Debug, Clone, clap::Args)]
pub struct TrainOptions {
    /// The stock task (default ballplate; leap-cube needs a build with `--features mujoco`).
    #[arg(value_parser = task_names(), conflicts_with = "task_file")]
    pub task: Option<String>,
    /// A task file (task.toml: fast/slow/action keys, horizon, n_obs, policy, model,
    /// optimiser, held-out episodes) for a user's own dataset.
    #[arg(long = "task", value_name = "TASK_TOML")]
    pub task_file: Option<PathBuf>,
    /// Dataset directory (LeRobotDataset v3.0).
    #[arg(long)]
    pub data: PathBuf,
    /// Which policy: pir2, pir2-hidden, pir2-full, rtc, flow, pir2-zero-delay or
    /// pir2-zero-delay-full (or its name in study configs, e.g. pi_r2_zero_delay_full).
    /// Required for ballplate (the first five); leap-cube: the config's `policies` when absent.
    #[arg(long, value_parser = train_policy)]
    pub policy: Option<Policy>,
    /// Checkpoint directory (must not exist, unless --resume).
    #[arg(long)]
    pub out: PathBuf,
    /// TOML config (ballplate: fields of `DemoConfig`: steps, lr, nfe, ...; leap-cube:
    /// `LeapStudyConfig`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Seed (ballplate; leap-cube trains the config's seeds).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// leap-cube: train only these of the config's seeds (default: all of them). Like
    /// --policy, it narrows which runs this command trains without changing the run's config,
    /// so a long study can go one run at a time and resume run by run; a seed the config
    /// does not list is refused.
    #[arg(long, value_delimiter = ',')]
    pub seeds: Option<Vec<u64>>,
    /// Continue an interrupted `pir2 train … --out DIR` (SIGINT / SIGTERM save the training
    /// state and name it) with the same config and data (leap-cube: checked against
    /// `DIR/config.toml` and `DIR/data.json`; ballplate: the policy, seed and config against
    /// `DIR/train.toml` and the data against `DIR/data.json`; --task: the task file against
    /// `DIR/task.toml`): finished policies are kept, unfinished ones continue from their last
    /// step checkpoint or interrupted state (bit-identically to an uninterrupted run on the
    /// same kind of CPU).
    #[arg(long)]
    pub resume: bool,
}

/// `pir2 eval`.
#[derive(Debug, Clone, clap::Args)]
pub struct EvalOptions {
    /// The task (leap-cube needs a build with `--features mujoco`).
    #[arg(value_parser = task_names(), default_value = "ballplate")]
    pub task: String,
    /// Checkpoint directory (leap-cube: the output of `pir2 train leap-cube`; a listed
    /// policy × seed without a `best/` there is an error, unless --train-missing).
    /// ballplate: a candle checkpoint (config.json, stats.json, model.safetensors), or an
    /// ONNX checkpoint (model.onnx, stats.json, identity.json; e.g. trained in PyTorch, see
    /// examples/lerobot-flow) run through ONNX Runtime (a build with `--features ort`).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// leap-cube: train the listed policies missing from --checkpoint (into --out) instead
    /// of refusing them.
    #[arg(long)]
    pub train_missing: bool,
    /// Which policy the checkpoint is (ballplate).
    #[arg(long, value_parser = policy_parser())]
    pub policy: Option<Policy>,
    /// leap-cube: evaluate only these policies (comma-separated; default: the config's
    /// `policies`), e.g. the πR² rows of a study whose baselines' cells are in another log
    /// (`pir2 report` takes several). What is evaluated is not part of a cell's key, so
    /// the cells are the same as with the whole list.
    #[arg(long, value_parser = config_policy, value_delimiter = ',')]
    pub policies: Vec<Policy>,
    /// leap-cube: evaluate only these of the config's seeds (comma-separated; default: all),
    /// e.g. a one-seed table while the other seeds train. The seeds evaluated are not part
    /// of a cell's key either, so `--resume` with more seeds later measures only the new
    /// cells; a seed the config does not list is refused.
    #[arg(long, value_delimiter = ',')]
    pub seeds: Option<Vec<u64>>,
    /// leap-cube: how many other step checkpoints of each run the best-checkpoint-per-cell
    /// protocol takes (default: the config's `best_of_last`). 0 measures only the chosen
    /// checkpoints' cells, e.g. of a run restored from its saved state, which has no step
    /// checkpoints (with more, such a run is refused by name). Not part of a cell's key.
    #[arg(long)]
    pub best_of_last: Option<usize>,
    /// leap-cube: which study.
    #[arg(long, value_parser = ["deployment", "horizon"], default_value = "deployment")]
    pub study: String,
    /// leap-cube: TOML config (fields of `LeapStudyConfig`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// leap-cube: dataset directory (overrides the config's).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// leap-cube: output directory (must not exist or be empty, unless --resume).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// leap-cube: continue an interrupted evaluation in --out with the same config: the
    /// cells in its `cells.jsonl` are reused, the rest are measured (the config's seed
    /// list may grow, e.g. from a one-seed table to three seeds). SIGINT or SIGTERM ends an
    /// evaluation after the cell being measured (a second signal at once); every finished
    /// cell is in the log.
    #[arg(long)]
    pub resume: bool,
    /// Unit delays.
    #[arg(long, value_delimiter = ',', default_value = "1,2,3")]
    pub d0: Vec<usize>,
    /// Episodes per cell (default 100; leap-cube: the config's).
    #[arg(long)]
    pub episodes: Option<usize>,
    /// Seed of the evaluation episodes.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write the cells as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Send the action-head calls to `pir2 serve policy` at this Zenoh endpoint
    /// (e.g. `tcp/10.0.0.2:7447`; feature `remote`). The server must run the same
    /// checkpoint (a server announcing another policy or other weights is refused); locally
    /// only its normalisation is used.
    #[arg(long)]
    pub remote: Option<String>,
    /// With --remote: ms a request may take before it is sent again.
    #[arg(long, default_value_t = 200)]
    pub remote_timeout_ms: u64,
    /// With --remote: consecutive timeouts before the evaluation stops.
    #[arg(long, default_value_t = 25)]
    pub remote_max_failed: u32,
    /// With --remote: seconds to wait for the server at start.
    #[arg(long, default_value_t = 5.0)]
    pub connect_timeout: f64,
    /// With --remote: mutual TLS for a `tls/…` endpoint.
    #[command(flatten)]
    pub tls: TlsOptions,
}

/// `pir2 report`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReportOptions {
    /// The task (leap-cube needs a build with `--features mujoco`).
    #[arg(value_parser = reporting_task_names())]
    pub task: String,
    /// Which study.
    #[arg(long, value_parser = ["deployment", "horizon"], default_value = "deployment")]
    pub study: String,
    /// TOML config (fields of `LeapStudyConfig`): the rows, seeds and columns to report,
    /// and the settings the cells were measured with.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Dataset directory (overrides the config's): the one the evaluation was given, since
    /// the config's fingerprint, under which the cells are logged, includes it.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// The cell log; repeat to take several logs together (e.g. a study's own log and the
    /// log its baselines were measured in: a baseline's cells count under every config
    /// that trains and evaluates it the same way).
    #[arg(long, required = true)]
    pub cells: Vec<PathBuf>,
    /// Also write `report.json`, `table.md` and the plots here (must not exist or be
    /// empty).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Report what the log holds when cells are missing (listed), instead of refusing.
    #[arg(long)]
    pub partial: bool,
}

/// `e` with, when it is an interrupted training (SIGINT / SIGTERM, the training state saved),
/// the command that continues it (`resume`) in front; any other error as it is.
pub(crate) fn with_resume_hint(e: anyhow::Error, resume: &str) -> anyhow::Error {
    let interrupted = e.chain().any(|c| {
        matches!(
            c.downcast_ref::<pir2_backends::Error>(),
            Some(pir2_backends::Error::Interrupted { .. })
        )
    });
    if interrupted {
        e.context(format!("interrupted: `{resume}` continues the run"))
    } else {
        e
    }
}

/// Say where a resumed collection moved the data files of an interrupted write.
fn report_set_aside(s: &pir2_sim::dataset::DatasetSummary) {
    for p in &s.set_aside {
        println!(
            "moved {} aside: a data file of a write that was killed before its metadata (its \
             episodes are collected again)",
            p.display()
        );
    }
}

/// `pir2 collect`: the task's expert demonstrations.
pub fn collect(o: &CollectOptions, stop: &AtomicBool) -> Result<()> {
    task(&o.task)?.collect(o, stop)
}

/// `pir2 train`: a stock task's policies, or with `--task FILE` the [`dataset`] task.
pub fn train(o: &TrainOptions) -> Result<()> {
    match &o.task_file {
        Some(file) => dataset::train(o, file),
        None => task(o.task.as_deref().unwrap_or("ballplate"))?.train(o),
    }
}

/// `pir2 eval`: a checkpoint or a study of the task.
pub fn eval(o: &EvalOptions) -> Result<()> {
    task(&o.task)?.eval(o)
}

/// `pir2 report`: a study's tables from its cell log.
pub fn report(o: &ReportOptions) -> Result<()> {
    task(&o.task)?.report(o)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn train_takes_every_policy_by_either_name_and_lists_them_when_wrong() {
        for p in Policy::ALL {
            assert_eq!(train_policy(p.name()), Ok(p));
        }
        assert_eq!(
            train_policy("pi_r2_zero_delay_full"),
            Ok(Policy::PiR2ZeroDelayFull)
        );
        let e = train_policy("pir2-fast").unwrap_err();
        assert!(
            e.contains("`pir2-fast`")
                && e.contains("pi_r2_full")
                && e.contains("pir2-zero-delay-full"),
            "{e}"
        );
    }

    #[test]
    fn config_policy_names_are_the_study_configs() {
        assert_eq!(
            config_policy("pi_r2_zero_delay_full"),
            Ok(Policy::PiR2ZeroDelayFull)
        );
        assert_eq!(config_policy("flow"), Ok(Policy::Flow));
        let e = config_policy("pir2-full").unwrap_err();
        assert!(e.contains("pi_r2_full") && e.contains("`pir2-full`"), "{e}");
    }
}
